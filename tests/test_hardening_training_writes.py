"""Training under a failing disk and under signals (issue "Hardening, second pass", items 1 and 2).

Writes: a full disk (ENOSPC), a quota (EDQUOT), a read-only disk (EROFS) or a file-size limit (EFBIG) during any
write of a run (a checkpoint through our atomic IO, the final save, the CSV / TensorBoard loggers, hparams.yaml,
config.yaml, an export) ends `degusta train` with exit 2 and ONE line naming the file and the cause, and the
previous last.ckpt is loadable, metrics.csv is still readable, no temp file is left, and the run resumes once
the fault is gone. A real file-size limit (RLIMIT_FSIZE in a subprocess) does the same.

Signals: a SIGTERM (real signal, to a real `degusta train` subprocess and in-process) or a Ctrl-C ends the run
with 143 / 130 and one line, last.ckpt intact and the run resumable; a SIGTERM with no handler of ours (a library
caller) still raises instead of returning as if training had finished. Runs are the tiniest learned model.
"""

from __future__ import annotations

import errno
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning.pytorch  # noqa: F401  (imported now: its log handler must bind the real stderr, not a test's)
import pytest
import torch
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from conftest import make_small_dataset  # noqa: E402

from degusta_learn import cli  # noqa: E402
from degusta_learn.errors import Terminated  # noqa: E402
from degusta_learn.scene import save_dataset  # noqa: E402
from degusta_learn.training import TMP_PREFIX, validation_curve  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")
CONFIGS = Path(__file__).parent.parent / "configs"


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    return save_dataset(make_small_dataset(), tmp_path_factory.mktemp("writes") / "data")


def learned_yaml(tmp_path: Path, data: Path, **trainer) -> Path:
    cfg = {"kind": "learned", "num_threads": 1, "dataset": str(data),
           "data": {"batch_size": 8, "repeats": 1, "val_contexts": [2]},
           "model": {"d_model": 16, "n_layers": 1, "n_heads": 2, "d_ff": 32, "max_objects": 8},
           "trainer": {"run_dir": str(tmp_path / "runs"), "run_name": "tiny", "max_epochs": -1, "max_steps": 2,
                       "val_check_interval": 1, "accelerator": "cpu", "devices": 1, "progress_bar": False,
                       "log_every_n_steps": 1, **trainer}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def train(config: Path, *overrides: str) -> int:
    return cli.main(["train", "--config", str(config), *[a for o in overrides for a in ("--set", o)]])


def step_of(ckpt: Path) -> int:
    return int(torch.load(ckpt, map_location="cpu", weights_only=True)["global_step"])


def degusta_lines(text: str) -> list[str]:
    return [line for line in text.strip().splitlines() if line.startswith("degusta: ")]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, data_root) -> Path:
    """A run of 2 steps (last.ckpt at step 2), copied by each test that resumes it under a fault."""
    base = tmp_path_factory.mktemp("finished")
    assert train(learned_yaml(base, data_root)) == 0
    return base


def copy_run(finished: Path, tmp_path: Path, data: Path) -> Path:
    """`finished`'s run folder copied into tmp_path/runs, with a config that trains there; returns the run folder."""
    shutil.copytree(finished / "runs", tmp_path / "runs")
    learned_yaml(tmp_path, data)
    return tmp_path / "runs" / "tiny"


def _fd_path(fd: int) -> str:
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return ""


def _raise(code: int):
    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code))
    return fail


def _fault(monkeypatch, mode: str) -> tuple[str, str]:
    """Install the fault `mode`; returns (the file the error must name, the cause it must give)."""
    import csv
    import tempfile

    import lightning

    real_fsync, real_replace, real_mkstemp, real_save = os.fsync, os.replace, tempfile.mkstemp, torch.save
    if mode == "checkpoint_enospc":
        monkeypatch.setattr(torch, "save", _raise(errno.ENOSPC))
        return "last.ckpt", "No space left on device"
    if mode == "checkpoint_torch_runtime_error":  # torch.save wraps a failed write, keeping the OSError as context
        def save(obj, f, *args, **kwargs):
            try:
                raise OSError(errno.EFBIG, "File too large")
            except OSError:  # torch raises it this way: the OSError is only the context
                raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")  # noqa: B904
        monkeypatch.setattr(torch, "save", save)
        return "last.ckpt", "File too large"
    if mode == "checkpoint_torch_error_without_cause":  # torch.save to a path loses the OSError altogether
        def save(obj, f, *args, **kwargs):
            raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")
        monkeypatch.setattr(torch, "save", save)
        return "last.ckpt", "the write failed"
    if mode == "checkpoint_fsync_edquot":
        monkeypatch.setattr(os, "fsync", lambda fd: (_raise(errno.EDQUOT)() if TMP_PREFIX in _fd_path(fd)
                                                     else real_fsync(fd)))
        return "last.ckpt", "Disk quota exceeded"
    if mode == "checkpoint_tempfile_enospc":
        def mkstemp(*args, **kwargs):
            if str(kwargs.get("prefix", "")).startswith(TMP_PREFIX + "last"):
                _raise(errno.ENOSPC)()
            return real_mkstemp(*args, **kwargs)
        monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
        return "last.ckpt", "No space left on device"
    if mode == "checkpoint_rename_erofs":
        monkeypatch.setattr(os, "replace", lambda src, dst, **kw: (_raise(errno.EROFS)() if TMP_PREFIX in str(src)
                                                                  else real_replace(src, dst, **kw)))
        return "ckpt", "Read-only file system"
    if mode == "final_save_enospc":  # only the save at the end of fit fails
        real = lightning.Trainer.save_checkpoint

        def save_checkpoint(self, *args, **kwargs):
            if "weights_only" in kwargs:
                monkeypatch.setattr(torch, "save", _raise(errno.ENOSPC))
            try:
                return real(self, *args, **kwargs)
            finally:
                monkeypatch.setattr(torch, "save", real_save)
        monkeypatch.setattr(lightning.Trainer, "save_checkpoint", save_checkpoint)
        return "last.ckpt", "No space left on device"
    if mode == "csv_rows_enospc":
        monkeypatch.setattr(csv.DictWriter, "writerows", _raise(errno.ENOSPC))
        return "csv", "No space left on device"
    if mode == "csv_header_efbig":
        monkeypatch.setattr(csv.DictWriter, "writeheader", _raise(errno.EFBIG))
        return "csv", "File too large"
    if mode == "tensorboard_enospc":  # fails in TensorBoard's writer thread, surfaces at the next write
        from tensorboard.summary.writer import record_writer

        monkeypatch.setattr(record_writer.RecordWriter, "write", _raise(errno.ENOSPC))
        return "tb", "No space left on device"
    if mode == "hparams_yaml_enospc":
        import lightning.pytorch.loggers.csv_logs as csv_logs

        monkeypatch.setattr(csv_logs, "save_hparams_to_yaml", _raise(errno.ENOSPC))
        return "csv", "No space left on device"
    if mode == "config_yaml_enospc":
        monkeypatch.setattr(os, "fsync", lambda fd: (_raise(errno.ENOSPC)() if "config.yaml" in _fd_path(fd)
                                                     else real_fsync(fd)))
        return "config.yaml", "No space left on device"
    raise AssertionError(mode)


WRITE_FAULTS = ["checkpoint_enospc", "checkpoint_torch_runtime_error", "checkpoint_torch_error_without_cause",
                "checkpoint_fsync_edquot",
                "checkpoint_tempfile_enospc", "checkpoint_rename_erofs", "final_save_enospc", "csv_rows_enospc",
                "csv_header_efbig", "tensorboard_enospc", "hparams_yaml_enospc", "config_yaml_enospc"]


@pytest.mark.parametrize("mode", WRITE_FAULTS)
def test_a_failed_write_while_training_is_one_line_and_keeps_the_last_checkpoint(tmp_path, finished_run, data_root,
                                                                                monkeypatch, capfd, mode):
    run = copy_run(finished_run, tmp_path, data_root)
    before = (run / "last.ckpt").read_bytes()
    names, cause = _fault(monkeypatch, mode)
    capfd.readouterr()
    assert train(tmp_path / "tiny.yaml", "trainer.max_steps=4") == 2
    lines = degusta_lines(capfd.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("degusta: error: "), lines
    assert names in lines[0] and cause in lines[0] and "cannot write" in lines[0], lines[0]
    if mode != "config_yaml_enospc":
        assert "training stopped" in lines[0] and "re-run to resume" in lines[0], lines[0]
    monkeypatch.undo()
    assert step_of(run / "last.ckpt") >= 2  # the previous checkpoint (or a later complete one), loadable
    if mode != "final_save_enospc":
        assert (run / "last.ckpt").read_bytes() == before or step_of(run / "last.ckpt") > 2
    assert not list(run.rglob(f"{TMP_PREFIX}*"))
    validation_curve(run, "val/rmsd")  # metrics.csv of every version still parses
    assert train(tmp_path / "tiny.yaml", "trainer.max_steps=4") == 0  # the fault gone: it resumes
    assert step_of(run / "last.ckpt") == 4
    steps = [r["step"] for r in validation_curve(run, "val/rmsd")]
    assert steps == sorted(set(steps)) and steps[-1] == 3  # every validation once; the resumed ones are read too


def test_a_failed_csv_append_is_cut_back_to_its_last_complete_row(tmp_path, finished_run, data_root, monkeypatch):
    """A write that fails halfway through a row (the disk filled mid-write) leaves metrics.csv as it was."""
    import csv

    copy_run(finished_run, tmp_path, data_root)
    real = csv.DictWriter.writerows
    calls = []

    def half(self, rows):
        calls.append(1)
        if len(calls) > 1:  # the second save of the resumed run: write a partial row, then fail
            self.writer.writerow(["0.5", "0."])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, rows)

    monkeypatch.setattr(csv.DictWriter, "writerows", half)
    assert train(tmp_path / "tiny.yaml", "trainer.max_steps=4") == 2
    monkeypatch.undo()
    for path in (tmp_path / "runs" / "tiny" / "csv").glob("version_*/metrics.csv"):
        text = path.read_text()
        assert "0.5,0." not in text and (not text or text.endswith("\n")), text
    validation_curve(tmp_path / "runs" / "tiny", "val/rmsd")


def test_a_real_file_size_limit_is_one_line_and_keeps_the_last_checkpoint(tmp_path, finished_run, data_root):
    """RLIMIT_FSIZE in a subprocess: the kernel's SIGXFSZ would kill the process, but Python ignores it, so the
    write fails with EFBIG; the checkpoint (larger than the limit) is refused in one line naming the limit."""
    run = copy_run(finished_run, tmp_path, data_root)
    before = (run / "last.ckpt").read_bytes()
    limit = len(before) // 2

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))  # SIGXFSZ left as the child's Python sets it

    r = subprocess.run([sys.executable, "-m", "degusta_learn.cli", "train", "--config", str(tmp_path / "tiny.yaml"),
                        "--set", "trainer.max_steps=4"], capture_output=True, text=True, preexec_fn=limited,
                       timeout=300)
    lines = degusta_lines(r.stderr)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert len(lines) == 1 and ".ckpt: cannot write the checkpoint (File too large" in lines[0], lines  # best or last
    assert f"ulimit -f) is {limit:,} bytes" in lines[0], lines[0]
    assert (run / "last.ckpt").read_bytes() == before and not list(run.glob(f"{TMP_PREFIX}*"))


def test_a_failed_export_write_is_one_line(tmp_path, monkeypatch, capfd):
    """A VLM trainer's export (safetensors raises its own SafetensorError) through files.folders.write_folder."""
    import safetensors.torch
    from safetensors import SafetensorError
    from test_hardening_training import _vlm_overrides

    def full(*args, **kwargs):
        raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")

    overrides = _vlm_overrides("finetune", tmp_path, "a")  # builds the tiny model first (safetensors too)
    monkeypatch.setattr(safetensors.torch, "serialize_file", full)
    capfd.readouterr()
    assert train(CONFIGS / "finetune_tiny_cpu.yaml", *overrides) == 2
    lines = degusta_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "adapter: cannot write the model folder (No space left on device)" in lines[0], lines
    assert not list((tmp_path / "runs" / "a").glob(".adapter*.tmp"))


# ---------------------------------------------------------------- signals
def _stop_at_step(monkeypatch, step: int, how: str) -> None:
    """Make the learned module's training step `step` deliver `how`: a real SIGTERM / SIGINT to this process,
    or raise KeyboardInterrupt."""
    from degusta_learn.baselines.learned.module import LearnedModule

    real = LearnedModule.training_step

    def training_step(self, batch, batch_idx):
        if self.global_step == step:
            if how == "sigterm":
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.5)  # the handler runs at the next bytecode; never return first
            elif how == "keyboard":
                raise KeyboardInterrupt
        return real(self, batch, batch_idx)

    monkeypatch.setattr(LearnedModule, "training_step", training_step)


@pytest.mark.parametrize("how, status", [("sigterm", 143), ("keyboard", 130)])
def test_an_interrupted_run_exits_with_the_signal_status_in_one_line_and_resumes(tmp_path, data_root, monkeypatch,
                                                                                capfd, how, status):
    cfg = learned_yaml(tmp_path, data_root, max_steps=50)
    _stop_at_step(monkeypatch, 3, how)
    capfd.readouterr()
    assert train(cfg) == status
    err = capfd.readouterr().err
    lines = degusta_lines(err)
    assert len(lines) == 1 and ("terminated (SIGTERM)" if how == "sigterm" else "interrupted") in lines[0], err
    assert "Detected KeyboardInterrupt" not in err and "Traceback" not in err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # Lightning set it to "ignore"
    run = tmp_path / "runs" / "tiny"
    assert step_of(run / "last.ckpt") == 3  # the last validation's checkpoint, complete
    monkeypatch.undo()
    assert train(cfg, "trainer.max_steps=5") == 0
    assert step_of(run / "last.ckpt") == 5


def test_a_sigterm_without_a_handler_of_ours_raises_instead_of_returning(tmp_path, data_root, monkeypatch):
    """A library caller (no CLI): Lightning's own SIGTERM handler only flags the signal and its loop ended the run
    with a SystemExit of status 0, as if it had finished; the harness raises Terminated instead, no export."""
    from degusta_learn.methods import run_train

    assert signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None)
    cfg = learned_yaml(tmp_path, data_root, max_steps=50)
    _stop_at_step(monkeypatch, 3, "sigterm")  # delivered while Lightning's handler is installed (inside fit)
    with pytest.raises(Terminated):
        run_train(cfg, [])
    assert signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None)  # Lightning's handler is gone again
    assert step_of(tmp_path / "runs" / "tiny" / "last.ckpt") in (3, 4)


def test_sigterm_to_a_real_training_process_exits_143_and_the_run_resumes(tmp_path, data_root, capfd):
    """`degusta train` as a user runs it, SIGTERM'd while it trains; a second run into the same folder while it
    trains is refused in one line naming it (pid, command); afterwards the run resumes."""
    cfg = learned_yaml(tmp_path, data_root, max_steps=100_000)
    run = tmp_path / "runs" / "tiny"
    proc = subprocess.Popen([sys.executable, "-m", "degusta_learn.cli", "train", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not (run / "last.ckpt").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        capfd.readouterr()
        assert train(cfg, "trainer.max_steps=3") == 2  # the folder is in use
        refusal = degusta_lines(capfd.readouterr().err)
        assert len(refusal) == 1 and f"{run}: pid {proc.pid} (" in refusal[0] and "is writing this run folder" in \
            refusal[0] and "train --config" in refusal[0], refusal
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    lines = degusta_lines(err)
    assert proc.returncode == 143 and "Traceback" not in err, err[-3000:]
    assert len(lines) == 1 and lines[0].startswith("degusta: terminated (SIGTERM)"), err[-3000:]
    assert "Detected KeyboardInterrupt" not in err
    step = step_of(run / "last.ckpt")
    assert not list(run.glob(f"{TMP_PREFIX}*"))
    assert train(cfg, f"trainer.max_steps={step + 2}") == 0
    assert step_of(run / "last.ckpt") == step + 2


@pytest.mark.parametrize("validate", [True, False])
def test_last_ckpt_follows_every_validation_or_else_every_epoch(tmp_path, validate):
    """`val_check_interval: 1` (every batch) is not "once an epoch" (Lightning compares it with 1.0): last.ckpt is
    rewritten after every validation, so an interrupted run loses at most one step; with no validation at all it
    is written at every epoch's end."""
    from lightning.pytorch.callbacks import Callback
    from test_trainer import Toy, ToyData

    from degusta_learn.training import TrainerConfig, fit

    seen = {}

    class Watch(Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            last = tmp_path / "toy" / "last.ckpt"
            seen[trainer.global_step] = step_of(last) if last.exists() else None

    data = ToyData()
    if not validate:
        data.val_dataloader = None  # no validation loop
    cfg = TrainerConfig(run_dir=str(tmp_path), run_name="toy", max_epochs=-1, max_steps=6, accelerator="cpu",
                        devices=1, progress_bar=False, val_check_interval=1, monitor="val/rmsd" if validate else None,
                        loggers=[])
    fit(Toy(), data, cfg, full_config={"kind": "toy"}, callbacks=[Watch()])
    expected = {0: None, 1: 1, 2: 2, 3: 3, 4: 4, 5: 5} if validate else {0: None, 1: None, 2: None, 3: None, 4: 4, 5: 4}
    assert seen == expected
