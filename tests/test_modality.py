"""The modality controls (issue 53, item 2): the context tables shown as images, as text only or both, one spelling
(`data.modality` in fine-tuning, `modality` in predicting), the same everything else in every modality, and the
modality used recorded in predictions, ledgers, the adapter's record and its card."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
from conftest import make_small_dataset

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import make_episodes
from degusta_learn.task.prompt import ImagePart, build_prompt, with_modality
from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt

G = Grid(8, 8)


@pytest.fixture(scope="module")
def setting():
    ds = make_small_dataset(n_participants=4)
    episode = make_episodes(ds, 2, "test", 0)[0]
    return ds, episode, Renderer.for_dataset(ds, size=64)


def _shape(prompt) -> list[str]:
    """Each part as the image's name or the text's first words: what the model is shown, in order."""
    return [f"<{p.name}>" if isinstance(p, ImagePart) else " ".join(p.split()[:4]) for p in prompt.parts]


def test_each_modality_shows_the_context_tables_as_it_says(setting):
    ds, episode, renderer = setting
    prompts = {m: build_prompt("mogma", ds, episode, renderer, G, modality=m) for m in ("images", "text", "both")}
    shown = {m: _shape(p) for m, p in prompts.items()}
    sheets = [s for t in ds.catalog.types for s in (f"objects_{t}.jpg:", f"<objects_{t}.jpg>")]
    head = ["These are the objects", *sheets]
    tail = ["initial_state_1.jpg:", "<initial_state_1.jpg>", "My preferences for setting"]
    order = ["Placement order in final_state_1.jpg:", "Placement order in final_state_2.jpg:"]
    line = ["The objects in final_state_1.jpg,", "The objects in final_state_2.jpg,"]
    image = [["final_state_1.jpg:", "<final_state_1.jpg>"], ["final_state_2.jpg:", "<final_state_2.jpg>"]]
    assert shown["images"] == head + image[0] + [order[0]] + image[1] + [order[1]] + tail
    assert shown["text"] == head + [order[0], line[0], order[1], line[1]] + tail  # no context image, no label
    assert shown["both"] == head + image[0] + [order[0], line[0]] + image[1] + [order[1], line[1]] + tail
    # the text a line writes is the context's answer; the task text and every other image are the same
    for m, p in prompts.items():
        assert p.modality == m and p.parts[-1] == prompts["images"].parts[-1]
        assert [i.sha256() for i in p.images if not i.name.startswith("final_state")] == \
            [i.sha256() for i in prompts["images"].images if not i.name.startswith("final_state")]
    written = [t for t in prompts["text"].parts if isinstance(t, str) and t.startswith("The objects in ")]
    assert written == [f"The objects in {n}, written as an answer: {a}" for n, a in prompts["text"].context_answers.items()]
    # images is what build_prompt always drew: the paper's prompt
    assert prompts["images"].parts == build_prompt("mogma", ds, episode, renderer, G).parts


def test_a_chosen_modality_is_kept_and_another_refused(setting):
    ds, episode, renderer = setting
    text = build_prompt("mouma", ds, episode, renderer, modality="text")
    assert with_modality(text, "text") is text
    with pytest.raises(DegustaError, match="shows its context tables as 'text' already"):
        with_modality(text, "both")
    # a local model's options choose only where the prompt has not: a predict config's modality wins
    fixed = build_prompt("mogma", ds, episode, renderer, G, modality="images")
    assert adapt_prompt(fixed, PromptOptions(modality="both")).parts == fixed.parts
    chosen = adapt_prompt(build_prompt("mogma", ds, episode, renderer, G), PromptOptions(modality="text"))
    assert chosen.modality == "text" and not [i for i in chosen.images if i.name.startswith("final_state")]
    with pytest.raises(DegustaError, match=r"modality: expected one of \['images', 'text', 'both'\], got 'audio'"):
        build_prompt("mogma", ds, episode, renderer, G, modality="audio")


def test_text_with_composed_contexts_leaves_no_context_canvas(setting):
    ds, episode, renderer = setting
    p = adapt_prompt(build_prompt("mogma", ds, episode, renderer, G),
                     PromptOptions(compose=["objects", "context"], modality="text"))
    assert [i.name for i in p.images] == ["objects.jpg", "initial_state_1.jpg"]


def test_old_spelling_of_the_options_maps_onto_modality():
    assert PromptOptions(context_answers=True).modality == "both"
    assert PromptOptions(context_answers=False, modality="text").modality == "images"  # the old flag decides
    assert PromptOptions(include=["objects", "target"], context_answers=True).modality == "images"  # no images: no text
    assert PromptOptions(context_answers=True) == PromptOptions(modality="both")
    assert PromptOptions(modality="both").to_json() == {"include": ["objects", "context", "target"], "compose": [],
                                                        "modality": "both"}
    with pytest.raises(DegustaError, match="data.modality: both shows the context images, which data.include"):
        PromptOptions(include=["objects", "target"], modality="both")


def test_finetune_config_modality_reaches_examples_record_and_card(small_dataset_dir, tmp_path):
    from degusta_learn.finetune.card import card_text
    from degusta_learn.finetune.train import build_examples, write_meta
    from degusta_learn.scene import load_dataset
    from degusta_learn.vlm.record import FINETUNE_FILE, read_record

    cfg = load_config(FinetuneConfig, data={"dataset": str(small_dataset_dir), "seed": 0, "data": {
        "render_size": 64, "contexts": [2], "modality": "text"}})
    train, val = build_examples(cfg, load_dataset(small_dataset_dir), G)
    for ex in (train[0], val[0]):
        names = [i.name for i in ex.prompt.images]
        assert ex.prompt.modality == "text" and not [n for n in names if n.startswith("final_state")], names
        assert sum(isinstance(t, str) and t.startswith("The objects in final_state_") for t in ex.prompt.parts) == \
            len(ex.context)  # 2 in training, 4 in validation (data.val_contexts)
    assert (len(train[0].context), len(val[0].context)) == (2, 4)
    write_meta(tmp_path, cfg, SimpleNamespace(image_processor=SimpleNamespace(size={})))
    assert read_record(tmp_path / FINETUNE_FILE).prompt.modality == "text"
    assert json.loads((tmp_path / FINETUNE_FILE).read_text())["prompt"]["modality"] == "text"
    card = card_text(cfg, True, None, None)
    assert "- prompt: `mogma`, the person's past tables written out in the answer format only" in card
    assert "`data.modality: text`" in card


def test_finetune_config_refuses_what_it_cannot_show(small_dataset_dir):
    base = {"dataset": str(small_dataset_dir)}
    with pytest.raises(DegustaError, match=r"data.modality: expected one of \['images', 'text', 'both'\]"):
        load_config(FinetuneConfig, data={**base, "data": {"modality": "audio"}})
    with pytest.raises(DegustaError, match="data.modality: both shows the context images, which data.include"):
        load_config(FinetuneConfig, data={**base, "data": {"include": ["objects", "target"], "modality": "both"}})
    assert load_config(FinetuneConfig, data={**base, "data": {"include": ["target"], "modality": "text"}})


def test_every_shipped_config_keeps_what_it_computed():
    from degusta_learn.methods import build_config, get_method
    from degusta_learn.shipped import shipped_config

    assert load_config(FinetuneConfig, shipped_config("finetune_tiny_base_cpu")).data.modality == "both"
    assert load_config(FinetuneConfig, shipped_config("finetune_smolvlm_256m")).data.modality == "images"
    assert build_config(shipped_config("predict_hf_base_zeroshot"), [], "method", get_method)[1].modality == "images"
    assert build_config(shipped_config("predict_hf_base_finetuned"), [], "method", get_method)[1].modality is None


def _zeroshot(tmp_path, ds_dir, **keys):
    from degusta_learn.prompting.runner import ZeroShotConfig

    data = {"method": "mogma", "dataset": str(ds_dir), "out": str(tmp_path / "p.jsonl"), "context": 2,
            "render_size": 64, "cache": "off", **keys}
    return load_config(ZeroShotConfig, data=data)


def test_predict_spelling_is_modality(small_dataset_dir, tmp_path):
    assert _zeroshot(tmp_path, small_dataset_dir, modality="text").modality == "text"
    with pytest.raises(DegustaError, match=r"'backend.context_answers' is now 'modality, at the top level of a predict config \(the old context_answers: true was both"):
        _zeroshot(tmp_path, small_dataset_dir, backend={"name": "hf", "context_answers": True})
    with pytest.raises(DegustaError, match=r"'context_answers' is now 'modality"):
        _zeroshot(tmp_path, small_dataset_dir, context_answers=True)
    with pytest.raises(DegustaError, match=r"modality: expected one of \['images', 'text', 'both'\]"):
        _zeroshot(tmp_path, small_dataset_dir, modality="audio")


def test_predictions_and_ledger_record_the_modality_and_only_the_prompt_changes(small_dataset_dir, tmp_path,
                                                                                monkeypatch):
    from degusta_learn.prompting.backends.replay import ReplayBackend
    from degusta_learn.prompting.runner import run_zeroshot
    from degusta_learn.scene import load_dataset

    ds = load_dataset(small_dataset_dir)
    episodes = make_episodes(ds, 2, "test", 0)[:2]
    answer = "[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]"
    replay = tmp_path / "answers.jsonl"
    replay.write_text("".join(json.dumps({"episode": e.id, "sample": 0, "text": answer}) + "\n" for e in episodes))
    sent = []
    real = ReplayBackend.complete
    monkeypatch.setattr(ReplayBackend, "complete", lambda self, prompt, *a, **k: sent.append(prompt) or
                        real(self, prompt, *a, **k))
    runs = {}
    for modality in (None, "images", "text", "both"):
        out = tmp_path / str(modality)
        cfg = _zeroshot(out, small_dataset_dir, modality=modality, backend={"name": "replay", "path": str(replay)})
        runs[modality] = (run_zeroshot(cfg, ds, episodes), sent[-len(episodes):],
                          json.loads((out / "ledger.json").read_text()))
    for modality, (preds, prompts, ledger) in runs.items():
        used = modality or "images"  # a model without a record: the images
        assert [p.diagnostics["modality"] for p in preds] == [used] * len(episodes)
        assert ledger["modality"] == used and [p.modality for p in prompts] == [used] * len(episodes)
        assert [p.placements for p in preds] == [p.placements for p in runs["images"][0]]  # same answers, decoding
        assert [p.episode for p in preds] == [e.id for e in episodes]
    n_context_images = {m: sum(i.name.startswith("final_state") for i in r[1][0].images) for m, r in runs.items()}
    assert n_context_images == {None: 2, "images": 2, "text": 0, "both": 2}


def test_a_local_model_is_prompted_as_trained_unless_the_config_says(small_dataset_dir, tmp_path):
    """null: the record's modality (an adapter's before its base's); a key of its own for an images-only prompt of a
    model trained with text (before `modality`, the backend added the text to that very prompt: its old key)."""
    from degusta_learn.finetune.train import write_meta
    from degusta_learn.prompting.cache import sample_keys
    from degusta_learn.prompting.runner import ZeroShotRun
    from degusta_learn.scene import load_dataset

    ds = load_dataset(small_dataset_dir)
    ep = make_episodes(ds, 2, "test", 0)[0]
    adapter = tmp_path / "adapter"
    adapter.mkdir()
    train_cfg = load_config(FinetuneConfig, data={"dataset": str(small_dataset_dir), "data": {"modality": "both"}})
    write_meta(adapter, train_cfg, SimpleNamespace(image_processor=SimpleNamespace(size={})))

    def run(modality, with_adapter):
        model = {"name": "tiny_vlm_base", "adapter": str(adapter) if with_adapter else None}
        return ZeroShotRun(_zeroshot(tmp_path, small_dataset_dir, modality=modality, backend={"name": "hf"},
                                     model=model), ds)

    def old_keys(r):  # what the runner keyed this episode with before `modality`: the prompt as build_prompt drew it
        c = r.cfg
        plain = build_prompt(c.method, ds, ep, r.renderer, r.grid, c.image_format, style=c.prompt_style)
        return sample_keys(plain, c.backend, c.model, c.decoding, c.decoding.sampling_temperature, r.max_tokens,
                           c.seed, c.decoding.n)

    base, tuned, tuned_images = run(None, False), run(None, True), run("images", True)
    assert (base.trained_modality, base.modality) == ("images", "images")  # the shipped base's degusta_base.json
    assert (tuned.trained_modality, tuned.modality) == ("both", "both")
    assert tuned_images.modality == "images"
    assert tuned.prompt(ep)[0].modality == "both"
    assert base.prompt(ep)[1] == old_keys(base)  # the zero-shot base's cached answers stay valid
    assert tuned_images.prompt(ep)[1] != old_keys(tuned_images)
    assert run("text", False).prompt(ep)[1] != old_keys(base)
