"""`build_trainer` and `fit`: a `lightning.Trainer` from a `TrainerConfig`, run so that Ctrl-C and SIGTERM are raised
again (exit 130 / 143, the run resumes) and Lightning's complaints become one-line errors.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError, Terminated
from degusta_learn.files.write_errors import writing
from degusta_learn.training.checkpoint_io import atomic_checkpoint_io, last_checkpoint_class
from degusta_learn.training.config import TrainerConfig, check_trainer
from degusta_learn.training.hardware import run_precision, seed_everything
from degusta_learn.training.loggers import build_loggers
from degusta_learn.training.run_dir import (
    BEST,
    LAST,
    check_run_dir,
    prepare_run_dir,
    resume_note,
    run_lock,
    user_errors,
)


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
    ckpts.append(last_checkpoint_class(ModelCheckpoint)(dirpath=run, filename=LAST[:-5], monitor=None, save_top_k=1,
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
            plugins=None if sharded else [atomic_checkpoint_io()],
        )
    except (MisconfigurationException, ValueError, ImportError, RuntimeError) as e:
        first = " ".join(str(e).split(". ")[0].split())[:200]
        raise DegustaError(f"trainer: Lightning refused these settings ({first})") from None


def fit(module, datamodule, cfg: TrainerConfig, full_config: Any = None, callbacks: list | None = None,
        monitors: Iterable[str] | None = None) -> Path:
    """Train `module` on `datamodule` per `cfg`; returns the run folder (with last.ckpt, best.ckpt).

    Resumes from `<run>/last.ckpt` when it exists and `cfg.resume` is true (model, optimizer, scheduler,
    epoch and global step all continue; a corrupt last.ckpt falls back to best.ckpt or is refused).
    Checkpoints are read weights-only and written atomically. Bad trainer values are refused before the
    run folder is touched; a DegustaError before the first checkpoint removes a folder this call created.
    """
    check_trainer(cfg, monitors)
    check_run_dir(cfg)  # before the Trainer exists: Lightning prints its banner lines when it is built
    trainer = build_trainer(cfg, cfg.path, callbacks)
    zero = trainer.is_global_zero  # known once the Trainer exists (from the launcher's environment)
    with run_lock(cfg.path, zero) as created:  # re-entrant: `training_run` holds it already
        with user_errors(cfg.path, created):
            run, ckpt = prepare_run_dir(cfg, full_config, write=zero)
        seed_everything(cfg.seed)
        with user_errors(run, created), warnings.catch_warnings():  # the run folder holds config.yaml by design
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
    a one-line DegustaError naming the file (`files.write_errors`), with the state of last.ckpt.
    """
    recorder = next((c for c in trainer.callbacks if type(c).__name__ == "InterruptRecorder"), None)
    main = threading.current_thread() is threading.main_thread()
    sigint = signal.getsignal(signal.SIGINT) if main else None
    quiet = _QuietInterrupt()
    for name in _LIGHTNING_INTERRUPT_LOGGERS:
        logging.getLogger(name).addFilter(quiet)
    try:
        with writing(run, "training files", after=resume_note(run / LAST), any_oserror=False):
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
