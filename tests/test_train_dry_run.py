"""`degusta train --dry-run` for every trainer kind: a report, no weights loaded, nothing written; over-budget
configs are refused with one line naming the key; impossible device counts too."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from finetune_support import dataset, tiny_dir

from degusta_learn.cli import main
from degusta_learn.dryrun import DryRunReport
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_train
from degusta_learn.scene import save_dataset

CONFIGS = Path(__file__).parent.parent / "configs"


def _report(path, overrides) -> tuple[str, DryRunReport]:
    """(the printed report, the DryRunReport run_train returns: the checks that FAIL on this machine)."""
    out: list[str] = []
    report = run_train(path, overrides, dry_run=True, log=out.append)
    assert isinstance(report, DryRunReport)
    text = "\n".join(out)
    assert report.ok == ("FAILS on this machine" not in text), text  # a FAILS line is what the caller is told
    return text, report


def _lines(path, overrides):
    return _report(path, overrides)[0]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return save_dataset(dataset(), tmp_path_factory.mktemp("dry") / "data")


def _finetune(tmp_path, data, *extra):
    return [f"dataset={data}", f"model.name={tiny_dir('idefics3')}", f"trainer.run_dir={tmp_path / 'runs'}",
            "data.max_train_episodes=16", "data.render_size=128", *extra]


def test_finetune_dry_run_reports_and_writes_nothing(tmp_path, data):
    text = _lines(CONFIGS / "finetune_tiny_cpu.yaml", _finetune(tmp_path, data))
    for needle in ("parameters, built on the meta device", "trainable", "LoRA r=16", "tokens per example",
                   "of data.max_length 2048", "over 16 training examples", "steps per epoch", "4 (16 examples",
                   "predicted memory", "ESTIMATE"):
        assert needle in text, (needle, text)
    assert not (tmp_path / "runs").exists()


def test_the_memory_estimate_keeps_tower_activations_only_where_the_tower_trains(tmp_path, data):
    """An adapted connector sits after the tower: its backward pass keeps none of the tower's activations."""
    notes = {}
    for name, extra in (("connector", ["lora.connector=true", "lora.vision_targets=[]"]),
                        ("frozen", ["lora.connector=false", "lora.vision_targets=[]"]),
                        ("tower", ["lora.connector=false", "lora.vision_targets=[q_proj,v_proj]"])):
        text = _lines(CONFIGS / "finetune_tiny_cpu.yaml", _finetune(tmp_path, data, *extra))
        notes[name] = next(line for line in text.splitlines() if "predicted memory" in line)
    assert "frozen vision tower: no activations kept for it" in notes["connector"]
    assert notes["connector"].split("(")[0] == notes["frozen"].split("(")[0]  # the same estimate
    assert "the vision tower trains: its activations are counted" in notes["tower"]
    assert notes["tower"].split("(")[0] != notes["frozen"].split("(")[0]


def test_the_dry_run_reports_and_sizes_the_precision_this_cpu_runs(tmp_path, data, monkeypatch):
    """bf16-mixed on a CPU without native bfloat16 trains in 32-true: the report says so and sizes fp32 activations."""
    import torch

    reports = {}
    for native in (True, False):
        monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda native=native: native)
        text = _lines(CONFIGS / "finetune_tiny_cpu.yaml", _finetune(tmp_path, data, "trainer.precision=bf16-mixed",
                                                                    "trainer.accelerator=cpu"))
        check = next(line for line in text.splitlines() if "trainer check" in line)
        memory = next(line for line in text.splitlines() if "predicted memory" in line)
        value, unit = memory.split("activations ")[1].split()[:2]
        reports[native] = check, float(value) * {"KiB": 2**10, "MiB": 2**20, "GiB": 2**30}[unit]
    assert "run as 32-true here" in reports[False][0] and "run as" not in reports[True][0]
    assert reports[False][1] > reports[True][1]  # 4-byte activations instead of 2


def test_finetune_dry_run_counts_like_the_collator(tmp_path, data):
    """The dry run's token counts are the collator's on the real (rendered) examples."""
    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.dry_run import meta_model
    from degusta_learn.finetune.token_count import count_tokens, set_budget
    from degusta_learn.finetune.train import build_examples
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor

    cfg = load_config(FinetuneConfig, CONFIGS / "finetune_tiny_cpu.yaml", _finetune(tmp_path, data, "data.max_train_episodes=6"))
    processor = load_processor(str(tiny_dir("idefics3")))
    model, config = meta_model(str(tiny_dir("idefics3")))
    set_budget(cfg, processor, config)
    collator = Collator(processor, ChatFormat(processor, model.generation_config), 4096, config.image_token_id)
    train, _ = build_examples(cfg, load_dataset(data), Grid(8, 8))
    real = collator.token_counts([train[i] for i in range(len(train))])
    assert count_tokens(train, collator) == real


def test_finetune_dry_run_refuses_examples_over_max_length(tmp_path, data):
    with pytest.raises(DegustaError, match=r"^data.max_length: episode .* needs \d+ tokens .* budget is 200"):
        _lines(CONFIGS / "finetune_tiny_cpu.yaml", _finetune(tmp_path, data, "data.max_length=200"))
    assert not (tmp_path / "runs").exists()


def _counting_setup(tmp_path, data, kind="idefics3", *extra, max_length=4096):
    """(collator, train examples, val examples) of finetune_tiny_cpu.yaml on the tiny `kind` model, as the dry run
    builds them (config and processor only)."""
    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.dry_run import meta_model
    from degusta_learn.finetune.token_count import set_budget
    from degusta_learn.finetune.train import build_examples
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor

    source = str(tiny_dir(kind))
    cfg = load_config(FinetuneConfig, CONFIGS / "finetune_tiny_cpu.yaml",
                      _finetune(tmp_path, data, f"model.name={source}", *extra))
    processor = load_processor(source)
    model, config = meta_model(source)
    set_budget(cfg, processor, config)
    collator = Collator(processor, ChatFormat(processor, model.generation_config), max_length, config.image_token_id)
    return (collator, *build_examples(cfg, load_dataset(data), Grid(8, 8)))


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_the_bounded_count_is_the_processors_count_of_every_example(tmp_path, data, kind):
    """`token_budget` runs the processor on one example per image layout and a few more to check, and tokenizes
    every example's text alone: its counts are the processor's own for every example (so the same max as counting
    them all), epoch 0's contexts and the heaviest any epoch could draw alike. Qwen2-VL's image tokens follow the
    image's size, Idefics3's its tiles."""
    from degusta_learn.finetune.token_count import count_tokens, token_budget

    extra = ["model.image_size=224"] if kind == "qwen2vl" else []
    collator, train, _ = _counting_setup(tmp_path, data, kind, "data.max_train_episodes=24", *extra)
    budget = token_budget(train, collator, sample=4, seed=1)
    assert not budget.exhaustive and budget.layouts == 3 and budget.sample == 4 and budget.checked >= 4
    every = count_tokens(train, collator)  # the processor on every example
    assert budget.counts == every
    heavier = [(i, train.heaviest(i)) for i in range(len(train)) if train.heaviest(i).context != train.episode(i).context]
    assert heavier  # contexts resampled each epoch: some examples can draw heavier ones
    assert budget.heavier == collator.token_counts([train.example(i, ep) for i, ep in heavier])  # rendered for real
    top = max(c["total"] for c in every + budget.heavier)
    assert max(c["total"] for c in budget.everything) == top == budget.worst[1]["total"]


def test_the_dry_run_reports_what_counting_every_example_reports_and_says_what_it_counted(tmp_path, data):
    from degusta_learn.config import load_config
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.dry_run import dry_run

    cfg = load_config(FinetuneConfig, CONFIGS / "finetune_tiny_cpu.yaml", _finetune(tmp_path, data))

    def report(**kw) -> dict[str, str]:
        out: list[str] = []
        dry_run(cfg, log=out.append, **kw)
        return dict(line.strip().split("  ", 1) for line in out if line.startswith("  "))

    bounded, exhaustive = report(), report(sample=None)  # sample=None: the processor counts every example
    for key in ("tokens per example", "predicted memory"):
        assert bounded[key].strip() == exhaustive[key].strip(), key
    counted = bounded["tokens counted"].strip()
    assert counted.startswith("every example, exactly (no estimate): the text of all 16 training examples"), counted
    assert re.search(r"and the \d+ validation examples by the tokenizer alone; the image tokens once per image layout "
                     r"\(3 layouts\) by the processor, which recounted \d+ examples in full to check \(\d+ sampled "
                     r"with seed 0, the heaviest-looking and the longest\): all agreed$", counted), counted
    assert exhaustive["tokens counted"].strip().startswith("the processor counted all 16 training examples")
    assert "maxima also with the heaviest any epoch could draw" in bounded["tokens per example"]


def test_the_bounded_count_refuses_an_over_budget_example_as_counting_all_did(tmp_path, data):
    """The same one-line error for the same episode as `refuse_over_budget` over every example's count; a budget
    the heaviest contexts fit passes."""
    from degusta_learn.finetune.token_count import (
        count_tokens,
        refuse_budget,
        refuse_over_budget,
        token_budget,
    )

    collator, train, _ = _counting_setup(tmp_path, data)
    counts = count_tokens(train, collator)
    collator.max_length = max(c["total"] for c in counts) - 1
    with pytest.raises(DegustaError) as every:
        refuse_over_budget(train, counts, collator)
    with pytest.raises(DegustaError) as bounded:
        refuse_budget(token_budget(train, collator, heaviest=False), collator)
    assert str(bounded.value) == str(every.value)
    assert re.match(rf"^data.max_length: episode .* needs \d+ tokens .* budget is {collator.max_length};", str(every.value))
    budget = token_budget(train, collator)
    collator.max_length = max(c["total"] for c in budget.everything)
    refuse_budget(budget, collator)  # fits: no error


def test_layout_counts_that_do_not_add_up_make_the_processor_count_every_example(tmp_path, data, monkeypatch):
    """If the text's tokens plus its image layout's are not the processor's count (a processor whose image
    expansion merges with the text), the check finds it and every example is counted by the processor."""
    from degusta_learn.finetune.token_count import count_tokens, token_budget

    collator, train, _ = _counting_setup(tmp_path, data)
    real, calls = collator.text_counts, iter(range(10**6))

    def off_by_some(examples):
        out = real(examples)
        for t in out:
            t["prompt"] += next(calls) % 2  # not a function of the layout
        return out

    monkeypatch.setattr(collator, "text_counts", off_by_some)
    budget = token_budget(train, collator, sample=len(train), heaviest=False)
    assert budget.exhaustive and "the processor counted" in budget.mismatch
    assert budget.counts == count_tokens(train, collator)


def test_blank_counting_images_have_the_renderers_sizes_on_a_wide_table():
    """The blank images token counts use are the size the renderer draws each image, non-square tables too."""
    from degusta_learn.finetune.token_count import _SizeOnlyRenderer
    from degusta_learn.render.compose import sheet_source
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer
    from degusta_learn.scene import Table

    ds = dataset()
    wide = Table(id=99, width=1200, height=700, surface=((0.1, 0.1), (0.9, 0.1), (0.9, 0.9), (0.1, 0.9)))
    real = Renderer(ds.catalog, {**ds.tables, 99: wide}, ds.root, size=128)
    grid = Grid(8, 8)
    for pixels in (True, False):
        blank = _SizeOnlyRenderer(real, pixels)
        for table in (0, 99):
            assert blank.uma(table, []).size == real.uma(table, []).size
            assert blank.gma(table, [], grid).size == real.gma(table, [], grid).size
            assert blank.table(table).size == real.table(table).size
            assert blank.table(table, grid).size == real.table(table, grid).size
        kind = ds.catalog.types[0]
        assert blank.gomo(kind).size == real.gomo(kind).size
        assert sheet_source(blank.gomo(kind)) == sheet_source(real.gomo(kind))  # composed as in training
    assert real.uma(99, []).size[0] != real.uma(99, []).size[1]


def test_cli_dry_run_one_line_error_exit_2(tmp_path, data, capsys):
    args = ["train", "--config", str(CONFIGS / "finetune_tiny_cpu.yaml"), "--dry-run"]
    for o in _finetune(tmp_path, data, "data.max_length=200"):
        args += ["--set", o]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("degusta: error: data.max_length:") and "\n" not in err


def test_learned_dry_run(tmp_path, data):
    base = [f"dataset={data}", f"trainer.run_dir={tmp_path / 'runs'}", "model.d_model=16", "model.n_layers=1",
            "model.n_heads=2", "model.d_ff=32", "model.max_objects=12"]
    text = _lines(CONFIGS / "learned_cpu.yaml", base)
    for needle in ("slot model", "parameters", "slots per example", "of model.max_objects 12", "steps per epoch",
                   "predicted memory", "ESTIMATE"):
        assert needle in text, (needle, text)
    assert not (tmp_path / "runs").exists()
    with pytest.raises(DegustaError, match=r"^model.max_objects: 2, but participant"):
        _lines(CONFIGS / "learned_cpu.yaml", base + ["model.max_objects=2"])


@pytest.mark.slow
def test_pretrain_dry_run(tmp_path):
    overrides = [f"trainer.run_dir={tmp_path / 'runs'}", "data.val_examples=4", "model.vocab_size=256"]
    out: list[str] = []
    from degusta_learn.config import load_config
    from degusta_learn.pretrain.train import PretrainConfig, dry_run

    cfg = load_config(PretrainConfig, CONFIGS / "pretrain_tiny_vlm_cpu.yaml", overrides)
    dry_run(cfg, log=out.append, sample=16)
    text = "\n".join(out)
    assert "FastVLM" in text and "of data.max_length 2048" in text and "predicted memory" in text
    assert not (tmp_path / "runs").exists()
    with pytest.raises(DegustaError, match="^data.max_length: "):
        dry_run(load_config(PretrainConfig, CONFIGS / "pretrain_tiny_vlm_cpu.yaml", overrides + ["data.max_length=40"]),
                log=out.append, sample=16)


def test_impossible_device_counts_name_the_key(tmp_path, data):
    from degusta_learn.config import load_config
    from degusta_learn.training import TrainerConfig, check_trainer

    cores = os.cpu_count() or 1
    with pytest.raises(DegustaError, match=rf"^trainer.devices: {cores + 1} CPU processes .* {cores} cores"):
        check_trainer(TrainerConfig(accelerator="cpu", devices=cores + 1))
    with pytest.raises(DegustaError, match="^trainer.devices: .* selects GPUs"):
        check_trainer(TrainerConfig(accelerator="cpu", devices=[0, 1]))
    with pytest.raises(DegustaError, match="^trainer.num_nodes: 2 machines"):
        check_trainer(TrainerConfig(accelerator="cpu", devices=1, num_nodes=2))
    with pytest.raises(DegustaError, match="num_nodes: expected a value from 1"):
        load_config(TrainerConfig, None, ["num_nodes=0"])
    # a real run refuses before anything is written; the dry run reports it as a failing check instead
    base = [f"dataset={data}", f"trainer.run_dir={tmp_path / 'runs'}", "trainer.accelerator=cpu",
            f"trainer.devices={cores * 32}", "model.d_model=16", "model.n_layers=1", "model.n_heads=2", "model.d_ff=32"]
    with pytest.raises(DegustaError, match="^trainer.devices: "):
        run_train(CONFIGS / "learned_cpu.yaml", base)
    assert not (tmp_path / "runs").exists()
    report, found = _report(CONFIGS / "learned_cpu.yaml", base)
    assert "FAILS on this machine: trainer.devices" in report and "predicted memory" in report
    assert [label for label, _ in found.failures] == ["trainer check"]
    assert found.failures[0][1].startswith(f"trainer.devices: {cores * 32} CPU processes")


def test_dry_run_fails_on_a_config_mistake_and_reports_a_missing_machine(tmp_path, data, capsys):
    """What the machine lacks is reported, the dry run goes on and exits 3 (it ran, a check FAILS); a config mistake
    fails it with the real run's error (exit 2), so a dry-run is a check of the config. (In-process through
    `cli.main`; tests/test_exit_codes.py runs the CLI as a real process.)"""
    from degusta_learn.cli import main

    base = [f"dataset={data}", f"trainer.run_dir={tmp_path / 'runs'}", "model.d_model=16", "model.n_layers=1",
            "model.n_heads=2", "model.d_ff=32"]

    def dry(*extra):
        args = ["train", "--config", str(CONFIGS / "learned_cpu.yaml"), "--dry-run"]
        for o in base + list(extra):
            args += ["--set", o]
        code = main(args)
        out, err = capsys.readouterr()
        return code, out, err

    import torch

    code, out, err = dry("trainer.accelerator=gpu")
    assert code == (0 if torch.cuda.is_available() else 3), out + err
    if not torch.cuda.is_available():  # reported, the rest of the report is printed, one line on stderr says so
        assert "FAILS on this machine: trainer.accelerator" in out and "predicted memory" in out
        assert err.startswith("degusta: dry run: trainer check FAILS on this machine: trainer.accelerator")
        assert err.count("\n") == 1 and "Traceback" not in err
    for key, value in [("trainer.monitor", "val/no_such_key"), ("trainer.strategy", "no_such_strategy")]:
        code, out, err = dry(f"{key}={value}")
        assert code == 2, out + err
        assert f"{key}: " in err and "Traceback" not in err
        assert "FAILS on this machine" not in out
    assert not (tmp_path / "runs").exists()


def test_a_gpu_config_dry_run_on_a_cpu_machine_exits_3_with_the_whole_report(tmp_path, data, capsys):
    """configs/learned_gpu.yaml checked on this CPU machine: the full report (FAILS line included) on stdout, one
    line naming the failing check on stderr, exit 3, nothing written; the same config fixed for the CPU exits 0."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("needs a machine without a CUDA GPU")
    base = [f"dataset={data}", f"trainer.run_dir={tmp_path / 'runs'}", "data.num_workers=0"]
    args = ["train", "--config", str(CONFIGS / "learned_gpu.yaml"), "--dry-run"] + [x for o in base for x in ("--set", o)]
    assert main(args) == 3
    out, err = capsys.readouterr()
    for needle in ("dry run of kind learned", "slot model (d_model 256", "steps per epoch",
                   "trainer check", "FAILS on this machine: trainer.accelerator: 'gpu'", "predicted memory",
                   "dry run: nothing loaded, trained or written"):
        assert needle in out, (needle, out)
    assert err.startswith("degusta: dry run: trainer check FAILS on this machine: trainer.accelerator: 'gpu'")
    assert err.count("\n") == 1
    assert not (tmp_path / "runs").exists()
    cpu = ["trainer.accelerator=cpu", "trainer.devices=1", "trainer.strategy=auto", "trainer.precision=32-true"]
    assert main(args + [x for o in cpu for x in ("--set", o)]) == 0
    out, err = capsys.readouterr()
    assert re.search(r"trainer check +ok on this machine", out) and "FAILS" not in out and err == "", out + err
