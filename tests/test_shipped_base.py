"""The shipped tiny base VLM (degusta_learn/shipped_models/tiny_vlm_base): a plain Hugging Face folder that loads offline and answers.

The one test that loads the shipped weights (every other test builds its model tiny): its files and size, the plain
transformers Auto classes, the toolkit's loader, and one constrained perception answer that parses.
"""

from __future__ import annotations

import json

from degusta_learn.shipped import BASE_DIR, shipped_base

MAX_MB = 40


def test_the_shipped_base_is_complete_and_small():
    assert shipped_base() == BASE_DIR, f"{BASE_DIR}: the shipped base is missing (config.json, model.safetensors)"
    for name in ("config.json", "model.safetensors", "tokenizer.json", "processor_config.json", "README.md",
                 "degusta_base.json", "pretrain_config.yaml", "perception.json", "selection.json"):
        assert (BASE_DIR / name).is_file(), name
    size = sum(p.stat().st_size for p in BASE_DIR.rglob("*") if p.is_file())
    assert size <= MAX_MB * 2**20, f"{size / 2**20:.1f} MB"
    card = (BASE_DIR / "README.md").read_text()
    scores = json.loads((BASE_DIR / "perception.json").read_text())
    assert scores["n_images"] >= 500 and "object-set F1" in card  # held-out scores are in the card
    selection = json.loads((BASE_DIR / "selection.json").read_text())  # how it was chosen: the test looked at once
    assert selection["protocol"] and selection["test"]["split"] == "test" and "How this build was chosen" in card


def test_the_shipped_base_loads_offline_and_answers_one_perception_question(monkeypatch):
    import torch
    from transformers import AutoModelForImageTextToText, AutoProcessor

    from degusta_learn.pretrain.score import score_answer
    from degusta_learn.pretrain.tasks import PerceptionExamples, TaskMix
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import default_catalog, default_tables
    from degusta_learn.task.grammar import AnswerGrammar
    from degusta_learn.vlm.generate import generate_answers
    from degusta_learn.vlm.load import load_vlm

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    model = AutoModelForImageTextToText.from_pretrained(BASE_DIR)
    assert AutoProcessor.from_pretrained(BASE_DIR).tokenizer is not None and model.num_parameters() > 1e6
    model, processor = load_vlm(str(BASE_DIR), device="cpu", dtype="float32")
    catalog, grid = default_catalog(), Grid(8, 8)
    meta = json.loads((BASE_DIR / "degusta_base.json").read_text())
    mix = TaskMix(lists=0.0, describe=1.0, gomo=0.0, locate=0.0, describe_questions=1, scenes=[1.0, 0, 0, 0])
    ex = PerceptionExamples(catalog, {t.id: t for t in default_tables()}, grid, meta["image_size"], 7, 1, mix)[0]
    with torch.no_grad():
        text = generate_answers(model, processor, ex.prompt, n=1, temperature=0.0, max_new_tokens=160,
                                constrained=True, grammar=AnswerGrammar("grid", catalog, grid))[0].text
    assert score_answer(ex, text, catalog, grid)["parsed"], text


def test_the_card_reports_the_transcribe_score_when_the_benchmark_measured_it(tmp_path):
    """bench_perception.py's transcribe questions (copying, not perception) get their own line in the card."""
    from degusta_learn.pretrain.export import BASE_META, PERCEPTION, write_card

    (tmp_path / BASE_META).write_text((BASE_DIR / BASE_META).read_text())
    scores = json.loads((BASE_DIR / PERCEPTION).read_text())
    scores.pop("transcribe", None)  # a benchmark run that did not ask them
    (tmp_path / PERCEPTION).write_text(json.dumps(scores))
    card = write_card(tmp_path).read_text()
    assert "*transcribe* questions" not in card
    scores["transcribe"] = {"n": 100, "object_f1": 0.34, "length_exact": 0.12}
    (tmp_path / PERCEPTION).write_text(json.dumps(scores))
    card = write_card(tmp_path).read_text()
    assert "100 *transcribe* questions): object F1 0.34, the written length 0.12 of the time" in card


def test_each_shipped_bases_card_gives_the_command_that_rebuilds_it_from_todays_recipe():
    """The shipped config changes (channels_last, fewer validations, shorter stages); a base built before must name the
    `--set` values that repeat its own run, as `recipe_command` derives them from the folder's resolved config and
    the precision and CPU kernels the run trained with (recorded: `bf16-mixed` in a config is fp32 on one CPU and bf16
    on another, `cpu_kernels: native` AVX2 on one and AVX-512 on another)."""
    from degusta_learn.config import load_config
    from degusta_learn.pretrain.export import ran_as, recipe_command
    from degusta_learn.pretrain.train import PretrainConfig

    for folder in sorted(BASE_DIR.parent.glob("tiny_vlm_base*")):
        resolved = load_config(PretrainConfig, folder / "pretrain_config.yaml")
        training = json.loads((folder / "degusta_base.json").read_text())["training"]
        command = training["command"]
        assert training.get("cpu_kernels"), folder  # both were built on CPUs: which kernels is part of the recipe
        assert command == recipe_command(resolved, ran=ran_as(training)), folder
        assert f"`{command}`" in (folder / "README.md").read_text(), folder


def test_the_shipped_record_renders_its_card_and_one_with_the_removed_training_keys_still_reads(tmp_path):
    """The card is `write_card` of the record, byte for byte; a record written before `data.freeze_projector` and
    `data.teacher_weight` were removed (its training facts carry them) still reads and renders the same card."""
    from degusta_learn.pretrain.export import BASE_META, PERCEPTION, SELECTION, write_card
    from degusta_learn.vlm.record import read_record

    meta = json.loads((BASE_DIR / BASE_META).read_text())
    for name in (PERCEPTION, SELECTION):  # the card's perception table and "How this build was chosen"
        (tmp_path / name).write_text((BASE_DIR / name).read_text())
    card = (BASE_DIR / "README.md").read_text()
    for extra in ({}, {"freeze_projector": False, "teacher_weight": 0.0}):
        (tmp_path / BASE_META).write_text(json.dumps({**meta, "training": {**meta["training"], **extra}}))
        assert read_record(tmp_path / BASE_META).training.items() >= extra.items()
        assert write_card(tmp_path, name=BASE_DIR.name, path=BASE_DIR).read_text() == card
