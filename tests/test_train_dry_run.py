"""`degusta train --dry-run` for every trainer kind: a report, no weights loaded, nothing written; over-budget
configs are refused with one line naming the key; impossible device counts too."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from finetune_support import dataset, tiny_dir

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_train
from degusta_learn.scene import save_dataset

CONFIGS = Path(__file__).parent.parent / "configs"


def _lines(path, overrides):
    out: list[str] = []
    assert run_train(path, overrides, dry_run=True, log=out.append) is None
    return "\n".join(out)


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
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor
    from degusta_learn.finetune.train import build_examples, count_tokens, meta_model, set_budget
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset

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
    from degusta_learn.finetune.pretrain.train import PretrainConfig, dry_run

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
    from degusta_learn.trainer import TrainerConfig, check_trainer

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
    report = _lines(CONFIGS / "learned_cpu.yaml", base)
    assert "FAILS on this machine: trainer.devices" in report and "predicted memory" in report


def test_dry_run_fails_on_a_config_mistake_and_reports_a_missing_machine(tmp_path, data):
    """What the machine lacks is reported and the dry run goes on (exit 0); a config mistake fails it with the
    real run's error (exit 2), so a dry-run is a check of the config."""
    import subprocess
    import sys

    base = [f"dataset={data}", f"trainer.run_dir={tmp_path / 'runs'}", "model.d_model=16", "model.n_layers=1",
            "model.n_heads=2", "model.d_ff=32"]

    def dry(*extra):
        cmd = [sys.executable, "-m", "degusta_learn.cli", "train", "--config", str(CONFIGS / "learned_cpu.yaml"),
               "--dry-run"]
        for o in base + list(extra):
            cmd += ["--set", o]
        return subprocess.run(cmd, capture_output=True, text=True)

    import torch

    gpu = dry("trainer.accelerator=gpu")
    assert gpu.returncode == 0, gpu.stdout + gpu.stderr
    if not torch.cuda.is_available():  # reported, and the rest of the report is printed
        assert "FAILS on this machine: trainer.accelerator" in gpu.stdout and "predicted memory" in gpu.stdout
    for key, value in [("trainer.monitor", "val/no_such_key"), ("trainer.strategy", "no_such_strategy")]:
        bad = dry(f"{key}={value}")
        assert bad.returncode == 2, bad.stdout + bad.stderr
        assert f"{key}: " in bad.stderr and "Traceback" not in bad.stderr
        assert "FAILS on this machine" not in bad.stdout
    assert not (tmp_path / "runs").exists()
