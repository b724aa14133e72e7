"""The run's loggers (CSV, TensorBoard, optional W&B / MLflow offline into the run folder), each wrapped so that a
failed write is one line naming the file, and `validation_curve` to read a run's validation metrics back.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError
from degusta_learn.files.write_errors import writing
from degusta_learn.training.config import TrainerConfig
from degusta_learn.training.run_dir import LAST, TMP_PREFIX, resume_note


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
    """A constructor of `cls` (a Lightning logger) whose writes fail in one line (`files.write_errors.writing`: "<where>:
    cannot write the <what> (No space left on device); training stopped, <run>/last.ckpt keeps ..."); a failure
    while Lightning finalizes a run that is failing already is dropped (the first error is the one to report).
    The CSV logger's metrics.csv also stays whole: a failed append is cut back to its last complete row and a
    header change rewrites the file atomically (`_SafeMetrics`), so `validation_curve` reads it after a resume."""
    if cls not in _GUARDED:
        def guard(name):
            def method(self, *args, **kwargs):
                with writing(self._degusta_where, self._degusta_what, after=resume_note(self._degusta_run / LAST)):
                    return getattr(super(sub, self), name)(*args, **kwargs)
            method.__name__ = name
            return method

        def finalize(self, status: str) -> None:
            try:
                with writing(self._degusta_where, self._degusta_what, after=resume_note(self._degusta_run / LAST)):
                    super(sub, self).finalize(status)
            except DegustaError:
                if status == "success":
                    raise

        def experiment(self):
            with writing(self._degusta_where, self._degusta_what, after=resume_note(self._degusta_run / LAST)):
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
    from degusta_learn.files.atomic import UMASK

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
