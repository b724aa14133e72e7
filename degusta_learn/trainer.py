"""Shared Lightning training harness: run folders, loggers, checkpoints, resume, `fit`.

Every trainer of the toolkit (the learned arrangement model, VLM fine-tuning) embeds a `TrainerConfig`
under its config's `trainer:` section and calls `fit(module, datamodule, cfg.trainer, full_config)`.
What `fit` does, in order:

1. `prepare_run_dir`: makes `<run_dir>/<run_name>/` (default `checkpoints/<run>/`) and writes the resolved
   config there as `config.yaml` (atomically). A folder that already holds `last.ckpt` is resumed when
   `resume: true` (its `config.yaml` must agree with the new one outside the `trainer` section) and refused
   otherwise, so an interrupted run is never overwritten by accident.
2. `seed_everything(seed, workers=True)`.
3. `build_trainer`: a `lightning.Trainer` with CSV + TensorBoard loggers (`csv/version_N`, `tb/version_N`:
   a resumed run opens a new version, earlier logs are kept), a `ModelCheckpoint` writing `last.ckpt` and
   `best.ckpt` (best by `monitor`, e.g. validation RMSD), a progress bar, and the accelerator / devices /
   strategy / precision from the config — multi-GPU is `devices: 4, strategy: ddp`, no code change.
4. `trainer.fit(..., ckpt_path=last.ckpt if resuming, weights_only=True)`; `last.ckpt` is written after
   every validation and once more when training ends, so a run stopped by a crash or Ctrl-C resumes from
   its last validation and a finished run can be extended with a larger `max_epochs` / `max_steps`.

Checkpoints must load weights-only: a LightningModule that calls `save_hyperparameters` must pass plain
dicts / lists / numbers / strings only (e.g. `dataclasses.asdict(cfg)`), never dataclasses or Paths.

Usage:
    from degusta_learn.trainer import TrainerConfig, fit
    run_dir = fit(module, datamodule, TrainerConfig(run_name="demo", max_epochs=3), full_config=cfg)
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from degusta_learn.config import read_yaml, to_dict
from degusta_learn.errors import DegustaError
from degusta_learn.fileio import atomic_write_text

LAST = "last.ckpt"
BEST = "best.ckpt"


@dataclass
class TrainerConfig:
    """The `trainer:` section of every train config (Lightning settings + where the run is written)."""

    run_name: str = "run"
    """Run folder name: outputs go to `<run_dir>/<run_name>/`."""
    run_dir: str = "checkpoints"
    """Parent folder of run folders."""
    resume: bool = True
    """Continue from `<run>/last.ckpt` when it exists (false: refuse to reuse a folder that has one)."""
    seed: int = 0
    """Seed for Python, numpy, torch and data-loader workers."""
    max_epochs: int = 10
    """Stop after this many epochs (-1: no epoch limit, use max_steps)."""
    max_steps: int = -1
    """Stop after this many optimizer steps (-1: no step limit)."""
    accelerator: str = "auto"
    """"cpu", "gpu", "auto" (GPU when present)."""
    devices: Any = "auto"
    """Number of devices (int), a list of device indices, or "auto"."""
    strategy: str = "auto"
    """Lightning strategy: "auto", "ddp", "ddp_spawn", "fsdp", ... (multi-GPU needs no code change)."""
    precision: str = "32-true"
    """"32-true", "bf16-mixed" (GPU), "16-mixed" (GPU)."""
    accumulate_grad_batches: int = 1
    """Gradient accumulation: effective batch = batch_size * this * devices."""
    gradient_clip_val: float | None = 1.0
    """Clip the gradient norm to this (null: no clipping)."""
    log_every_n_steps: int = 10
    """How often training losses are logged."""
    val_check_interval: int | float = 1.0
    """Validate every this fraction of an epoch (float) or number of batches (int)."""
    check_val_every_n_epoch: int = 1
    """Validate every this many epochs."""
    monitor: str | None = "val/rmsd"
    """Metric that picks best.ckpt (null: only last.ckpt)."""
    monitor_mode: str = "min"
    """"min" or "max" for `monitor`."""
    progress_bar: bool = True
    """Show Lightning's progress bar."""
    num_sanity_val_steps: int = 0
    """Validation batches run before training as a smoke check (0: none)."""

    def __post_init__(self):
        if not self.run_name or "/" in self.run_name or self.run_name in (".", ".."):
            raise DegustaError(f"trainer.run_name: expected a plain folder name, got {self.run_name!r}")
        if self.max_epochs == -1 and self.max_steps == -1:
            raise DegustaError("trainer.max_epochs / trainer.max_steps: set at least one of them (not both -1)")
        if self.monitor_mode not in ("min", "max"):
            raise DegustaError(f"trainer.monitor_mode: expected 'min' or 'max', got {self.monitor_mode!r}")
        if self.accumulate_grad_batches < 1:
            raise DegustaError(f"trainer.accumulate_grad_batches: expected >= 1, got {self.accumulate_grad_batches}")

    @property
    def path(self) -> Path:
        """The run folder `<run_dir>/<run_name>`."""
        return Path(self.run_dir) / self.run_name


def prepare_run_dir(cfg: TrainerConfig, full_config: Any = None) -> tuple[Path, Path | None]:
    """Create the run folder, write `config.yaml` beside the checkpoints and decide whether to resume.

    Args:
        cfg: the trainer section.
        full_config: the whole train config (dataclass or dict) to record; defaults to `cfg`.

    Returns:
        (run folder, path of last.ckpt to resume from or None).

    Raises:
        DegustaError: the folder has a last.ckpt but `resume` is false, or its config.yaml differs from
            this one outside the `trainer` section (resuming would mix two different models).
    """
    run = cfg.path
    run.mkdir(parents=True, exist_ok=True)
    resolved = to_dict(full_config) if dataclasses.is_dataclass(full_config) else dict(full_config or to_dict(cfg))
    last = run / LAST
    ckpt = None
    if last.exists():
        if not cfg.resume:
            raise DegustaError(f"{run}: holds {LAST} from an earlier run; set trainer.resume=true to continue "
                               f"it or choose another trainer.run_name")
        if (run / "config.yaml").exists():
            _check_same(read_yaml(run / "config.yaml"), resolved, run / "config.yaml")
        ckpt = last
    atomic_write_text(run / "config.yaml", yaml.safe_dump(resolved, sort_keys=False))
    return run, ckpt


def _check_same(old: dict, new: dict, where: Path, prefix: str = "") -> None:
    for key in sorted(set(old) | set(new)):
        if not prefix and key == "trainer":
            continue  # epochs, devices etc. may change between an interrupted run and its resume
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            _check_same(a, b, where, prefix + key + ".")
        elif a != b and not (isinstance(a, list) and isinstance(b, tuple) and list(b) == a):
            raise DegustaError(f"{where}: cannot resume, '{prefix}{key}' was {a!r} and is now {b!r} "
                               f"(use another trainer.run_name, or trainer.resume=false in a new folder)")


def build_trainer(cfg: TrainerConfig, run: Path, callbacks: list | None = None):
    """A `lightning.Trainer` writing into `run`: loggers, checkpointing, progress bar, devices."""
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    ckpt = ModelCheckpoint(dirpath=run, filename=BEST[:-5], monitor=cfg.monitor, mode=cfg.monitor_mode,
                           save_top_k=1 if cfg.monitor else 0, save_last=True, enable_version_counter=False,
                           auto_insert_metric_name=False)
    cbs = [ckpt, *(callbacks or [])]
    if cfg.progress_bar:
        cbs.append(TQDMProgressBar(refresh_rate=max(1, cfg.log_every_n_steps)))
    loggers = [CSVLogger(save_dir=run, name="csv"), TensorBoardLogger(save_dir=run, name="tb", default_hp_metric=False)]
    return L.Trainer(
        accelerator=cfg.accelerator, devices=cfg.devices, strategy=cfg.strategy, precision=cfg.precision,
        max_epochs=cfg.max_epochs, max_steps=cfg.max_steps, accumulate_grad_batches=cfg.accumulate_grad_batches,
        gradient_clip_val=cfg.gradient_clip_val, log_every_n_steps=cfg.log_every_n_steps,
        val_check_interval=cfg.val_check_interval, check_val_every_n_epoch=cfg.check_val_every_n_epoch,
        num_sanity_val_steps=cfg.num_sanity_val_steps, enable_progress_bar=cfg.progress_bar,
        enable_model_summary=cfg.progress_bar, logger=loggers, callbacks=cbs, default_root_dir=run,
    )


def fit(module, datamodule, cfg: TrainerConfig, full_config: Any = None, callbacks: list | None = None) -> Path:
    """Train `module` on `datamodule` per `cfg`; returns the run folder (with last.ckpt, best.ckpt).

    Resumes from `<run>/last.ckpt` when it exists and `cfg.resume` is true (model, optimizer, scheduler,
    epoch and global step all continue). Checkpoints are read weights-only.
    """
    import lightning as L

    run, ckpt = prepare_run_dir(cfg, full_config)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    trainer = build_trainer(cfg, run, callbacks)
    with warnings.catch_warnings():  # the run folder holds config.yaml (and logs) by design
        warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
        trainer.fit(module, datamodule=datamodule, ckpt_path=str(ckpt) if ckpt else None, weights_only=True)
    if not trainer.interrupted:  # last.ckpt is written at each validation; also keep the steps after the last one
        trainer.save_checkpoint(run / LAST, weights_only=False)  # full state (optimizer too), to resume
    return run
