"""Training runs under bad input and faults (issue 12, items 9 and 10), through `degusta train` as a user runs it.

Each case asserts the user-facing outcome: exit status 2 and ONE line "degusta: error: ..." naming the
config key (or file), no run folder left behind; or, for faults, the documented recovery (fallback to
best.ckpt with a note, or a one-line refusal that leaves the run folder as it was). Runs are the tiniest
learned model (max_steps 1-2) on a hand-built dataset, so the file takes well under a minute.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import lightning.pytorch  # noqa: F401  (imported now: its log handler must bind the real stderr, not a test's)
import pytest
import torch
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from conftest import make_small_dataset  # noqa: E402

from degusta_learn import cli  # noqa: E402
from degusta_learn.errors import DegustaError  # noqa: E402
from degusta_learn.scene import save_dataset  # noqa: E402
from degusta_learn.training import TMP_PREFIX, TrainerConfig, atomic_checkpoint_io, build_trainer, fit  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py
CONFIGS = Path(__file__).parent.parent / "configs"
NO_GPU = not torch.cuda.is_available()


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    return save_dataset(make_small_dataset(), tmp_path_factory.mktemp("hardening") / "data")


def learned_yaml(tmp_path: Path, data: Path | str, **trainer) -> Path:
    """The tiniest learned config, written as a user's YAML file; runs go to tmp_path/runs/tiny."""
    cfg = {"kind": "learned", "num_threads": 1,
           "dataset": str(data), "data": {"batch_size": 8, "repeats": 1, "val_contexts": [2]},
           "model": {"d_model": 16, "n_layers": 1, "n_heads": 2, "d_ff": 32, "max_objects": 8},
           "trainer": {"run_dir": str(tmp_path / "runs"), "run_name": "tiny", "max_epochs": -1, "max_steps": 1,
                       "val_check_interval": 1, "accelerator": "cpu", "devices": 1, "progress_bar": False,
                       "log_every_n_steps": 1, **trainer}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def train(config: Path | str, *overrides: str) -> int:
    return cli.main(["train", "--config", str(config), *[a for o in overrides for a in ("--set", o)]])


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("degusta: error: "), err
    return err[0]


def weights(ckpt: Path) -> dict:
    return torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]


# ---------------------------------------------------------------- bad trainer values: refused up front
BAD_TRAINER = [
    ("trainer.devices=banana", "trainer.devices"),
    ("trainer.devices=0", "trainer.devices"),
    ("trainer.devices=[0,0]", "trainer.devices"),
    ("trainer.devices=-7", "trainer.devices"),
    ("trainer.precision=bogus", "trainer.precision"),
    ("trainer.precision=16-true", "trainer.precision"),  # float16 weights: GPU only
    ("trainer.accelerator=warp", "trainer.accelerator"),
    pytest.param("trainer.accelerator=gpu", "trainer.accelerator: 'gpu' but no CUDA GPU",
                 marks=pytest.mark.skipif(not NO_GPU, reason="a GPU is present")),
    pytest.param("trainer.accelerator=cuda", "trainer.accelerator: 'cuda' but no CUDA GPU",
                 marks=pytest.mark.skipif(not NO_GPU, reason="a GPU is present")),
    ("trainer.strategy=warp", "trainer.strategy"),
    pytest.param("trainer.strategy=fsdp", "trainer.strategy: 'fsdp' needs a GPU",
                 marks=pytest.mark.skipif(not NO_GPU, reason="a GPU is present")),
    ("trainer.monitor=val/never_logged", "trainer.monitor: 'val/never_logged' is never logged"),
    ("trainer.monitor=val/rmsd_k4", "trainer.monitor: 'val/rmsd_k4' is never logged"),  # only k2 validated
    ("trainer.monitor=", "trainer.monitor"),
    ("trainer.max_steps=0", "trainer.max_steps"),
    ("trainer.max_steps=-5", "trainer.max_steps"),
    ("trainer.max_steps=1000000000000000000000000000000", "trainer.max_steps"),
    ("trainer.max_epochs=0", "trainer.max_epochs"),
    ("trainer.val_check_interval=1.5", "trainer.val_check_interval"),
    ("trainer.val_check_interval=0", "trainer.val_check_interval"),
    ("trainer.val_check_interval=1000", "trainer.val_check_interval"),  # more batches than an epoch has
    ("trainer.log_every_n_steps=0", "trainer.log_every_n_steps"),
    ("trainer.accumulate_grad_batches=0", "trainer.accumulate_grad_batches"),
    ("trainer.gradient_clip_val=-1", "trainer.gradient_clip_val"),
    ("trainer.gradient_clip_val=.inf", "trainer.gradient_clip_val: expected a finite number"),
    ("trainer.seed=-1", "trainer.seed"),
    ("trainer.seed=99999999999", "trainer.seed"),
    ("trainer.num_sanity_val_steps=-3", "trainer.num_sanity_val_steps"),
    ("trainer.run_name=..", "trainer.run_name"),
]


@pytest.mark.parametrize("override, message", BAD_TRAINER)
def test_bad_trainer_value_is_one_line_naming_the_key_and_leaves_no_run_folder(tmp_path, data_root, capsys,
                                                                               override, message):
    assert train(learned_yaml(tmp_path, data_root), override) == 2
    line = one_error_line(capsys)
    assert message in line, line
    assert not (tmp_path / "runs").exists()


def test_monitor_never_logged_by_a_module_fails_at_the_first_validation_without_a_folder(tmp_path):
    """The backstop when a module logs less than it declares: one clear error at the first validation."""
    sys.path.insert(0, str(Path(__file__).parent))
    from test_trainer import Toy, ToyData

    cfg = TrainerConfig(run_dir=str(tmp_path / "runs"), run_name="toy", max_epochs=-1, max_steps=4, accelerator="cpu",
                        devices=1, progress_bar=False, val_check_interval=2, monitor="val/other")
    with pytest.raises(DegustaError, match=r"trainer.monitor: 'val/other' was not logged .*val/rmsd"):
        fit(Toy(), ToyData(), cfg, full_config={"kind": "toy"})
    assert not (tmp_path / "runs" / "toy").exists()


# ---------------------------------------------------------------- oversized configs (item 10)
OVERSIZED = [
    ("learned", "model.max_objects=100000", "model.max_objects: expected a value from 1 to 1,000"),
    ("learned", "data.batch_size=1000000000", "data.batch_size"),
    ("learned", "model.d_model=1000000", "model.d_model"),
    ("learned", "data.repeats=10000000", "data.repeats"),
    ("learned", "num_threads=100000", "num_threads"),
    ("finetune", "model.image_size=60000", "model.image_size: expected a value from 16 to 4,096, got 60000"),
    ("finetune", "data.render_size=60000", "data.render_size"),
    ("finetune", "data.max_length=1000000000", "data.max_length"),
    ("finetune", "data.batch_size=100000", "data.batch_size"),
    ("finetune", "decoding.max_new_tokens=10000000", "decoding.max_new_tokens: expected a value from 1 to 131,072"),
    ("finetune", "lora.r=1000000", "lora.r"),
    ("finetune", "optim.lr=.nan", "optim.lr: expected a finite number"),
    ("pretrain", "model.image_size=60000", "model.image_size"),
    ("pretrain", "model.text_hidden=10000000", "model.text_hidden"),
    ("pretrain", "model.vision_channels=[8,8,16,100000000]", "model.vision_channels"),
    ("pretrain", "data.val_examples=1000000000", "data.val_examples"),
]


@pytest.mark.parametrize("kind, override, message", OVERSIZED)
def test_oversized_config_values_are_refused_before_anything_is_built(tmp_path, data_root, capsys, kind, override,
                                                                      message):
    config = {"learned": learned_yaml(tmp_path, data_root), "finetune": CONFIGS / "finetune_tiny_cpu.yaml",
              "pretrain": CONFIGS / "pretrain_tiny_vlm_cpu.yaml"}[kind]
    assert train(config, override, f"trainer.run_dir={tmp_path / 'runs'}") == 2
    line = one_error_line(capsys)
    assert message in line, line
    assert not (tmp_path / "runs").exists()


def _bomb(levels: int = 9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels + 1):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    return "kind: learned\n" + "\n".join(lines) + "\n"


BAD_FILES = [
    ("alias_bomb", _bomb(), "refused: aliases expand it to more than 100,000 values"),
    ("recursive", "kind: learned\nloop: &x [1, *x]\n", "refused: an alias refers to a node that contains it"),
    ("huge_int", "kind: learned\nnum_threads: " + "7" * 5000 + "\n", "invalid YAML value"),
    ("deep", "kind: learned\nx: " + "[" * 20000 + "]" * 20000 + "\n", "nested too deeply"),
    ("syntax", "kind: learned\ntrainer: {max_steps: [\n", "invalid YAML"),
    ("list_top", "- kind\n- learned\n", "expected a mapping of keys at the top level"),
    ("non_utf8", b"kind: learned\n# \xff\xfe\n", "not UTF-8 text"),
    ("folder", None, "is a folder, expected a YAML config file"),
]


@pytest.mark.parametrize("name, content, message", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_bad_config_files_are_one_line_naming_the_file(tmp_path, capsys, name, content, message):
    path = tmp_path / f"{name}.yaml"
    if content is None:
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    assert train(path, f"trainer.run_dir={tmp_path / 'runs'}") == 2
    line = one_error_line(capsys)
    assert str(path) in line and message in line, line
    assert not (tmp_path / "runs").exists()


def test_alias_bomb_in_a_set_value_is_refused(tmp_path, data_root, capsys):
    bomb = "[" + ", ".join(["&a0 [1,1,1,1,1,1,1,1,1,1]"] + ["*a0"] * 3) + "]"  # small: fine (not a bomb)
    nested = "{" + ", ".join(f"k{i}: &b{i} [" + ", ".join([f"*b{i - 1}" if i else "1"] * 10) + "]"
                             for i in range(7)) + "}"
    assert train(learned_yaml(tmp_path, data_root), f"data.x={bomb}") == 2
    assert "unknown key 'data.x'" in one_error_line(capsys)  # a few aliases load normally
    assert train(learned_yaml(tmp_path, data_root), f"data.x={nested}") == 2
    assert "--set data.x: refused value (aliases expand" in one_error_line(capsys)


# ---------------------------------------------------------------- reproducibility
def test_same_seed_same_weights_after_one_step_other_seed_differs(tmp_path, data_root):
    cfg = learned_yaml(tmp_path, data_root, monitor=None)
    runs = tmp_path / "runs"
    torch.manual_seed(123)  # whatever the process did before must not matter
    assert train(cfg, "trainer.run_name=a") == 0
    torch.rand(17)
    assert train(cfg, "trainer.run_name=b") == 0
    assert train(cfg, "trainer.run_name=c", "trainer.seed=1") == 0
    a, b, c = (weights(runs / n / "last.ckpt") for n in "abc")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], c[k]) for k in a)


def _vlm_overrides(kind: str, tmp_path: Path, name: str) -> list[str]:
    common = [f"trainer.run_dir={tmp_path / 'runs'}", f"trainer.run_name={name}", "trainer.max_steps=1",
              "trainer.progress_bar=false", "trainer.monitor=null", "data.batch_size=1", "trainer.log_every_n_steps=1"]
    if kind == "pretrain":
        from test_pretrain_train import TINY

        return TINY + common + ["data.steps_per_epoch=1", "data.val_examples=0", f"export={tmp_path / name}_base"]
    from finetune_support import dataset, tiny_dir

    data = tmp_path / "data"
    if not data.exists():
        save_dataset(dataset(), data)
    return common + [f"dataset={data}", f"model.name={tiny_dir('idefics3')}", "trainer.val_check_interval=1",
                     "data.val_episodes=0", "data.max_train_episodes=2", "data.render_size=128"]


@pytest.mark.parametrize("kind", ["finetune", "pretrain"])
def test_vlm_trainers_same_seed_same_weights_after_one_step(tmp_path, kind):
    """LoRA adapters (finetune) and the dense head (pretrain) are initialised after seeding too."""
    config = CONFIGS / ("finetune_tiny_cpu.yaml" if kind == "finetune" else "pretrain_tiny_vlm_cpu.yaml")
    assert train(config, *_vlm_overrides(kind, tmp_path, "a")) == 0
    torch.rand(17)  # the process's RNG state before a run must not matter
    assert train(config, *_vlm_overrides(kind, tmp_path, "b")) == 0
    a, b = (weights(tmp_path / "runs" / n / "last.ckpt") for n in "ab")
    assert a and a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------- checkpoints: atomic saves, corrupt last.ckpt
def test_checkpoints_are_saved_atomically_in_the_run_folder(tmp_path):
    io = atomic_checkpoint_io()
    trainer = build_trainer(TrainerConfig(run_dir=str(tmp_path), accelerator="cpu", devices=1, progress_bar=False),
                            tmp_path / "run")
    assert type(trainer.strategy.checkpoint_io).__name__ == "AtomicCheckpointIO"
    target = tmp_path / "run" / "last.ckpt"
    io.save_checkpoint({"state_dict": {"w": torch.ones(3)}, "global_step": 1}, target)
    before = target.read_bytes()

    class Boom:  # pickling fails halfway through writing, as a kill or a full disk would stop it
        def __reduce__(self):
            raise OSError(28, "No space left on device")

    with pytest.raises(DegustaError, match=r"last.ckpt: cannot write the checkpoint \(No space left on device\); "
                                           r"training stopped, the previous one is intact"):  # one line, not OSError
        io.save_checkpoint({"state_dict": {"w": torch.zeros(10_000)}, "global_step": 2, "x": Boom()}, target)
    assert target.read_bytes() == before  # the previous complete checkpoint is untouched
    assert sorted(p.name for p in target.parent.iterdir()) == ["last.ckpt"]  # no temp file left


def _first_run(tmp_path, data_root, **trainer) -> tuple[Path, Path]:
    cfg = learned_yaml(tmp_path, data_root, max_steps=2, **trainer)
    assert train(cfg) == 0
    return cfg, tmp_path / "runs" / "tiny"


def test_truncated_last_ckpt_resumes_from_best_with_a_note(tmp_path, data_root, capsys):
    cfg, run = _first_run(tmp_path, data_root)
    assert (run / "best.ckpt").is_file()
    data = (run / "last.ckpt").read_bytes()
    (run / "last.ckpt").write_bytes(data[: len(data) // 2])  # a kill mid-copy under the old saving
    (run / f"{TMP_PREFIX}last.ckpt.abc").write_bytes(b"partial")  # a temp file a kill left behind
    capsys.readouterr()
    assert train(cfg, "trainer.max_steps=3") == 0
    err = capsys.readouterr().err
    assert f"degusta: note: {run / 'last.ckpt'} is unusable" in err and "resuming from" in err and "best.ckpt" in err
    assert torch.load(run / "last.ckpt", weights_only=True)["global_step"] == 3
    assert not list(run.glob(f"{TMP_PREFIX}*"))


@pytest.mark.parametrize("damage", ["truncated", "empty", "garbage"])
def test_corrupt_last_ckpt_without_a_good_best_is_refused_and_left_as_is(tmp_path, data_root, capsys, damage):
    cfg, run = _first_run(tmp_path, data_root, monitor=None)  # no best.ckpt to fall back to
    assert not (run / "best.ckpt").exists()
    data = (run / "last.ckpt").read_bytes()
    bad = {"truncated": data[:1000], "empty": b"", "garbage": b"PK\x03\x04" + os.urandom(2000)}[damage]
    (run / "last.ckpt").write_bytes(bad)
    listing = sorted(p.relative_to(run) for p in run.rglob("*"))
    capsys.readouterr()
    assert train(cfg, "trainer.max_steps=3") == 2
    line = one_error_line(capsys)
    assert f"{run / 'last.ckpt'}: cannot resume" in line and "delete" in line and "trainer.run_name" in line, line
    assert (run / "last.ckpt").read_bytes() == bad and sorted(p.relative_to(run) for p in run.rglob("*")) == listing


def test_same_dataset_by_relative_and_absolute_path_resumes(tmp_path, data_root, monkeypatch):
    monkeypatch.chdir(data_root.parent)
    cfg = learned_yaml(tmp_path, os.path.relpath(data_root), monitor=None)
    assert train(cfg) == 0
    assert train(cfg, f"dataset={data_root}", "trainer.max_steps=2") == 0  # same folder, absolute
    assert torch.load(tmp_path / "runs" / "tiny" / "last.ckpt", weights_only=True)["global_step"] == 2
    other = save_dataset(make_small_dataset(seed=1), tmp_path / "other")
    with pytest.raises(DegustaError, match="cannot resume, 'dataset' was"):
        from degusta_learn.methods import run_train

        run_train(cfg, [f"dataset={other}", "trainer.max_steps=3"])


def test_a_run_from_before_a_new_config_key_resumes_and_says_so(tmp_path, data_root, capsys):
    """A config key that a newer degusta_learn added (absent from the run's config.yaml) is not a change of the
    run: the resume goes on, names the key and the value it now runs with, and records it; a changed key refuses."""
    cfg = learned_yaml(tmp_path, data_root, monitor=None)
    assert train(cfg) == 0
    saved = tmp_path / "runs" / "tiny" / "config.yaml"
    old = yaml.safe_load(saved.read_text())
    del old["model"]["d_ff"]  # as an older version would have written it
    saved.write_text(yaml.safe_dump(old))
    capsys.readouterr()
    assert train(cfg, "trainer.max_steps=2") == 0
    err = capsys.readouterr().err
    assert "predates model.d_ff; resuming with 32" in err, err
    assert yaml.safe_load(saved.read_text())["model"]["d_ff"] == 32
    assert train(cfg, "trainer.max_steps=3", "model.d_ff=64") == 2
    assert "cannot resume, 'model.d_ff' was 32 and is now 64" in one_error_line(capsys)


def test_a_run_dir_under_a_file_is_one_line_before_lightning_says_anything(tmp_path, data_root, capfd):
    """The check ran after the Trainer was built: Lightning's GPU/TPU banner and tips came before the error."""
    (tmp_path / "afile").write_text("x")
    assert train(learned_yaml(tmp_path, data_root), f"trainer.run_dir={tmp_path / 'afile'}") == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "trainer.run_dir: cannot create the run folder" in err[0] and "is a file" in err[0], err
