"""The context tables written in the answer format after their images (`modality: both`, spelled
`context_answers: true` in records written before `modality`; a config's old `context_answers` keys are refused
with one line naming `modality`). The modality controls themselves: tests/test_modality.py."""

from __future__ import annotations

import dataclasses
import json

import pytest
from conftest import make_small_dataset

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.finetune.data import LiftedExamples
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import make_episodes
from degusta_learn.task.answers import parse_answer
from degusta_learn.task.prompt import ImagePart, build_prompt
from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt
from degusta_learn.vlm.record import FINETUNE_FILE, FinetuneRecord, read_record

LINE = "The objects in {}, written as an answer: "


@pytest.fixture(scope="module")
def setting():
    ds = make_small_dataset(n_participants=4)
    episode = make_episodes(ds, 2, "test", 0)[0]
    return ds, episode, Renderer.for_dataset(ds, size=64)


def _answer_lines(prompt) -> dict[str, str]:
    out = {}
    for part in prompt.parts:
        if isinstance(part, str) and part.startswith("The objects in "):
            name, answer = part[len("The objects in "):].split(", written as an answer: ")
            out[name] = answer
    return out


@pytest.mark.parametrize("method", ["mogma", "logma", "mouma", "louma"])
def test_each_context_is_written_as_the_answer_that_places_its_objects(setting, method):
    ds, episode, renderer = setting
    prompt = build_prompt(method, ds, episode, renderer, Grid(8, 8))
    assert list(prompt.context_answers) == [f"final_state_{k}.jpg" for k in (1, 2)]
    assert not _answer_lines(prompt)  # recorded, not sent: the paper's prompt is unchanged
    told = adapt_prompt(prompt, PromptOptions(context_answers=True))
    lines = _answer_lines(told)
    assert lines == prompt.context_answers
    for k, trial in enumerate(episode.context, start=1):
        name = f"final_state_{k}.jpg"
        arr = ds.arrangement(episode.participant, trial)
        kind = "grid" if method in ("mogma", "logma") else "unmarked"
        items = parse_answer(lines[name], kind, ds.catalog, Grid(8, 8))
        assert [i.id for i in items] == [p.object for p in arr.placements]  # ids in placement order
        assert [i.type for i in items] == [ds.catalog[p.object].type for p in arr.placements]
        # the line comes right after the image's placement-order line
        at = told.parts.index(LINE.format(name) + lines[name])
        assert told.parts[at - 1].startswith(f"Placement order in {name}:")
        assert isinstance(told.parts[at - 2], ImagePart) and told.parts[at - 2].name == name


def test_off_by_default_and_left_out_with_the_context_images(setting):
    ds, episode, renderer = setting
    prompt = build_prompt("mogma", ds, episode, renderer, Grid(8, 8))
    assert adapt_prompt(prompt, PromptOptions()).parts == prompt.parts
    no_context = adapt_prompt(prompt, PromptOptions(include=["objects", "target"], context_answers=True))
    assert not _answer_lines(no_context)


def test_composed_canvases_keep_every_answer_line(setting):
    ds, episode, renderer = setting
    prompt = build_prompt("mogma", ds, episode, renderer, Grid(8, 8))
    told = adapt_prompt(prompt, PromptOptions(compose=["objects", "context"], context_answers=True))
    assert _answer_lines(told) == prompt.context_answers
    assert [p.name for p in told.images] == ["objects.jpg", "context.jpg", "initial_state_1.jpg"]


def test_adapting_an_adapted_prompt_adds_nothing(setting):
    ds, episode, renderer = setting
    opts = PromptOptions(context_answers=True)
    once = adapt_prompt(build_prompt("mogma", ds, episode, renderer, Grid(8, 8)), opts)
    assert adapt_prompt(once, opts).parts == once.parts


def test_a_context_image_without_its_order_line_is_an_error(setting):
    ds, episode, renderer = setting
    prompt = build_prompt("mogma", ds, episode, renderer, Grid(8, 8))
    cut = dataclasses.replace(prompt, parts=[p for p in prompt.parts if not (isinstance(p, str) and
                                                                            p.startswith("Placement order in"))])
    cut = dataclasses.replace(cut, parts=cut.parts[:cut.parts.index(cut.images[-1])])  # ends on an image
    with pytest.raises(DegustaError, match="final_state_1.jpg is not followed by its placement-order line"):
        adapt_prompt(cut, PromptOptions(context_answers=True))


def test_the_finetune_config_key_reaches_the_examples_and_the_record(small_dataset_dir, tmp_path):
    from types import SimpleNamespace

    from degusta_learn.finetune.train import build_examples, write_meta
    from degusta_learn.scene import load_dataset

    cfg = load_config(FinetuneConfig, data={"dataset": str(small_dataset_dir), "seed": 0, "data": {
        "render_size": 64, "contexts": [2], "modality": "both"}})
    ds = load_dataset(small_dataset_dir)
    train, _ = build_examples(cfg, ds, Grid(8, 8))
    assert isinstance(train, LiftedExamples) and train.options.modality == "both"
    assert len(_answer_lines(train[0].prompt)) == 2
    write_meta(tmp_path, cfg, SimpleNamespace(image_processor=SimpleNamespace(size={})))
    record = read_record(tmp_path / FINETUNE_FILE)
    assert isinstance(record, FinetuneRecord) and record.prompt.modality == "both"
    data = json.loads((tmp_path / FINETUNE_FILE).read_text())
    # a record written before `modality` says context_answers: true is both, false (or neither key) images
    for old, modality in (({"context_answers": True}, "both"), ({"context_answers": False}, "images"), ({}, "images")):
        prompt = {k: v for k, v in data["prompt"].items() if k not in ("modality", "context_answers")}
        (tmp_path / FINETUNE_FILE).write_text(json.dumps({**data, "prompt": {**prompt, **old}}))
        assert read_record(tmp_path / FINETUNE_FILE).prompt.modality == modality, old


def test_the_old_config_key_names_the_new_one(small_dataset_dir):
    with pytest.raises(DegustaError, match=r"'data.context_answers' is now 'data.modality \(true was both"):
        load_config(FinetuneConfig, data={"dataset": str(small_dataset_dir), "data": {"context_answers": True}})


def test_the_hf_backend_shows_the_contexts_as_the_prompt_or_else_the_training_says(setting, monkeypatch):
    """A prompt whose modality the runner chose keeps it; one without is shown as the model's record says (a plain
    model: images, the paper's prompt). The backend has no modality key of its own: `backend.context_answers` is
    refused with one line naming the top-level `modality`."""
    from finetune_support import tiny_dir

    from degusta_learn.prompting.backends.base import backend_config
    from degusta_learn.prompting.backends.hf import HFBackend
    from degusta_learn.task.prompt import with_modality
    from degusta_learn.vlm import generate

    ds, episode, renderer = setting
    prompt = build_prompt("mogma", ds, episode, renderer, Grid(8, 8))
    seen = []
    monkeypatch.setattr(generate, "generate_answers", lambda model, processor, p, **kw: seen.append(p) or [])
    backend = HFBackend(str(tiny_dir("idefics3")), device="cpu")
    for shown, lines in ((prompt, 0), (with_modality(prompt, "both"), 2), (with_modality(prompt, "images"), 0)):
        backend.complete(shown, 1, 0.0, 64)
        assert len(_answer_lines(seen[-1])) == lines
    backend.options = PromptOptions(modality="both")  # as a record of a model trained on both reads
    backend.complete(prompt, 1, 0.0, 64)
    assert len(_answer_lines(seen[-1])) == 2
    backend.complete(with_modality(prompt, "images"), 1, 0.0, 64)  # the runner's choice stands
    assert len(_answer_lines(seen[-1])) == 0
    for value in (True, "often"):
        with pytest.raises(DegustaError, match=r"'backend.context_answers' is now 'modality, at the top level"):
            backend_config("hf", context_answers=value)
