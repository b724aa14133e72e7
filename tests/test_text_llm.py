"""`text_llm` without a server: its two prompts (the context as text, no image, the summary fed to step 2), a run
through the replay backend (a missing summary and a malformed answer are counted failures), the dry run, and bad
config keys refused in one line naming the key."""

from __future__ import annotations

import json

import pytest
import yaml
from conftest import make_small_dataset

from degusta_learn.cli import main as cli_main
from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.methods import get_method, run_predict
from degusta_learn.prompting.text_llm import TextLLMConfig
from degusta_learn.render.lifting import oal_text, order_text
from degusta_learn.scene import make_episodes, read_predictions, save_dataset
from degusta_learn.task.prompt import context_answer
from degusta_learn.task.text_llm_prompt import (
    NO_CONTEXT_LINE,
    SUMMARY_SUFFIX,
    SUMMARY_TASK,
    placement_prompt,
    summary_prompt,
    table_text,
)

SUMMARY = "I set one plate in the middle with the fork left of it; everything blue."


@pytest.fixture(scope="module")
def ds():
    return make_small_dataset(n_participants=3, n_trials=3)


@pytest.fixture(scope="module")
def data(ds, tmp_path_factory):
    return save_dataset(ds, tmp_path_factory.mktemp("ds") / "data")


def answer(ds, ep) -> str:
    """The target's own arrangement in the unmarked answer format (a perfect answer)."""
    return context_answer("louma", ds.arrangement(ep.participant, ep.target), ds.catalog, None)


def test_summary_prompt_writes_every_context_table_as_text_and_no_image(ds):
    ep = make_episodes(ds, 2, "all")[0]
    prompt = summary_prompt(ds, ep)
    text = prompt.text
    assert prompt.images == [] and all(isinstance(p, str) for p in prompt.parts)
    assert prompt.episode == ep.id + SUMMARY_SUFFIX and prompt.modality == "text"
    assert oal_text(ds.catalog) in text  # colours and materials of every id
    for k, trial in enumerate(ep.context, start=1):
        arr = ds.arrangement(ep.participant, trial)
        assert context_answer("louma", arr, ds.catalog, None) in text
        assert order_text(arr, ds.catalog, f"table setting {k}") in text
        assert f"Table setting {k}, on {table_text(ds.tables[arr.table])}:" in text
    assert text.endswith(SUMMARY_TASK)
    assert answer(ds, ep) not in text  # the held-out target never leaks into the prompt
    assert "final_state" not in text and "initial_state" not in text  # no image is named
    assert summary_prompt(ds, make_episodes(ds, 0, "all")[0]) is None  # context 0: nothing to summarise


def test_placement_prompt_gets_the_summary_and_the_target_table_not_the_context(ds):
    ep = make_episodes(ds, 2, "all")[0]
    prompt = placement_prompt(ds, ep, SUMMARY)
    text = prompt.text
    target = ds.tables[ds.arrangement(ep.participant, ep.target).table]
    assert prompt.images == [] and prompt.episode == ep.id
    assert SUMMARY in text and table_text(target) in text and oal_text(ds.catalog) in text
    assert "'position': [x, y], 'rotation': degrees" in text and "according to my preferences" in text
    for trial in ep.context:  # step 2 sees the summary only, as TidyBot's second prompt
        assert context_answer("louma", ds.arrangement(ep.participant, trial), ds.catalog, None) not in text
    assert answer(ds, ep) not in text
    blind = placement_prompt(ds, make_episodes(ds, 0, "all")[0], None).text
    assert NO_CONTEXT_LINE in blind and "summary" not in blind


def replay_config(tmp_path, data, answers, **extra) -> list[str]:
    return [f"dataset={data}", "method=text_llm", "context=2", "split=all", "decoding.n=2", "backend.name=replay",
            f"backend.path={answers}", f"out={tmp_path / 'run' / 'predictions.jsonl'}",
            *[f"{k}={v}" for k, v in extra.items()]]


def test_replay_runs_both_steps_and_counts_a_missing_summary_and_a_bad_answer(tmp_path, ds, data, capsys):
    episodes = make_episodes(ds, 2, "all")
    rows = []
    for j, ep in enumerate(episodes):
        if j != 0:  # episode 0 has no recorded summary
            rows.append({"episode": ep.id + SUMMARY_SUFFIX, "sample": 0, "text": f"  {SUMMARY} ({j})\n"})
        rows += [{"episode": ep.id, "sample": 0, "text": answer(ds, ep)},
                 {"episode": ep.id, "sample": 1, "text": "I would put a plate in the middle." if j == 1
                  else answer(ds, ep)}]
    path = tmp_path / "answers.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = run_predict(None, replay_config(tmp_path, data, path))
    preds = read_predictions(out, ds.catalog)
    assert len(preds) == len(episodes)
    missing, bad, *rest = preds
    assert missing.failed and missing.placements == [] and missing.diagnostics["summary"] is None
    why = missing.diagnostics["summary_failure"]
    assert why == "the backend returned no answer"  # what the runner says of an episode the file lacks
    assert [f["reason"] for f in missing.diagnostics["failures"]] == [f"no summary: {why}"] * 2
    assert not bad.failed and bad.diagnostics["n_parsed"] == 1  # one unparseable answer of two: counted
    assert bad.diagnostics["failures"][0]["reason"].startswith("unparseable answer: ")
    for j, p in enumerate([bad, *rest], start=1):
        ep = episodes[j]
        assert p.diagnostics["summary"] == f"{SUMMARY} ({j})" and p.diagnostics["summary_cached"] is False
        truth = ds.arrangement(ep.participant, ep.target).placements
        assert [q.object for q in p.placements] == [q.object for q in truth]
        d = p.diagnostics
        assert d["backend"] == "replay" and d["modality"] == "text" and d["split"] == "all"
        assert d["choices"]["method"] == "text_llm" and d["choices"]["modality"] == "text"
    ledger = json.loads((tmp_path / "run" / "ledger.json").read_text())
    assert ledger["cost_usd"] == 0 and ledger["method"] == "text_llm" and ledger["episodes_failed"] == 1
    assert ledger["steps"]["summary"]["samples_received"] == len(episodes) - 1
    assert ledger["steps"]["summary"]["episodes_failed"] == 1
    assert ledger["steps"]["placement"]["samples_received"] == 2 * (len(episodes) - 1)
    assert not (tmp_path / "run" / "responses_cache.sqlite").exists()  # replay: the file is the cache


def test_a_text_llm_predictions_file_replays_both_steps_as_recorded(tmp_path, ds, data):
    """A text_llm predictions.jsonl is itself a replay file: its summaries (diagnostics.summary) answer step 1 and
    its responses step 2, so the replayed run gives the same predictions and summaries; a summary recorded cut to
    SUMMARY_MAX_CHARS is given to step 2 unchanged (the cut is idempotent)."""
    from degusta_learn.prompting.text_llm import SUMMARY_MAX_CHARS

    episodes = make_episodes(ds, 2, "all")
    long = "x" * (SUMMARY_MAX_CHARS + 50)
    rows = []
    for j, ep in enumerate(episodes):
        rows.append({"episode": ep.id + SUMMARY_SUFFIX, "sample": 0, "text": long if j == 0 else f"{SUMMARY} ({j})"})
        rows += [{"episode": ep.id, "sample": i, "text": answer(ds, ep)} for i in range(2)]
    path = tmp_path / "answers.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    first = read_predictions(run_predict(None, replay_config(tmp_path, data, path)), ds.catalog)
    assert first[0].diagnostics["summary"] != long and len(first[0].diagnostics["summary"]) < len(long) + 80
    recorded = tmp_path / "first.jsonl"
    recorded.write_text((tmp_path / "run" / "predictions.jsonl").read_text())
    again = read_predictions(run_predict(None, replay_config(tmp_path, data, recorded)), ds.catalog)
    assert not any(p.failed for p in again)
    for a, b in zip(first, again):
        assert b.diagnostics["summary"] == a.diagnostics["summary"]
        assert [(q.object, q.x, q.y) for q in b.placements] == [(q.object, q.x, q.y) for q in a.placements]


def test_context_zero_skips_the_summary(tmp_path, ds, data):
    episodes = make_episodes(ds, 0, "all")
    path = tmp_path / "answers.jsonl"
    path.write_text("".join(json.dumps({"episode": ep.id, "sample": i, "text": answer(ds, ep)}) + "\n"
                            for ep in episodes for i in range(2)))
    out = run_predict(None, replay_config(tmp_path, data, path, context=0))
    preds = read_predictions(out, ds.catalog)
    assert not any(p.failed for p in preds)
    assert all(p.diagnostics["summary"] is None and p.diagnostics["summary_failure"] is None for p in preds)
    steps = json.loads((tmp_path / "run" / "ledger.json").read_text())["steps"]
    assert steps["summary"]["samples_received"] == 0 and steps["summary"]["episodes_without_context"] == len(preds)


def test_dry_run_prices_both_prompts_and_writes_nothing(tmp_path, data, capsys):
    cfg = {"method": "text_llm", "dataset": str(data), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "backend": {"name": "openai", "base_url": "http://127.0.0.1:9/v1"},
           "model": {"name": "gpt-4o"}, "decoding": {"n": 5}}
    path = tmp_path / "text_llm.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert cli_main(["predict", "--config", str(path), "--dry-run"]) == 0  # port 9: nothing may be called
    out = capsys.readouterr().out
    assert "dry run: text_llm with openai gpt-4o, 9 episodes x n=5" in out
    assert "step 1, summary: 9 requests for 9 summaries" in out and "step 2, placement: 9 requests for 45 samples" in out
    assert "estimated cost: USD" in out and "nothing written" in out
    assert not (tmp_path / "run").exists()
    assert cli_main(["predict", "--config", str(path), "--dry-run", "--set", "context=0"]) == 0
    assert "step 1, summary: none (context 0" in capsys.readouterr().out


BASE = {"method": "text_llm", "dataset": "data", "out": "runs/x/predictions.jsonl"}


@pytest.mark.parametrize("extra, key", [
    ({"summary": {"max_tokens": 5}}, "summary.max_tokens"),
    ({"sumary": {}}, "sumary"),
    ({"summary": {"temperature": -1}}, "summary.temperature"),
    ({"backend": {"name": "openai", "structured_output": True}}, "backend.structured_output"),
    ({"image_format": "png"}, "image_format"),
    ({"modality": "images"}, "modality"),
    ({"prompt_style": "paper"}, "prompt_style"),
    ({"backend": {"name": "hf"}, "model": {"name": "m"}, "decoding": {"constrained": True}}, "decoding.constrained"),
    ({"backend": {"name": "replay", "base_url": "x"}}, "backend.base_url"),
])
def test_bad_keys_are_refused_in_one_line_naming_the_key(extra, key):
    with pytest.raises(DegustaError) as e:
        from_dict(TextLLMConfig, {**BASE, **extra}, where="text_llm.yaml")
    message = str(e.value)
    assert "\n" not in message and key in message, message


def test_a_local_model_decodes_its_summary_freely():
    cfg = from_dict(TextLLMConfig, {**BASE, "backend": {"name": "hf"}, "model": {"name": "m"}})
    assert cfg.decoding.constrained is False  # null is false here: the summary is prose
    assert get_method("text_llm").config_cls is TextLLMConfig
