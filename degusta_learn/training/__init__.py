"""The shared Lightning training harness: run folders, loggers, checkpoints, resume, `fit`.

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
1. `prepare_run_dir`: makes `<run_dir>/<run_name>/` (default `runs/<run>/`) and writes the resolved
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
   DegustaError naming the file and the cause (`files.write_errors`); the previous last.ckpt stays whole.

The run folder is locked for the whole run (`training_run` and `fit`, rank 0; `files.locks`: a lock
file `.<run_name>.degusta-lock` beside it): a second run into the same folder is refused in one line naming the
first (pid, command, start time), and never removes a folder the first one made.

Checkpoints must load weights-only: a LightningModule that calls `save_hyperparameters` must pass plain
dicts / lists / numbers / strings only (e.g. `dataclasses.asdict(cfg)`), never dataclasses or Paths.

Usage:
    from degusta_learn.training import TrainerConfig, fit
    run_dir = fit(module, datamodule, TrainerConfig(run_name="demo", max_epochs=3), full_config=cfg)

Modules: config.py (`TrainerConfig`, `check_trainer`), run_dir.py (`training_run`, `prepare_run_dir`), fit.py
(`build_trainer`, `fit`), checkpoint_io.py (atomic checkpoints), loggers.py (`build_loggers`, `validation_curve`),
hardware.py (ranks, seeding, CPU threads and kernels, precision), protocol.py (validation chooses, never test:
`selection_episodes`, the monitor check, `refuse_test_split`).
"""

from degusta_learn.training.checkpoint_io import atomic_checkpoint_io
from degusta_learn.training.config import TrainerConfig, check_trainer, world_size
from degusta_learn.training.fit import build_trainer, fit, gather_unique_rows
from degusta_learn.training.hardware import (
    AVX2_KERNELS,
    effective_precision,
    global_rank,
    is_global_zero,
    pin_cpu_kernels,
    run_precision,
    seed_everything,
    torch_threads,
    trains_on_gpu,
    x86_with_avx2,
)
from degusta_learn.training.loggers import build_loggers, validation_curve
from degusta_learn.training.run_dir import BEST, LAST, TMP_PREFIX, prepare_run_dir, training_run

__all__ = ['atomic_checkpoint_io', 'AVX2_KERNELS', 'BEST', 'build_loggers', 'build_trainer', 'check_trainer', 'effective_precision', 'fit', 'gather_unique_rows', 'global_rank', 'is_global_zero', 'LAST', 'pin_cpu_kernels', 'prepare_run_dir', 'run_precision', 'seed_everything', 'TMP_PREFIX', 'torch_threads', 'TrainerConfig', 'training_run', 'trains_on_gpu', 'validation_curve', 'world_size', 'x86_with_avx2']
