"""Shared Lightning training harness: run folders, loggers, checkpoints, resume, `fit`.

Every trainer of the toolkit (the learned arrangement model, VLM fine-tuning) embeds a `TrainerConfig`
under its config's `trainer:` section and calls `fit(module, datamodule, cfg.trainer, full_config)`.
Every trainer's `run` wraps its whole body in `with training_run(cfg.trainer, monitors=...)`: it checks
the trainer values first (accelerator present, devices, precision, strategy, that `monitor` is a key the
module logs; one-line errors naming the key), then seeds Python / numpy / torch *before* any model or data
is built (same seed, same initial weights), and removes the run folder again if it created it and a user
mistake stops the run before its first checkpoint.

What `fit` does, in order:

0. `check_trainer` again and `build_trainer` (Lightning's own complaints become one-line errors) — before
   anything is written.
1. `prepare_run_dir`: makes `<run_dir>/<run_name>/` (default `checkpoints/<run>/`) and writes the resolved
   config there as `config.yaml` (atomically). A folder that already holds `last.ckpt` is resumed when
   `resume: true` (its `config.yaml` must agree with the new one outside the `trainer` section) and refused
   otherwise, so an interrupted run is never overwritten by accident. Paths in the two configs are compared
   resolved (`data/x` and `/abs/data/x` are the same dataset). A truncated or corrupt `last.ckpt` is
   detected before Lightning reads it: the run resumes from `best.ckpt` with a printed note, or is refused
   with a one-line message naming the file when no good checkpoint is left.
2. `seed_everything(seed, workers=True)` (again: the data order of a resumed run is seeded too).
3. `build_trainer`: a `lightning.Trainer` with the loggers of `loggers` (default CSV + TensorBoard,
   `csv/version_N`, `tb/version_N`: a resumed run opens a new version, earlier logs are kept; W&B / MLflow
   offline into the run folder by default, `tracking_offline`), two `ModelCheckpoint`s writing `best.ckpt`
   (best by `monitor`, e.g. validation set RMSD, decided right after each validation) and `last.ckpt`
   (after every validation, improving or not), optionally `EarlyStopping` on the same monitor
   (`early_stopping_patience`: validations without improvement), a progress bar, and the accelerator /
   devices / strategy / precision from the config — multi-GPU is `devices: 4, strategy: ddp`, no code change.
4. `trainer.fit(..., ckpt_path=last.ckpt if resuming, weights_only=True)`; `last.ckpt` is written after
   every validation and once more when training ends, so a run stopped by a crash or Ctrl-C resumes from
   its last validation and a finished run can be extended with a larger `max_epochs` / `max_steps`.
   Every checkpoint is written atomically *inside the run folder* (`AtomicCheckpointIO`: a hidden temp file
   beside it, fsync, `os.replace`), so a kill at any moment leaves the previous complete checkpoint.
   Ctrl-C and SIGTERM, which Lightning catches and turns into an exit status of 1 (or 0), are raised again
   (`_fit_or_interrupt`): the CLI exits 130 / 143 with one line, nothing is exported, the run resumes.
   A failed write anywhere in the run (a full disk, a file-size limit: checkpoints, loggers, config.yaml) is one
   DegustaError naming the file and the cause (degusta_learn/writeerrors.py); the previous last.ckpt stays whole.

The run folder is locked for the whole run (`training_run` and `fit`, rank 0; degusta_learn/locks.py: a lock
file `.<run_name>.degusta-lock` beside it): a second run into the same folder is refused in one line naming the
first (pid, command, start time), and never removes a folder the first one made.

Checkpoints must load weights-only: a LightningModule that calls `save_hyperparameters` must pass plain
dicts / lists / numbers / strings only (e.g. `dataclasses.asdict(cfg)`), never dataclasses or Paths.

Usage:
    from degusta_learn.trainer import TrainerConfig, fit
    run_dir = fit(module, datamodule, TrainerConfig(run_name="demo", max_epochs=3), full_config=cfg)
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import shutil
import signal
import sys
import threading
import tempfile
import warnings
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from degusta_learn.config import bounded, check_choices, dump_yaml, read_yaml, seed_field, to_dict
from degusta_learn.errors import DegustaError, MachineMismatch, Terminated
from degusta_learn.fileio import atomic_write_text
from degusta_learn.locks import hold, remove_made
from degusta_learn.writeerrors import writing

LAST = "last.ckpt"
BEST = "best.ckpt"
TMP_PREFIX = ".tmp-"
"""Prefix of the temp files checkpoints are written to before `os.replace` (stale ones are removed)."""
ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps", "tpu")
PRECISIONS = ("32-true", "32", "64-true", "64", "16-mixed", "16", "bf16-mixed", "bf16", "16-true", "bf16-true",
              "transformer-engine", "transformer-engine-float16")
MAX_DEVICES = 4096
LOGGERS = {"csv": None, "tensorboard": None, "wandb": "wandb", "mlflow": "mlflow"}
"""`trainer.loggers` choices -> the module an optional one needs (installed by the extra of the same name)."""


@dataclass
class TrainerConfig:
    """The `trainer:` section of every train config (Lightning settings + where the run is written)."""

    run_name: str = "run"
    """Run folder name: outputs go to `<run_dir>/<run_name>/`."""
    run_dir: str = "checkpoints"
    """Parent folder of run folders."""
    resume: bool = True
    """Continue from `<run>/last.ckpt` when it exists (false: refuse to reuse a folder that has one)."""
    seed: int = seed_field()
    """Seed for Python, numpy, torch and data-loader workers."""
    max_epochs: int = bounded(10, 1, 1_000_000, special=(-1,))
    """Stop after this many epochs (-1: no epoch limit, use max_steps)."""
    max_steps: int = bounded(-1, 1, 1_000_000_000, special=(-1,))
    """Stop after this many optimizer steps (-1: no step limit)."""
    accelerator: str = "auto"
    """"cpu", "gpu", "auto" (GPU when present)."""
    devices: Any = "auto"
    """Devices per node: a number (GPUs, or CPU processes: at most os.cpu_count()), a list of GPU indices, or "auto"."""
    num_nodes: int = bounded(1, 1, 100_000)
    """Machines of a multi-node run (launched by torchrun or SLURM `srun`; see docs/finetune.md)."""
    strategy: str = "auto"
    """Lightning strategy: "auto", "ddp", "ddp_fork", "fsdp", ... (multi-GPU needs no code change; the
    "ddp_spawn" family is refused: it pickles the run)."""
    precision: str = "32-true"
    """"32-true", "bf16-mixed" (GPU), "16-mixed" (GPU)."""
    cpu_kernels: Literal["native", "avx2"] = "native"
    """Which x86 kernels torch, oneDNN and MKL compute with on the CPU: "native", the widest this CPU has (AVX-512
    where present), or "avx2", capped at AVX2 (what most CPUs run). Rounding differs between them and takes a run
    elsewhere: the pretraining recipe's builds met the fine-tuned route's bars with AVX2 kernels and failed them with
    AVX-512 ones (docs/tiny_base.md, point 46), so its config asks for avx2. Kernels are chosen once per process, at
    torch's first CPU operation: `degusta train` asks before it; a process that ran torch earlier keeps its kernels,
    with a note. No effect off x86 or on a CPU without AVX2."""
    accumulate_grad_batches: int = bounded(1, 1, 10_000)
    """Gradient accumulation: effective batch = batch_size * this * devices * num_nodes."""
    gradient_clip_val: float | None = bounded(1.0, 0.0)
    """Clip the gradient norm to this (null: no clipping)."""
    log_every_n_steps: int = bounded(10, 1, 1_000_000_000)
    """How often training losses are logged."""
    val_check_interval: int | float = 1.0
    """Validate every this fraction of an epoch (float) or number of batches (int); the step that reaches
    `max_steps` validates too, wherever it falls."""
    check_val_every_n_epoch: int = bounded(1, 1, 1_000_000)
    """Validate every this many epochs."""
    monitor: str | None = "val/rmsd"
    """Metric that picks best.ckpt (null: only last.ckpt)."""
    monitor_mode: Literal["min", "max"] = "min"
    """"min" or "max" for `monitor`."""
    early_stopping_patience: int | None = bounded(None, 1, 1_000_000)
    """Stop after this many validations in a row without a better `monitor` (null: never stop early)."""
    early_stopping_min_delta: float = bounded(0.0, 0.0)
    """How much `monitor` must improve to count as better for early stopping (0: any improvement)."""
    progress_bar: bool = True
    """Show Lightning's progress bar."""
    num_sanity_val_steps: int = bounded(0, 0, 1_000_000, special=(-1,))
    """Validation batches run before training as a smoke check (0: none)."""
    loggers: list[str] = field(default_factory=lambda: ["csv", "tensorboard"])
    """Where metrics go, any of csv (`<run>/csv/`), tensorboard (`<run>/tb/`), wandb, mlflow (optional packages:
    `pip install 'degusta_learn[tracking]'`); see `tracking_offline`."""
    tracking_offline: bool = True
    """wandb / mlflow write only into the run folder: W&B offline mode (`<run>/wandb/`, `wandb sync` uploads it
    later), an MLflow file store `file:<run>/mlruns` (`mlflow ui --backend-store-uri <run>/mlruns`). false:
    W&B logs to its server (`wandb login`), MLflow to MLFLOW_TRACKING_URI (required)."""

    def __post_init__(self):
        check_choices(self, "trainer")
        if (not self.run_name or any(c in self.run_name for c in "/\\\0") or self.run_name in (".", "..")
                or len(self.run_name) > 200):
            raise DegustaError(f"trainer.run_name: expected a plain folder name, got {self.run_name[:80]!r}")
        if not self.run_dir or "\0" in self.run_dir:
            raise DegustaError(f"trainer.run_dir: expected a folder path, got {self.run_dir[:80]!r}")
        if self.max_epochs == -1 and self.max_steps == -1:
            raise DegustaError("trainer.max_epochs / trainer.max_steps: set at least one of them (not both -1)")
        if isinstance(self.num_nodes, bool) or not isinstance(self.num_nodes, int) or self.num_nodes < 1:
            raise DegustaError(f"trainer.num_nodes: expected a number of machines >= 1, got {self.num_nodes!r}")
        if self.accumulate_grad_batches < 1:
            raise DegustaError(f"trainer.accumulate_grad_batches: expected >= 1, got {self.accumulate_grad_batches}")
        if self.accelerator not in ACCELERATORS:
            raise DegustaError(f"trainer.accelerator: expected one of {', '.join(ACCELERATORS)}, "
                               f"got {self.accelerator[:40]!r}")
        if self.precision not in PRECISIONS:
            raise DegustaError(f"trainer.precision: expected one of {', '.join(PRECISIONS[:10])}, "
                               f"got {self.precision[:40]!r}")
        self.devices = _check_devices(self.devices)
        vci = self.val_check_interval
        if isinstance(vci, float) and not 0.0 < vci <= 1.0:
            raise DegustaError(f"trainer.val_check_interval: a fraction of an epoch must be in (0, 1], got {vci} "
                               f"(or give a whole number of batches)")
        if isinstance(vci, int) and not 1 <= vci <= 1_000_000_000:
            raise DegustaError(f"trainer.val_check_interval: expected a number of batches >= 1, got {vci}")
        if self.monitor is not None and not self.monitor.strip():
            raise DegustaError("trainer.monitor: expected a logged metric name (or null), got ''")
        if self.early_stopping_patience is not None and self.monitor is None:
            raise DegustaError("trainer.early_stopping_patience: early stopping watches trainer.monitor, which is "
                               "null; name a validation metric in trainer.monitor or set the patience to null")
        if not self.strategy or not isinstance(self.strategy, str):
            raise DegustaError(f"trainer.strategy: expected a Lightning strategy name, got {self.strategy!r}")
        self.loggers = _check_logger_names(self.loggers)

    @property
    def path(self) -> Path:
        """The run folder `<run_dir>/<run_name>`."""
        return Path(self.run_dir) / self.run_name


def _check_devices(devices: Any) -> Any:
    """`devices` as Lightning takes it: "auto", a count >= 1 (-1: all), or a list of device indices."""
    bad = DegustaError(f"trainer.devices: expected \"auto\", a number of devices (1..{MAX_DEVICES}, -1: all) "
                       f"or a list of device indices, got {str(devices)[:40]!r}")
    if isinstance(devices, str):
        text = devices.strip()
        if text == "auto":
            return "auto"
        try:
            parts = [int(p) for p in text.split(",") if p.strip()]
        except ValueError:
            raise bad from None
        if not parts:
            raise bad
        devices = parts[0] if len(parts) == 1 and "," not in text else parts
    if isinstance(devices, bool):
        raise bad
    if isinstance(devices, int):
        if devices == -1 or 1 <= devices <= MAX_DEVICES:
            return devices
        raise bad
    if isinstance(devices, (list, tuple)) and devices and len(devices) <= MAX_DEVICES and all(
            isinstance(d, int) and not isinstance(d, bool) and 0 <= d < MAX_DEVICES for d in devices) \
            and len(set(devices)) == len(devices):
        return list(devices)
    raise bad


def check_trainer(cfg: TrainerConfig, monitors: Iterable[str] | None = None) -> None:
    """Check what only this machine and the module can tell: the accelerator is present, enough devices,
    a known strategy, a precision this accelerator runs, and (given the keys the module logs) the monitor.

    Raises `MachineMismatch` (a `DegustaError`) for what this machine lacks (a GPU, cores, a logger package, a
    launcher) and `DegustaError` for a config mistake (an unknown strategy or monitor), each naming the
    `trainer.` key; writes nothing.
    """
    import torch

    acc = cfg.accelerator
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if acc in ("gpu", "cuda") and gpus == 0:
        raise MachineMismatch(f"trainer.accelerator: {acc!r} but no CUDA GPU is available on this machine; "
                           f"use trainer.accelerator=cpu (or auto)")
    if acc == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise MachineMismatch("trainer.accelerator: 'mps' but Apple MPS is not available here; use cpu (or auto)")
    if acc == "tpu":
        try:
            import torch_xla  # noqa: F401
        except ImportError:
            raise MachineMismatch("trainer.accelerator: 'tpu' but no TPU runtime (torch_xla) is installed; "
                               "use cpu (or auto)") from None
    on_gpu = acc in ("gpu", "cuda") or (acc == "auto" and gpus > 0)
    if on_gpu:
        wanted = cfg.devices if isinstance(cfg.devices, int) else len(cfg.devices) if isinstance(cfg.devices, list) else 0
        top = max(cfg.devices) + 1 if isinstance(cfg.devices, list) else wanted
        if wanted > gpus or top > gpus:
            raise MachineMismatch(f"trainer.devices: {cfg.devices} asks for more GPUs than the {gpus} available here")
    else:
        _check_cpu_devices(cfg)
    if cfg.num_nodes > 1 or cfg.strategy != "auto" or world_size(cfg) > 1:
        _check_cluster(cfg)
    if cfg.precision.startswith("transformer-engine") and not on_gpu:
        raise MachineMismatch(f"trainer.precision: {cfg.precision!r} needs a GPU; use 32-true or bf16-mixed on CPU")
    if cfg.precision in ("16-true", "16") and not on_gpu:
        raise MachineMismatch(f"trainer.precision: {cfg.precision!r} (float16) needs a GPU; use 32-true or bf16-mixed on CPU")
    if cfg.strategy != "auto":
        from lightning.pytorch.strategies import StrategyRegistry

        names = StrategyRegistry.available_strategies()
        if cfg.strategy not in names:
            raise DegustaError(f"trainer.strategy: unknown strategy {cfg.strategy[:40]!r} (use auto, ddp, ddp_fork, "
                               f"fsdp, deepspeed, ...)")
        if cfg.strategy.startswith("ddp_spawn"):  # was a PicklingError traceback from inside Lightning
            raise DegustaError(f"trainer.strategy: {cfg.strategy!r} pickles the whole run into new processes, which "
                               f"this harness does not support; use ddp (ranks started from the command line) "
                               f"or ddp_fork")
        if (cfg.strategy.startswith("fsdp") or cfg.strategy.startswith("deepspeed")) and not on_gpu:
            raise MachineMismatch(f"trainer.strategy: {cfg.strategy!r} needs a GPU accelerator; use auto or ddp on CPU")
    _check_logger_packages(cfg)
    if monitors is not None and cfg.monitor is not None:
        known = sorted(set(monitors))
        if cfg.monitor not in known:
            raise DegustaError(f"trainer.monitor: {cfg.monitor[:60]!r} is never logged by this trainer "
                               f"(logged: {', '.join(known)}; or null for last.ckpt only)")


def _check_logger_names(names: Any) -> list[str]:
    """`trainer.loggers` as a list of distinct known names (a single name is taken as a list of one)."""
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise DegustaError(f"trainer.loggers: expected a list of {', '.join(LOGGERS)}, got {str(names)[:60]!r}")
    for n in names:
        if n not in LOGGERS:
            raise DegustaError(f"trainer.loggers: unknown logger {n[:40]!r} (choose from {', '.join(LOGGERS)})")
    if len(set(names)) != len(names):
        raise DegustaError(f"trainer.loggers: {list(names)} names a logger twice")
    return list(names)


def _check_logger_packages(cfg: TrainerConfig) -> None:
    """An optional logger's package is importable here, or one line with the pip command; MLflow online needs
    MLFLOW_TRACKING_URI (Lightning's default would be a `./mlruns` folder wherever the command runs)."""
    import importlib

    for name in cfg.loggers:
        module = LOGGERS[name]
        if module is None:
            continue
        try:
            importlib.import_module(module)
        except ImportError:
            raise MachineMismatch(f"trainer.loggers: {name!r} needs the {module} package, not installed here: "
                               f"pip install 'degusta_learn[{name}]' (or remove {name!r} from trainer.loggers)") from None
    if "mlflow" in cfg.loggers and not cfg.tracking_offline and not os.environ.get("MLFLOW_TRACKING_URI"):
        raise MachineMismatch("trainer.tracking_offline: false sends MLflow runs to MLFLOW_TRACKING_URI, which is not "
                           "set; set it (e.g. http://host:5000) or keep tracking_offline true (<run>/mlruns)")


def build_loggers(cfg: TrainerConfig, run: Path) -> list:
    """Lightning's own loggers for `cfg.loggers`, each writing under `run` (wandb / mlflow: see
    `tracking_offline`). W&B and MLflow name the run `run_name` in the project / experiment "degusta"."""
    made = []
    for name in cfg.loggers:
        if name == "csv":
            from lightning.pytorch.loggers import CSVLogger

            made.append(_guarded(CSVLogger, "CSV log", run / "csv")(save_dir=run, name="csv"))
        elif name == "tensorboard":
            from lightning.pytorch.loggers import TensorBoardLogger

            made.append(_guarded(TensorBoardLogger, "TensorBoard log", run / "tb")(
                save_dir=run, name="tb", default_hp_metric=False))
        elif name == "wandb":
            from lightning.pytorch.loggers import WandbLogger

            made.append(_guarded(WandbLogger, "W&B log", run / "wandb")(
                name=cfg.run_name, project="degusta", save_dir=str(run), offline=cfg.tracking_offline))
        elif name == "mlflow":
            from lightning.pytorch.loggers import MLFlowLogger

            if cfg.tracking_offline:  # MLflow >= 3.x keeps the file store only on this opt-in ("maintenance mode")
                os.environ["MLFLOW_ALLOW_FILE_STORE"] = "true"
                uri = (run / "mlruns").resolve().as_uri()
            else:
                uri = os.environ["MLFLOW_TRACKING_URI"]
            made.append(_guarded(MLFlowLogger, "MLflow log", run / "mlruns")(
                experiment_name="degusta", run_name=cfg.run_name, tracking_uri=uri))
    return made


_GUARDED: dict[type, type] = {}


def _guarded(cls: type, what: str, where: Path) -> Any:
    """A constructor of `cls` (a Lightning logger) whose writes fail in one line (`writeerrors.writing`: "<where>:
    cannot write the <what> (No space left on device); training stopped, <run>/last.ckpt keeps ..."); a failure
    while Lightning finalizes a run that is failing already is dropped (the first error is the one to report).
    The CSV logger's metrics.csv also stays whole: a failed append is cut back to its last complete row and a
    header change rewrites the file atomically (`_SafeMetrics`), so `validation_curve` reads it after a resume."""
    if cls not in _GUARDED:
        def guard(name):
            def method(self, *args, **kwargs):
                with writing(self._degusta_where, self._degusta_what, after=_resume_note(self._degusta_run / LAST)):
                    return getattr(super(sub, self), name)(*args, **kwargs)
            method.__name__ = name
            return method

        def finalize(self, status: str) -> None:
            try:
                with writing(self._degusta_where, self._degusta_what, after=_resume_note(self._degusta_run / LAST)):
                    super(sub, self).finalize(status)
            except DegustaError:
                if status == "success":
                    raise

        def experiment(self):
            with writing(self._degusta_where, self._degusta_what, after=_resume_note(self._degusta_run / LAST)):
                exp = super(sub, self).experiment
            if hasattr(exp, "metrics_file_path") and not isinstance(exp, _SafeMetrics):
                exp.__class__ = _safe_metrics(type(exp))
            return exp

        body = {n: guard(n) for n in ("log_metrics", "log_hyperparams", "log_graph", "save", "after_save_checkpoint")
                if hasattr(cls, n)}
        sub = type(cls.__name__, (cls,), {**body, "finalize": finalize, "experiment": property(experiment),
                                           "__module__": cls.__module__, "__qualname__": cls.__qualname__})
        _GUARDED[cls] = sub
    sub = _GUARDED[cls]

    def make(**kwargs):
        logger = sub(**kwargs)
        logger._degusta_where, logger._degusta_what, logger._degusta_run = where, what, where.parent
        return logger

    return make


class _SafeMetrics:
    """Marks a CSV metrics writer made safe by `_safe_metrics`."""


_SAFE_METRICS: dict[type, type] = {}


def _safe_metrics(base: type) -> type:
    """Lightning's CSV `ExperimentWriter` (appends rows to metrics.csv, rewrites it in place when a new column
    appears) with a metrics.csv that a failed write leaves as it was: the append is cut back to the file's
    previous end (or the new file removed), the rewrite goes through a temp file and `os.replace`."""
    if base in _SAFE_METRICS:
        return _SAFE_METRICS[base]
    import csv

    class SafeMetrics(base, _SafeMetrics):
        def save(self) -> None:
            if not self.metrics:
                return
            path, keys = self.metrics_file_path, list(self.metrics_keys)
            exists = os.path.isfile(path)
            try:
                new_keys = self._record_new_keys()
                if new_keys and exists:
                    self._rewrite_with_new_header(self.metrics_keys)
                size = os.path.getsize(path) if exists else None
                try:
                    with open(path, "a" if exists else "w", newline="", encoding="utf-8") as f:
                        writer = csv.DictWriter(f, fieldnames=self.metrics_keys)
                        if not exists:
                            writer.writeheader()
                        writer.writerows(self.metrics)
                except BaseException:
                    with contextlib.suppress(OSError):
                        if size is None:
                            os.unlink(path)
                        else:
                            os.truncate(path, size)
                    raise
            except BaseException:
                self.metrics_keys[:] = keys  # the header on disk is still the old one
                raise
            self.metrics = []

        def _rewrite_with_new_header(self, fieldnames: list[str]) -> None:
            path = self.metrics_file_path
            with open(path, newline="", encoding="utf-8") as f:
                rows = list(csv.DictReader(f))
            fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=f"{TMP_PREFIX}metrics.csv.")
            try:
                with os.fdopen(fd, "w", newline="", encoding="utf-8") as f:
                    writer = csv.DictWriter(f, fieldnames=fieldnames)
                    writer.writeheader()
                    writer.writerows(rows)
                os.chmod(tmp, 0o666 & ~_umask())
                os.replace(tmp, path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise

    SafeMetrics.__name__ = SafeMetrics.__qualname__ = base.__name__
    _SAFE_METRICS[base] = SafeMetrics
    return SafeMetrics


def _umask() -> int:
    from degusta_learn.fileio import UMASK

    return UMASK


def validation_curve(run: Path, key: str) -> list[dict]:
    """The rows of a run's CSV logs (every `csv/version_*`, so resumed runs too) where `key` was logged, one per
    step (a later version's row wins), by step: {"step": int, "val/...": float} with NaN (not measured) left out."""
    import csv
    import math

    rows: dict[int, dict] = {}
    for path in sorted((Path(run) / "csv").glob("version_*/metrics.csv")):
        with path.open(newline="") as f:
            for row in csv.DictReader(f):
                if not row.get(key):
                    continue
                step = int(float(row["step"]))
                rows[step] = {"step": step, **{k: round(float(v), 4) for k, v in row.items()
                                               if k.startswith("val/") and v not in ("", None)
                                               and math.isfinite(float(v))}}
    return [rows[s] for s in sorted(rows)]


def _check_cpu_devices(cfg: TrainerConfig) -> None:
    """On CPU every device is a process holding a full model copy: a count >= 1, at most the cores here.

    Lightning would start 64 processes for `devices: 64` on a 2-core machine (each one loads the model and
    they time-slice the cores: slower than one process, and memory x 64), so more processes than
    `os.cpu_count()` are refused; -1 ("all") and lists of indices mean GPUs and are refused on CPU too.
    """
    cores = os.cpu_count() or 1
    d = cfg.devices
    if d == "auto":
        return
    if isinstance(d, list) or d == -1:
        raise MachineMismatch(f"trainer.devices: {d} selects GPUs, but this run is on the CPU; give a number of "
                           f"CPU processes (1..{cores}) or use trainer.accelerator=gpu on a GPU machine")
    if d > cores:
        raise MachineMismatch(f"trainer.devices: {d} CPU processes asked for, but this machine has {cores} cores "
                           f"(each process holds a whole model and needs a core); use at most {cores}")


def world_size(cfg: TrainerConfig) -> int:
    """Processes of the run: devices per node x num_nodes ("auto": the visible GPUs, else 1)."""
    d = cfg.devices
    if isinstance(d, list):
        n = len(d)
    elif d in ("auto", -1):
        import torch

        gpu = cfg.accelerator in ("gpu", "cuda", "auto") and torch.cuda.is_available()
        n = torch.cuda.device_count() if gpu else 1
    else:
        n = int(d)
    return n * cfg.num_nodes


def _check_cluster(cfg: TrainerConfig) -> None:
    """A multi-node run needs a launcher that started the other machines' processes (else it would wait for
    them forever); under torchrun / SLURM the world it made must be devices x num_nodes."""
    env = os.environ
    launched = env.get("WORLD_SIZE", "")
    if cfg.num_nodes > 1 and not launched.isdigit() and not env.get("SLURM_NTASKS") and not env.get("MASTER_ADDR"):
        raise MachineMismatch(f"trainer.num_nodes: {cfg.num_nodes} machines, but this process was not started by a "
                           "multi-node launcher (torchrun --nnodes / SLURM srun: no WORLD_SIZE, SLURM_NTASKS or "
                           "MASTER_ADDR); it would wait for the other machines forever. See docs/finetune.md, "
                           "'Multi-GPU and multi-node'")
    want = world_size(cfg)
    if launched.isdigit() and int(launched) > 1 and int(launched) != want:  # torchrun (SLURM: Lightning checks)
        raise MachineMismatch(f"trainer.devices / trainer.num_nodes: the launcher started {launched} processes "
                           f"(WORLD_SIZE) but devices x num_nodes = {want}; make them agree (devices = processes "
                           "per node, num_nodes = machines)")


def global_rank() -> int:
    """This process's rank as the launchers announce it, before any process group exists: torchrun's RANK,
    SLURM_PROCID, or (Lightning's own children) NODE_RANK / LOCAL_RANK, where only 0 / 0 means 0."""
    env = os.environ
    for key in ("RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK"):
        if env.get(key, "").isdigit():
            return int(env[key])
    ranks = [int(env[k]) for k in ("NODE_RANK", "GROUP_RANK", "LOCAL_RANK") if env.get(k, "").isdigit()]
    return 0 if not any(ranks) else max(1, sum(ranks))


def is_global_zero(trainer=None) -> bool:
    """True in the one process that writes files (rank 0), before and after the Trainer exists."""
    if trainer is not None:
        return bool(trainer.is_global_zero)
    return global_rank() == 0


def _trainer_key_in(message: str) -> str | None:
    """The TrainerConfig field a Lightning error message names (as `field` or field=), if any."""
    for f in dataclasses.fields(TrainerConfig):
        if f"`{f.name}`" in message or f"{f.name}=" in message:
            return f.name
    return None


def _first_missing(run: Path) -> Path | None:
    """The outermost folder of `run`'s path that does not exist yet (None: `run` exists)."""
    missing = None
    for p in [run, *run.parents]:
        if p.exists():
            break
        missing = p
    return missing


def _remove_if_empty_run(run: Path, created: Path | None) -> None:
    """Remove a run folder this call created (and the parents it created) when it holds no checkpoint."""
    if created is None or not run.is_dir() or (run / LAST).exists() or (run / BEST).exists():
        return
    shutil.rmtree(run, ignore_errors=True)
    for p in run.parents:  # parents made for it, while empty (never a folder that was there before)
        if p != created and created not in p.parents:
            break
        try:
            p.rmdir()
        except OSError:
            break


@contextlib.contextmanager
def training_run(cfg: TrainerConfig, monitors: Iterable[str] | None = None) -> Iterator[Path]:
    """The frame of every trainer's `run`: check trainer values, seed, and tidy up after a user mistake.

    Asks for the CPU kernels of `cfg.cpu_kernels` (`pin_cpu_kernels`), checks `cfg` (and `monitor` against
    `monitors`, the keys the module logs) before anything is built or written, seeds everything with `cfg.seed`
    *before* the caller builds its model and data (two runs with one seed start from identical weights), and,
    when the body raises DegustaError before the run's first checkpoint, removes the run folder if this call did
    not find it there. Yields the run folder path.
    """
    pin_cpu_kernels(cfg.cpu_kernels)  # first: before any CPU operation of the run fixes the kernels
    check_trainer(cfg, monitors)
    seed_everything(cfg.seed)
    run = cfg.path
    zero = is_global_zero()
    if zero:
        _check_run_dir(cfg)  # a file in the folder's path, a finished run: refused before a lock file is made
    with _run_lock(run, zero) as created, _user_errors(run, created):
        yield run


@contextlib.contextmanager
def _run_lock(run: Path, zero: bool) -> Iterator[Path | None]:
    """Hold the run folder's lock (`locks.hold`: `<run_dir>/.<run_name>.degusta-lock`, rank 0 only) for the whole
    block, so a second run into the same folder is refused in one line naming the first (pid, command, start);
    yields the outermost folder of `run`'s path this run creates (None: none; `_user_errors` removes it after a
    user mistake), and removes the folders made for the lock file once it is released, if they are empty."""
    if not zero:
        yield None
        return
    lock = None
    try:
        with hold(run, "run folder") as lock:
            yield lock.made or _first_missing(run)
    finally:
        if lock is not None:
            remove_made(lock)


@contextlib.contextmanager
def _user_errors(run: Path, created: Path | None) -> Iterator[None]:
    """A DegustaError, or a Lightning ValueError/TypeError naming a trainer key (e.g. val_check_interval >
    batches per epoch), removes the run folder this call `created` (None: keep it) and leaves as one line."""
    try:
        yield
    except DegustaError:
        _remove_if_empty_run(run, created)
        raise
    except (ValueError, TypeError) as e:
        key = _trainer_key_in(str(e))
        if key is None:
            raise
        _remove_if_empty_run(run, created)
        first = " ".join(str(e).split(". ")[0].split())[:240]
        raise DegustaError(f"trainer.{key}: {first}") from None


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch (and data-loader workers) quietly."""
    import lightning as L

    L.seed_everything(seed, workers=True, verbose=False)


def checkpoint_problem(path: Path) -> str | None:
    """None when `path` is a complete, weights-only-readable Lightning checkpoint; else what is wrong."""
    try:
        size = path.stat().st_size
        if size == 0:
            return "it is empty (0 bytes)"
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
            if bad is not None:
                return f"its entry {bad} is damaged"
            if not any(n.endswith("data.pkl") for n in z.namelist()):
                return "it is not a torch checkpoint"
    except (zipfile.BadZipFile, EOFError):
        return "it is truncated or not a torch checkpoint"
    except OSError as e:
        return f"it cannot be read ({e.strerror or e})"
    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as e:  # noqa: BLE001 - any failure to read means "unusable"
        return f"it cannot be loaded ({type(e).__name__})"
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "global_step" not in ckpt:
        return "it is not a Lightning training checkpoint"
    return None


def _pick_resume(run: Path) -> Path:
    """last.ckpt when it is intact; else best.ckpt with a printed note; else a one-line refusal."""
    last = run / LAST
    problem = checkpoint_problem(last)
    if problem is None:
        return last
    best = run / BEST
    if best.is_file() and checkpoint_problem(best) is None:
        print(f"degusta: note: {last} is unusable ({problem}); resuming from {best} instead "
              f"(steps after its validation are trained again)", file=sys.stderr)
        return best
    raise DegustaError(f"{last}: cannot resume, {problem} and no intact {BEST} is beside it; delete {last} to "
                       f"start this run again from scratch, or set trainer.run_name to a new folder")


def prepare_run_dir(cfg: TrainerConfig, full_config: Any = None, write: bool = True) -> tuple[Path, Path | None]:
    """Create the run folder, write `config.yaml` beside the checkpoints and decide whether to resume.

    Args:
        cfg: the trainer section.
        full_config: the whole train config (dataclass or dict) to record; defaults to `cfg`.
        write: False in the other processes of a multi-process run: they decide whether to resume
            exactly as rank 0 does, but create, clean and write nothing (rank 0 does).

    Returns:
        (run folder, path of last.ckpt to resume from or None).

    Raises:
        DegustaError: the folder has a last.ckpt but `resume` is false, or its config.yaml differs from
            this one outside the `trainer` section (resuming would mix two different models).
    """
    run = cfg.path
    resolved = to_dict(full_config) if dataclasses.is_dataclass(full_config) else dict(full_config or to_dict(cfg))
    last = run / LAST
    ckpt = None
    if last.exists():
        _refuse_finished_run(cfg)
        if (run / "config.yaml").exists():
            added = _check_same(read_yaml(run / "config.yaml"), resolved, run / "config.yaml")
            if added:  # keys a newer degusta_learn introduced: the old run had no say in them
                print(f"degusta: note: {run / 'config.yaml'} predates {', '.join(added)}; resuming with "
                      f"{', '.join(repr(v) for v in added.values())} (the run's config.yaml now records them)",
                      file=sys.stderr)
        ckpt = _pick_resume(run)
    if not write:
        return run, ckpt
    try:
        run.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DegustaError(f"trainer.run_dir: cannot create the run folder {run} ({e.strerror or e})") from None
    for stale in run.glob(f"{TMP_PREFIX}*"):  # a checkpoint write a kill interrupted (export folders: outdir)
        with contextlib.suppress(OSError):
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale)
            else:
                stale.unlink()
    atomic_write_text(run / "config.yaml", dump_yaml(resolved))
    return run, ckpt


def _check_run_dir(cfg: TrainerConfig) -> None:
    """The run-folder mistakes `prepare_run_dir` refuses, found without writing anything: a file where a folder
    of the path should be, or a finished run's last.ckpt with `trainer.resume` false."""
    run = cfg.path
    for folder in [run, *run.parents]:
        if folder.exists() or folder.is_symlink():
            if not folder.is_dir():
                raise DegustaError(f"trainer.run_dir: cannot create the run folder {run} ({folder} is a file, not a "
                                   "folder)")
            break
    _refuse_finished_run(cfg)


def _refuse_finished_run(cfg: TrainerConfig) -> None:
    if (cfg.path / LAST).exists() and not cfg.resume:
        raise DegustaError(f"{cfg.path}: holds {LAST} from an earlier run; set trainer.resume=true to continue "
                           f"it or choose another trainer.run_name")


def _check_same(old: dict, new: dict, where: Path, prefix: str = "") -> dict[str, Any]:
    """Refuse a resume whose config differs outside `trainer`; returns the keys `old` lacks ({dotted key: new
    value}): a config written before a newer version of the toolkit added them, not a change of the run."""
    added: dict[str, Any] = {}
    for key in sorted(set(old) | set(new)):
        if not prefix and key == "trainer":
            continue  # epochs, devices etc. may change between an interrupted run and its resume
        a, b = old.get(key), new.get(key)
        if key not in old:
            added[prefix + key] = b
        elif isinstance(a, dict) and isinstance(b, dict):
            added |= _check_same(a, b, where, prefix + key + ".")
        elif a != b and not (isinstance(a, list) and isinstance(b, tuple) and list(b) == a) \
                and not _same_path(a, b):
            raise DegustaError(f"{where}: cannot resume, '{prefix}{key}' was {a!r} and is now {b!r} "
                               f"(use another trainer.run_name, or trainer.resume=false in a new folder)")
    return added


def _same_path(a: Any, b: Any) -> bool:
    """Two strings naming the same existing file or folder (relative vs absolute, `./x` vs `x`, symlinks)."""
    if not (isinstance(a, str) and isinstance(b, str)) or not a or not b:
        return False
    try:
        return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def _atomic_checkpoint_io():
    """A TorchCheckpointIO whose saves go to a temp file in the checkpoint's own folder, then `os.replace`.

    Lightning's default writes through an fsspec transaction whose temp file may sit on another filesystem
    (then the commit *copies* over last.ckpt, and a kill mid-copy leaves a truncated file); a rename inside
    one folder is atomic: readers see the old complete file or the new complete one, never a part.
    """
    import torch
    from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

    class AtomicCheckpointIO(TorchCheckpointIO):
        def save_checkpoint(self, checkpoint: dict, path, storage_options: Any = None) -> None:
            if storage_options is not None:
                raise TypeError("AtomicCheckpointIO takes no storage_options")
            path = Path(path)
            # a full disk, a file-size limit, a quota: one line naming the file; the previous one stays whole
            with writing(path, "checkpoint", after=_resume_note(path.parent / LAST, path)):
                path.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f"{TMP_PREFIX}{path.name}.")
                try:
                    with os.fdopen(fd, "wb") as f:
                        torch.save(checkpoint, f)
                        f.flush()
                        os.fsync(f.fileno())
                    os.replace(tmp, path)
                except BaseException:
                    with contextlib.suppress(OSError):
                        os.unlink(tmp)
                    raise
            with contextlib.suppress(OSError):  # make the rename itself durable
                dfd = os.open(path.parent, os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)

    return AtomicCheckpointIO()


def _resumed_log_step():
    """A callback that restarts Lightning's logging step at the global step when a run resumes.

    Lightning restores its logging step (`_batches_that_stepped`) from the checkpoint and then adds one for some
    restart points; from our checkpoints (written at a validation, at an epoch's end, at the end of `fit`) every
    resume shifted the logged steps by one more (a 6,300-step run resumed twice logged its last validation at
    6,302, and its learning curve and model card said so). With automatic optimization, at the start of a
    training batch the logging step of an uninterrupted run equals `global_step` (both count optimizer steps,
    with or without gradient accumulation): it is set there, a no-op unless the run was resumed.
    """
    from lightning.pytorch.callbacks import Callback

    class ResumedLogStep(Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
            loop = trainer.fit_loop.epoch_loop
            if pl_module.automatic_optimization and hasattr(loop, "_batches_that_stepped"):
                loop._batches_that_stepped = trainer.global_step

    return ResumedLogStep()


def _validation_at_max_steps():
    """A callback that makes the step that reaches `trainer.max_steps` a validation step.

    Lightning validates at an epoch's end (or every `val_check_interval` batches) and stops at `max_steps` wherever
    it falls: a run whose last epoch is cut short ended without validating its last weights (the pretraining
    recipe's 5,650 steps at 300 an epoch: last validation at step 5,399, so neither its learning curve nor its model
    card showed the weights it exported, and a `trainer.monitor` never saw them). Asking the loop to stop at that
    step makes Lightning validate there (`Trainer.should_stop` does); a run that ends on a validation step
    validates once, as before.
    """
    from lightning.pytorch.callbacks import Callback

    class ValidationAtMaxSteps(Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            if 0 < trainer.max_steps <= trainer.global_step:
                trainer.should_stop = True

    return ValidationAtMaxSteps()


def _monitor_guard(monitor: str):
    """A callback that fails fast, with a one-line error, when a validation did not log `monitor`.

    It runs before ModelCheckpoint (Lightning orders checkpoint callbacks last), whose own error would be a
    multi-line MisconfigurationException. Trainers also check `monitor` up front (`check_trainer`); this
    catches a module that logs less than it declared.
    """
    from lightning.pytorch.callbacks import Callback

    class MonitorGuard(Callback):
        def on_validation_end(self, trainer, pl_module) -> None:
            if trainer.sanity_checking or monitor in trainer.callback_metrics:
                return
            logged = sorted(k for k in trainer.callback_metrics if "/" in k)
            raise DegustaError(f"trainer.monitor: {monitor!r} was not logged by the validation at step "
                               f"{trainer.global_step} (logged: {', '.join(logged) or 'nothing'})")

    return MonitorGuard()


@contextlib.contextmanager
def torch_threads(n: int | None):
    """torch's CPU threads set to `n` (None: unchanged) inside the block, and restored after it: a step that
    wants one thread must not leave every later step of the same process (quickstart's VLM fine-tuning) on one."""
    import torch

    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


AVX2_KERNELS = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}
"""The environment that caps torch's own kernels, oneDNN's and MKL's at AVX2 (each reads it at its first use)."""


def x86_with_avx2() -> bool:
    """Whether this CPU is an x86 one with AVX2: where `cpu_kernels: avx2` can cap the kernels at all."""
    import platform

    import torch

    return (platform.machine().lower() in ("x86_64", "amd64")
            and bool(getattr(torch.cpu, "_is_avx2_supported", lambda: False)()))


def pin_cpu_kernels(kernels: str) -> str:
    """Ask torch, oneDNN and MKL for `kernels` (`TrainerConfig.cpu_kernels`: "avx2" caps them at AVX2, "native"
    leaves them be) before this process's first CPU operation fixes them; variables already in the environment
    are kept. Returns the kernels torch runs ("AVX2", "AVX512", "DEFAULT", ...), with a note on stderr where "avx2"
    was asked for and is not what runs."""
    import platform

    import torch

    x86_avx2 = x86_with_avx2()
    if kernels == "avx2" and x86_avx2:
        for name, value in AVX2_KERNELS.items():
            os.environ.setdefault(name, value)
    running = torch.backends.cpu.get_cpu_capability()
    if kernels == "avx2" and running != "AVX2":
        asked = os.environ.get("ATEN_CPU_CAPABILITY", "")
        why = (f"this CPU ({platform.machine() or 'unknown'}) has no AVX2" if not x86_avx2 else
               f"ATEN_CPU_CAPABILITY={asked} in the environment asks for others" if asked.lower() != "avx2" else
               "this process ran torch before the run began, and the kernels are chosen at its first operation; "
               "start a fresh process, or set " + " ".join(f"{k}={v}" for k, v in AVX2_KERNELS.items())
               + " before Python starts")
        print(f"degusta: note: trainer.cpu_kernels avx2: torch runs its {running} kernels: {why}", file=sys.stderr)
    return running


def trains_on_gpu(cfg: TrainerConfig) -> bool:
    """Whether a run of `cfg` trains on a GPU on this machine (`accelerator: gpu`, or `auto` where CUDA is present)."""
    import torch

    return cfg.accelerator in ("gpu", "cuda") or (cfg.accelerator == "auto" and torch.cuda.is_available())


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX); elsewhere torch emulates it, ~60x slower
    than float32 (`run_precision`): autocast to bfloat16 on the CPU only where this is true."""
    import torch

    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


def effective_precision(cfg: TrainerConfig) -> str:
    """The precision a run of `cfg` uses on this machine: `cfg.precision`, except bfloat16 on a CPU that has no
    native bfloat16 (AVX512-BF16 or AMX), which runs it emulated: measured on an AVX2 EPYC, a 3x3 convolution 127x
    and a matmul 60x slower than float32. There it is 32-true (the same config stays fast where bf16 is native)."""
    if cfg.precision not in ("bf16-mixed", "bf16") or cfg.accelerator not in ("cpu", "auto") or trains_on_gpu(cfg):
        return cfg.precision
    return cfg.precision if cpu_has_native_bf16() else "32-true"


def run_precision(cfg: TrainerConfig) -> str:
    """The precision Lightning gets (`effective_precision`), with a note where it is not `cfg.precision`."""
    precision = effective_precision(cfg)
    if precision != cfg.precision:
        print(f"degusta: note: trainer.precision {cfg.precision}: this CPU has no native bfloat16 (AVX512-BF16/AMX) "
              f"and emulates it ~60x slower than float32; training in {precision}", file=sys.stderr)
    return precision


def build_trainer(cfg: TrainerConfig, run: Path, callbacks: list | None = None):
    """A `lightning.Trainer` writing into `run`: loggers, checkpointing, progress bar, devices.

    Lightning's own complaints about the trainer values become one-line DegustaErrors naming `trainer`.
    """
    import lightning as L
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint, TQDMProgressBar

    # Two checkpoint callbacks, because Lightning 2.6's `save_last` writes last.ckpt only when a top-k checkpoint
    # was saved at the same step (a validation that does not improve the monitor would leave last.ckpt behind):
    # - best.ckpt: decided right after each validation (never deferred to the epoch's end), so a module's
    #   on_validation_end, which runs after every callback's, sees the decision (finetune: best_adapter/);
    #   first, so it is `trainer.checkpoint_callback`;
    # - last.ckpt: a monitor-free "top 1" rewritten after every validation (no validation: every epoch's end).
    ckpts = [ModelCheckpoint(dirpath=run, filename=BEST[:-5], monitor=cfg.monitor, mode=cfg.monitor_mode,
                             save_top_k=1, save_last=False, enable_version_counter=False,
                             auto_insert_metric_name=False, save_on_train_epoch_end=False)] if cfg.monitor else []
    ckpts.append(_last_checkpoint(ModelCheckpoint)(dirpath=run, filename=LAST[:-5], monitor=None, save_top_k=1,
                                                   save_last=False, enable_version_counter=False,
                                                   auto_insert_metric_name=False))
    cbs = [*ckpts, *(callbacks or []), _resumed_log_step(), _validation_at_max_steps(), _interrupt_recorder()]
    if cfg.monitor:
        cbs.append(_monitor_guard(cfg.monitor))  # before EarlyStopping: its one-line error comes first
    if cfg.early_stopping_patience is not None:  # counts validations (checked after each, never at epoch end);
        # a NaN monitor counts as no improvement instead of stopping at once
        cbs.append(EarlyStopping(monitor=cfg.monitor, mode=cfg.monitor_mode, patience=cfg.early_stopping_patience,
                                 min_delta=cfg.early_stopping_min_delta, check_on_train_epoch_end=False,
                                 check_finite=False, verbose=False))
    if cfg.progress_bar:
        cbs.append(TQDMProgressBar(refresh_rate=max(1, cfg.log_every_n_steps)))
    loggers = build_loggers(cfg, run) or False  # an empty list: no logger at all
    # sharded strategies write their own checkpoint folders; every other one saves through one CheckpointIO
    sharded = cfg.strategy.startswith(("fsdp", "deepspeed"))
    try:
        return L.Trainer(
            accelerator=cfg.accelerator, devices=cfg.devices, num_nodes=cfg.num_nodes, strategy=cfg.strategy,
            precision=run_precision(cfg),
            max_epochs=cfg.max_epochs, max_steps=cfg.max_steps, accumulate_grad_batches=cfg.accumulate_grad_batches,
            gradient_clip_val=cfg.gradient_clip_val, log_every_n_steps=cfg.log_every_n_steps,
            val_check_interval=cfg.val_check_interval, check_val_every_n_epoch=cfg.check_val_every_n_epoch,
            num_sanity_val_steps=cfg.num_sanity_val_steps, enable_progress_bar=cfg.progress_bar,
            enable_model_summary=cfg.progress_bar, logger=loggers, callbacks=cbs, default_root_dir=run,
            plugins=None if sharded else [_atomic_checkpoint_io()],
        )
    except (MisconfigurationException, ValueError, ImportError, RuntimeError) as e:
        first = " ".join(str(e).split(". ")[0].split())[:200]
        raise DegustaError(f"trainer: Lightning refused these settings ({first})") from None


def _last_checkpoint(base: type) -> type:
    """Lightning's ModelCheckpoint for last.ckpt, saving after every validation when `val_check_interval` is the
    whole number 1 (validate after every batch) too: Lightning compares it with 1.0 ("once an epoch") and would
    save only at the epoch's end, so a run stopped mid-epoch resumed from the epoch before. Same state key as a
    plain ModelCheckpoint (runs written before resume as they did)."""

    class LastCheckpoint(base):
        def _should_save_on_train_epoch_end(self, trainer) -> bool:
            vci, n = trainer.val_check_interval, trainer.num_val_batches
            validates = (sum(n) if isinstance(n, list) else n) > 0  # no validation: save at the epoch's end
            if (self._save_on_train_epoch_end is None and type(vci) is int and vci == 1 and validates
                    and trainer.check_val_every_n_epoch == 1):
                return False
            return super()._should_save_on_train_epoch_end(trainer)

    LastCheckpoint.__name__ = LastCheckpoint.__qualname__ = base.__name__
    return LastCheckpoint


def fit(module, datamodule, cfg: TrainerConfig, full_config: Any = None, callbacks: list | None = None,
        monitors: Iterable[str] | None = None) -> Path:
    """Train `module` on `datamodule` per `cfg`; returns the run folder (with last.ckpt, best.ckpt).

    Resumes from `<run>/last.ckpt` when it exists and `cfg.resume` is true (model, optimizer, scheduler,
    epoch and global step all continue; a corrupt last.ckpt falls back to best.ckpt or is refused).
    Checkpoints are read weights-only and written atomically. Bad trainer values are refused before the
    run folder is touched; a DegustaError before the first checkpoint removes a folder this call created.
    """
    check_trainer(cfg, monitors)
    _check_run_dir(cfg)  # before the Trainer exists: Lightning prints its banner lines when it is built
    trainer = build_trainer(cfg, cfg.path, callbacks)
    zero = trainer.is_global_zero  # known once the Trainer exists (from the launcher's environment)
    with _run_lock(cfg.path, zero) as created:  # re-entrant: `training_run` holds it already
        with _user_errors(cfg.path, created):
            run, ckpt = prepare_run_dir(cfg, full_config, write=zero)
        seed_everything(cfg.seed)
        with _user_errors(run, created), warnings.catch_warnings():  # the run folder holds config.yaml by design
            warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
            # torch >= 2.10 under DDP, once a run (seen on an H100, configs/learned_gpu.yaml): DDP keeps a reference
            # to the gradient-accumulation node it was built with; the run uses one stream, nothing to act on
            warnings.filterwarnings("ignore", message=r"The AccumulateGrad node's stream does not match")
            _fit_or_interrupt(trainer, run, module, datamodule=datamodule, ckpt_path=str(ckpt) if ckpt else None,
                              weights_only=True)
        # last.ckpt is written at each validation; also keep the steps after the last one
        trainer.save_checkpoint(run / LAST, weights_only=False)  # full state (optimizer too), to resume
        if trainer.received_sigterm:  # a SIGTERM Lightning noticed only after the last step: the run is complete
            raise Terminated(signal.SIGTERM)  # and saved, but the process was asked to stop (no export now)
    _note_early_stop(trainer, cfg)
    return run


class _QuietInterrupt(logging.Filter):
    """Drops Lightning's own lines about an interrupt ("Detected KeyboardInterrupt, attempting graceful shutdown",
    "Received SIGTERM"): the CLI says it in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        text = str(record.msg)
        return not any(s in text for s in ("Detected KeyboardInterrupt", "Received SIGTERM", "Bypassing SIGTERM"))


_LIGHTNING_INTERRUPT_LOGGERS = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero",
                                "lightning.pytorch.trainer.connectors.signal_connector")


def _fit_or_interrupt(trainer, run: Path, module, **kwargs) -> None:
    """`trainer.fit(module, **kwargs)`, with Ctrl-C and SIGTERM propagated and failed writes in one line.

    Lightning 2.x catches a KeyboardInterrupt (Ctrl-C, or the CLI's `Terminated` on SIGTERM), tears down, sets
    SIGINT to "ignore" and calls `sys.exit(1)`; where no SIGTERM handler raises, its own handler only flags the
    signal and the loop ends with `SIGTERMException`, a `SystemExit` whose status is 0 (older versions returned
    normally with `trainer.interrupted` set). Here every such end raises the interrupt itself again (the same
    `KeyboardInterrupt` / `Terminated` object, or `Terminated` for a flagged SIGTERM), so the CLI exits 130 / 143
    with its one line and no export follows; SIGINT's handler is restored. The last complete `last.ckpt` stays as
    it was (atomic saves), so the run resumes from it.
    A failed write Lightning or a logger reports in its own exception type (a full disk, a file-size limit) becomes
    a one-line DegustaError naming the file (`writeerrors`), with the state of last.ckpt.
    """
    recorder = next((c for c in trainer.callbacks if type(c).__name__ == "InterruptRecorder"), None)
    main = threading.current_thread() is threading.main_thread()
    sigint = signal.getsignal(signal.SIGINT) if main else None
    quiet = _QuietInterrupt()
    for name in _LIGHTNING_INTERRUPT_LOGGERS:
        logging.getLogger(name).addFilter(quiet)
    try:
        with writing(run, "training files", after=_resume_note(run / LAST), any_oserror=False):
            trainer.fit(module, **kwargs)
    except SystemExit as e:  # Lightning's sys.exit(1) after an interrupt, or its SIGTERMException
        raise _interruption(trainer, recorder, e) from None
    finally:
        if main and sigint is not None and signal.getsignal(signal.SIGINT) is not sigint:
            signal.signal(signal.SIGINT, sigint)
        for name in _LIGHTNING_INTERRUPT_LOGGERS:
            logging.getLogger(name).removeFilter(quiet)
    if trainer.interrupted:  # a Lightning that returns normally after an interrupt
        raise _interruption(trainer, recorder, None)


def _interruption(trainer, recorder, exit_: SystemExit | None) -> BaseException:
    """What to raise for a `trainer.fit` that Lightning ended after an interrupt (`_fit_or_interrupt`)."""
    caught = getattr(recorder, "exception", None)
    if isinstance(caught, KeyboardInterrupt):
        return caught
    if trainer.received_sigterm or type(caught).__name__ == "SIGTERMException" \
            or type(exit_).__name__ == "SIGTERMException":
        return Terminated(signal.SIGTERM)
    if exit_ is not None:
        return exit_  # a sys.exit() of the module's own
    return KeyboardInterrupt()


def _resume_note(last: Path, failing: Path | None = None) -> str:
    """What a message about a failed write of `failing` (a run's file) says about resuming from `last`."""
    if not last.is_file():
        return "; training stopped before its first checkpoint"
    if failing is not None and Path(failing) == last:
        return "; training stopped, the previous one is intact: free space (or raise the limit) and re-run to resume"
    return (f"; training stopped, {last} keeps the last complete checkpoint: free space (or raise the limit) and "
            "re-run to resume")


def _interrupt_recorder():
    """A callback keeping the exception Lightning ended `fit` with (`on_exception`), for `_fit_or_interrupt`."""
    from lightning.pytorch.callbacks import Callback

    class InterruptRecorder(Callback):
        exception: BaseException | None = None

        def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
            self.exception = exception

    return InterruptRecorder()


def _note_early_stop(trainer, cfg: TrainerConfig) -> None:
    """Say on stderr (rank 0) when early stopping ended the run, and where the best validation was."""
    from lightning.pytorch.callbacks import EarlyStopping

    stopper = next((c for c in trainer.callbacks if isinstance(c, EarlyStopping)), None)
    if stopper is None or stopper.wait_count < stopper.patience or not trainer.is_global_zero:
        return
    best = trainer.checkpoint_callback.best_model_score if trainer.checkpoint_callback else None
    print(f"degusta: note: stopped early at step {trainer.global_step}: {cfg.monitor} did not improve for "
          f"{stopper.patience} validations (trainer.early_stopping_patience); best "
          f"{float(best) if best is not None else float('nan'):.4g} is in {BEST}", file=sys.stderr)


def gather_unique_rows(module, rows):
    """Every rank's validation rows as one tensor, each example once, sorted by example index (column 0).

    Under DDP the validation sampler gives each rank a share of the examples and pads the shares to equal
    length by repeating examples; a plain `self.log(..., sync_dist=True)` of per-rank means would then
    average unequal shares and count the repeats twice. Gathering the per-example rows (`all_gather`, padded
    with index -1 to the longest share) and keeping one row per index makes the metrics exactly those of a
    single-process validation; rows are sorted by index in a single process too, so sums add up in the same
    order. Every rank gets the same result (log it with sync_dist=True: the mean of equal values is the value).
    """
    import torch

    if rows.ndim != 2:
        raise ValueError("rows must be (n, columns)")
    trainer = getattr(module, "_trainer", None)
    if trainer is not None and trainer.world_size > 1:
        device = module.device
        counts = module.all_gather(torch.tensor([rows.shape[0]], device=device)).flatten()
        top = int(counts.max())
        padded = torch.full((top, rows.shape[1]), -1.0, dtype=rows.dtype, device=device)
        padded[:rows.shape[0]] = rows.to(device)
        rows = module.all_gather(padded).reshape(-1, rows.shape[1]).cpu()
        rows = rows[rows[:, 0] >= 0]
    rows = rows[torch.argsort(rows[:, 0], stable=True)]
    if len(rows) > 1:
        keep = torch.ones(len(rows), dtype=torch.bool)
        keep[1:] = rows[1:, 0] != rows[:-1, 0]
        rows = rows[keep]
    return rows
