"""`copy_context_text`: one context table's text in the prompt, copied verbatim as the answer, scored as a VLM's."""

from __future__ import annotations

import json

import pytest
from conftest import make_small_dataset

from degusta_learn.baselines.copy_context_text import CopyContextTextConfig, run_copy_context_text
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import Arrangement, Dataset, Episode, Placement, default_catalog, default_tables, make_episodes
from degusta_learn.task.aggregate import combine
from degusta_learn.task.answers import read_answer
from degusta_learn.task.prompt import build_prompt

G = Grid(8, 8)
C = (3 + 0.5) / 8  # the centre of column D (and of row 4): 0.4375


def _hand_made() -> tuple[Dataset, Episode]:
    """p000: trial 0 a plate on table 1, trial 1 two cups and a fork on table 2, the target trial 2 on table 1."""
    tables = {t.id: t for t in default_tables()}
    arrangements = [
        Arrangement("p000", 0, 1, (Placement(75, C, C, 0.0),)),
        Arrangement("p000", 1, 2, (Placement(0, C, C, 0.0),            # a cup on D4's centre: D4 alone
                                   Placement(1, 0.5, C, 100.0),        # a cup on the D4 | E4 border, turned 100 deg
                                   Placement(25, C, 0.6875, 100.0))),  # a fork across C6, D6, E6, turned 100 deg
        Arrangement("p000", 2, 1, (Placement(76, 0.3, 0.3, 0.0),)),
    ]
    ds = Dataset(default_catalog(), tables, arrangements, meta={"name": "hand-made", "synthetic": True})
    return ds, Episode("p000/t2/k2", "p000", (0, 1), 2, "reconstruction")


def _predict(ds, episodes, **keys):
    cfg = CopyContextTextConfig(method="copy_context_text", dataset="unused", out="unused", context=None,
                                episodes="unused", **keys)
    return run_copy_context_text(cfg, ds, episodes)


def test_the_last_context_is_copied_as_written_and_decoded_as_a_vlm_answer():
    ds, ep = _hand_made()
    (pred,) = _predict(ds, [ep])
    assert pred.diagnostics["response"] == (
        "[{'type': 'cup', 'id': 0, 'position': ['D4'], 'cardinal_direction': 'N'}, "
        "{'type': 'cup', 'id': 1, 'position': ['D4', 'E4'], 'cardinal_direction': 'E'}, "
        "{'type': 'fork', 'id': 25, 'position': ['C6', 'D6', 'E6'], 'cardinal_direction': 'E'}]")
    assert (pred.diagnostics["copied"], pred.diagnostics["source_trial"], pred.failed) == ("final_state_2", 1, False)
    # each object at the centre of the cells written for it, turned to the direction written (100 deg -> E = 90):
    # where it stood on the context's table, not carried onto the target's
    got = [(p.object, p.x, p.y, p.rotation) for p in pred.placements]
    assert got == [(0, C, C, 0.0), (1, 0.5, C, 90.0), (25, pytest.approx(C), 0.6875, 90.0)]


def test_nearest_copies_the_context_on_the_targets_table():
    ds, ep = _hand_made()
    (pred,) = _predict(ds, [ep], source="nearest")
    assert (pred.diagnostics["copied"], pred.diagnostics["source_trial"]) == ("final_state_1", 0)
    assert [(p.object, p.x, p.y, p.rotation) for p in pred.placements] == [(75, C, C, 0.0)]  # C3..E5: centre D4


def test_unmarked_text_copies_rounded_positions_and_whole_degrees():
    ds, ep = _hand_made()
    ds.arrangements[1] = Arrangement("p000", 1, 2, (Placement(0, 0.12345, 0.6789, 359.6),))
    ds = Dataset(ds.catalog, ds.tables, ds.arrangements, meta=ds.meta)
    (pred,) = _predict(ds, [ep], prompt_method="mouma")
    assert pred.diagnostics["response"] == "[{'type': 'cup', 'id': 0, 'position': [0.123, 0.679], 'rotation': 0}]"
    assert [(p.object, p.x, p.y, p.rotation) for p in pred.placements] == [(0, 0.123, 0.679, 0.0)]


@pytest.mark.parametrize("method", ["mogma", "louma"])
def test_it_is_the_prompts_own_text_parsed_as_the_runner_parses_an_answer(method):
    ds = make_small_dataset(n_participants=4)
    episodes = make_episodes(ds, 4, "all", 0)[:6]
    renderer = Renderer.for_dataset(ds, size=64)
    preds = _predict(ds, episodes, prompt_method=method)
    kind = "grid" if method == "mogma" else "unmarked"
    for ep, pred in zip(episodes, preds):
        prompt = build_prompt(method, ds, ep, renderer, G, modality="text")
        last = [t for t in prompt.parts if isinstance(t, str) and t.startswith("The objects in final_state_4.jpg")]
        text = last[0].split(", written as an answer: ", 1)[1]
        assert pred.diagnostics["response"] == text
        placements, _ = combine([read_answer(text, kind, ds.catalog, G).items], kind, G, "steps")
        assert pred.placements == placements
        assert [p.object for p in pred.placements] == list(ds.arrangement(ep.participant, ep.context[-1]).objects)


def test_it_scores_what_a_vlm_answering_that_text_scores(small_dataset_dir, tmp_path):
    """The zero-shot runner fed the copied text as every episode's answer (replay) writes the same placements."""
    from degusta_learn.config import load_config
    from degusta_learn.prompting.runner import ZeroShotConfig, run_zeroshot
    from degusta_learn.scene import load_dataset

    ds = load_dataset(small_dataset_dir)
    episodes = make_episodes(ds, 4, "test", 0)
    copied = _predict(ds, episodes)
    replay = tmp_path / "answers.jsonl"
    replay.write_text("".join(json.dumps({"episode": p.episode, "sample": 0, "text": p.diagnostics["response"]}) + "\n"
                              for p in copied))
    cfg = load_config(ZeroShotConfig, data={"method": "mogma", "dataset": str(small_dataset_dir), "context": 4,
                                            "out": str(tmp_path / "p.jsonl"), "render_size": 64, "cache": "off",
                                            "backend": {"name": "replay", "path": str(replay)}})
    answered = run_zeroshot(cfg, ds, episodes)
    assert [p.placements for p in answered] == [p.placements for p in copied]


def test_context_zero_falls_back_to_population_mean(small_dataset):
    (pred,) = _predict(small_dataset, make_episodes(small_dataset, 0, "test", 0)[:1])
    assert pred.diagnostics["fallback"] == "population_mean" and pred.placements


def test_the_shipped_config_runs(small_dataset_dir, tmp_path):
    from degusta_learn.cli import main
    from degusta_learn.scene import default_catalog, read_predictions

    out = tmp_path / "p.jsonl"
    assert main(["predict", "--config", "baseline_copy_context_text", "--set", f"dataset={small_dataset_dir}",
                 "--set", f"out={out}", "--set", "context=2", "--set", "split=val"]) == 0
    preds = read_predictions(out, default_catalog())
    assert preds and {p.method for p in preds} == {"copy_context_text"}
    assert {p.diagnostics["source"] for p in preds} == {"last"}
