"""The shared Lightning harness: run folder + config.yaml, checkpoints, resume, refusals, config errors."""

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from degusta_learn.config import from_dict, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.training import TrainerConfig, fit, prepare_run_dir, validation_curve, x86_with_avx2


class Toy(L.LightningModule):
    """Linear regression; logs val/rmsd so ModelCheckpoint can pick best.ckpt."""

    def __init__(self):
        super().__init__()
        self.save_hyperparameters({"kind": "toy"})
        self.lin = torch.nn.Linear(2, 1)

    def training_step(self, batch, _):
        x, y = batch
        return ((self.lin(x) - y) ** 2).mean()

    def validation_step(self, batch, _):
        x, y = batch
        self.log("val/rmsd", ((self.lin(x) - y) ** 2).mean().sqrt())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class ToyData(L.LightningDataModule):
    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        x = torch.randn(32, 2, generator=g)
        self.ds = TensorDataset(x, x.sum(1, keepdim=True))

    def train_dataloader(self):
        return DataLoader(self.ds, batch_size=8)

    def val_dataloader(self):
        return DataLoader(self.ds, batch_size=16)


def cfg(tmp_path, **kw) -> TrainerConfig:
    base = dict(run_dir=str(tmp_path), run_name="toy", max_epochs=-1, max_steps=4, accelerator="cpu",
                devices=1, progress_bar=False, log_every_n_steps=1, val_check_interval=2)
    return TrainerConfig(**{**base, **kw})


def test_fit_writes_run_folder_and_resumes(tmp_path):
    full = {"kind": "toy", "lr": 0.1, "trainer": {"max_steps": 4}}
    run = fit(Toy(), ToyData(), cfg(tmp_path), full_config=full)
    assert run == tmp_path / "toy"
    for name in ("config.yaml", "last.ckpt", "best.ckpt", "csv/version_0/metrics.csv"):
        assert (run / name).is_file(), name
    assert list((run / "tb").glob("version_0/events.*"))
    assert read_yaml(run / "config.yaml") == full
    ckpt = torch.load(run / "last.ckpt", weights_only=True)  # plain data only
    assert ckpt["global_step"] == 4 and ckpt["hyper_parameters"]["kind"] == "toy"
    assert "val/rmsd" in (run / "csv/version_0/metrics.csv").read_text().splitlines()[0]
    # an interrupted run, resumed with a larger budget, continues from step 4; logs of the first part are kept
    fit(Toy(), ToyData(), cfg(tmp_path, max_steps=7), full_config={**full, "trainer": {"max_steps": 7}})
    assert torch.load(run / "last.ckpt", weights_only=True)["global_step"] == 7
    assert (run / "csv/version_0/metrics.csv").is_file() and (run / "csv/version_1/metrics.csv").is_file()
    # resumed again: the logged steps go on where an uninterrupted run's would be (Lightning's restored logging
    # step was one ahead per resume: validations after steps 2, 4, 6, 8, 10 logged at 1, 3, 6, 8, 11 before);
    # the run that stopped at step 7 validated its last weights there too
    fit(Toy(), ToyData(), cfg(tmp_path, max_steps=10), full_config={**full, "trainer": {"max_steps": 10}})
    assert [r["step"] for r in validation_curve(run, "val/rmsd")] == [1, 3, 5, 6, 7, 9]


@pytest.mark.parametrize("max_steps, validated_after", [(6, [4, 6]), (8, [4, 8])])
def test_a_run_validates_the_weights_it_stops_with(tmp_path, max_steps, validated_after):
    """Epochs of 4 batches, a validation at each epoch's end: a run that stops inside an epoch validates there too
    (Lightning alone stopped at step 6 without it); one that stops at an epoch's end validates once."""
    run = fit(Toy(), ToyData(), cfg(tmp_path, max_steps=max_steps, val_check_interval=1.0))
    assert [r["step"] + 1 for r in validation_curve(run, "val/rmsd")] == validated_after


def test_refuses_to_overwrite_or_mix_runs(tmp_path):
    run, resume_from = prepare_run_dir(cfg(tmp_path), {"kind": "toy", "lr": 0.1})
    assert resume_from is None and read_yaml(run / "config.yaml") == {"kind": "toy", "lr": 0.1}
    torch.save({"state_dict": {}, "global_step": 2}, run / "last.ckpt")  # stands in for an interrupted run
    assert prepare_run_dir(cfg(tmp_path), {"kind": "toy", "lr": 0.1, "trainer": {"max_steps": 9}})[1] == run / "last.ckpt"
    with pytest.raises(DegustaError, match="trainer.resume=true"):
        prepare_run_dir(cfg(tmp_path, resume=False), {"kind": "toy", "lr": 0.1})
    with pytest.raises(DegustaError, match="'lr' was 0.1 and is now 0.5"):
        prepare_run_dir(cfg(tmp_path), {"kind": "toy", "lr": 0.5})


@pytest.mark.parametrize("data, message", [
    ({"max_epoch": 3}, "unknown key 'max_epoch'"),
    ({"max_epochs": "ten"}, "max_epochs: expected int"),
    ({"run_name": "a/b"}, "trainer.run_name"),
    ({"max_epochs": -1, "max_steps": -1}, "set at least one"),
    ({"monitor_mode": "lowest"}, "monitor_mode: expected one of \\[.min., .max.\\]"),
])
def test_bad_trainer_config_names_the_key(data, message):
    with pytest.raises(DegustaError, match=message):
        from_dict(TrainerConfig, data)


@pytest.mark.parametrize("strategy", ["ddp_spawn", "ddp_spawn_find_unused_parameters_true"])
def test_spawn_strategies_are_refused_before_the_run(strategy):
    """ddp_spawn pickles the run: it died inside Lightning with a PicklingError traceback."""
    from degusta_learn.training import check_trainer

    with pytest.raises(DegustaError, match=rf"^trainer.strategy: '{strategy}' pickles the whole run.*use ddp"):
        check_trainer(from_dict(TrainerConfig, {"strategy": strategy, "accelerator": "cpu", "devices": 1}))


def test_val_check_interval_keeps_int_and_float():
    assert from_dict(TrainerConfig, {"val_check_interval": 50}).val_check_interval == 50
    assert isinstance(from_dict(TrainerConfig, {"val_check_interval": 0.5}).val_check_interval, float)


@pytest.mark.parametrize("native, accelerator, precision, expected", [
    (False, "cpu", "bf16-mixed", "32-true"),   # emulated bfloat16: ~60x slower than float32 on an AVX2 CPU
    (False, "cpu", "bf16", "32-true"),
    (True, "cpu", "bf16-mixed", "bf16-mixed"),  # AVX512-BF16 / AMX: kept
    (False, "cpu", "32-true", "32-true"),
    (False, "gpu", "bf16-mixed", "bf16-mixed"),  # a GPU's own business
])
def test_bfloat16_on_a_cpu_without_native_support_trains_in_float32(monkeypatch, capsys, native, accelerator,
                                                                     precision, expected):
    from degusta_learn.training import run_precision

    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: native)
    cfg = TrainerConfig(accelerator=accelerator, precision=precision)
    assert run_precision(cfg) == expected
    assert ("no native bfloat16" in capsys.readouterr().err) == (expected != precision)


def test_a_step_on_fewer_torch_threads_gives_them_back():
    from degusta_learn.training import torch_threads

    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("a failed step")
    assert torch.get_num_threads() == before


def _fresh_python(code: str, **env: str):
    """Run `code` in a new interpreter whose environment has none of the kernel variables (plus `env`)."""
    import os
    import subprocess
    import sys

    from degusta_learn.training import AVX2_KERNELS

    clean = {k: v for k, v in os.environ.items() if k not in AVX2_KERNELS} | env
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1], done.stderr


PIN = "from degusta_learn.training import pin_cpu_kernels; print(pin_cpu_kernels({!r}))"


@pytest.mark.skipif(not x86_with_avx2(), reason="cpu_kernels: avx2 caps x86 kernels; this CPU has none to cap")
def test_cpu_kernels_avx2_caps_a_fresh_process_and_says_where_it_comes_too_late():
    native, _ = _fresh_python("import torch; print(torch.backends.cpu.get_cpu_capability())")
    assert _fresh_python(PIN.format("native"))[0] == native  # the default leaves the kernels be
    kernels, err = _fresh_python(PIN.format("avx2"))
    assert kernels == "AVX2" and "trainer.cpu_kernels" not in err
    # torch ran an operation first: the kernels are fixed, the run goes on with them and says so (where they differ)
    kernels, err = _fresh_python("import torch; torch.ones(2).add_(1); " + PIN.format("avx2"))
    assert kernels == native
    assert ("this process ran torch before the run began" in err) == (native != "AVX2"), err
    # a variable the user set wins, and the note names it
    kernels, err = _fresh_python(PIN.format("avx2"), ATEN_CPU_CAPABILITY="default")
    assert kernels == "DEFAULT" and "ATEN_CPU_CAPABILITY=default in the environment" in err
    with pytest.raises(DegustaError, match=r"trainer.cpu_kernels: expected one of \['native', 'avx2'\]"):
        from_dict(TrainerConfig, {"cpu_kernels": "avx512"}, prefix="trainer.")
