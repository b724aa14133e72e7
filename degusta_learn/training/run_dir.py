"""Run folders: `training_run` (checks, seeding, the run lock, a folder removed again when a user mistake stops
the run before its first checkpoint), `prepare_run_dir` (config.yaml, resume or refuse), checkpoint checks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import sys
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from degusta_learn.config import dump_yaml, read_yaml, to_dict
from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import atomic_write_text
from degusta_learn.files.locks import hold, remove_made
from degusta_learn.files.paths import refuse_shipped
from degusta_learn.training.config import TrainerConfig, check_trainer, trainer_key_in
from degusta_learn.training.hardware import is_global_zero, pin_cpu_kernels, seed_everything

LAST = "last.ckpt"


BEST = "best.ckpt"


TMP_PREFIX = ".tmp-"
"""Prefix of the temp files checkpoints are written to before `os.replace` (stale ones are removed)."""


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
        check_run_dir(cfg)  # a file in the folder's path, a finished run: refused before a lock file is made
    with run_lock(run, zero) as created, user_errors(run, created):
        yield run


@contextlib.contextmanager
def run_lock(run: Path, zero: bool) -> Iterator[Path | None]:
    """Hold the run folder's lock (`locks.hold`: `<run_dir>/.<run_name>.degusta-lock`, rank 0 only) for the whole
    block, so a second run into the same folder is refused in one line naming the first (pid, command, start);
    yields the outermost folder of `run`'s path this run creates (None: none; `user_errors` removes it after a
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
def user_errors(run: Path, created: Path | None) -> Iterator[None]:
    """A DegustaError, or a Lightning ValueError/TypeError naming a trainer key (e.g. val_check_interval >
    batches per epoch), removes the run folder this call `created` (None: keep it) and leaves as one line."""
    try:
        yield
    except DegustaError:
        _remove_if_empty_run(run, created)
        raise
    except (ValueError, TypeError) as e:
        key = trainer_key_in(str(e))
        if key is None:
            raise
        _remove_if_empty_run(run, created)
        first = " ".join(str(e).split(". ")[0].split())[:240]
        raise DegustaError(f"trainer.{key}: {first}") from None


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
    for stale in run.glob(f"{TMP_PREFIX}*"):  # a checkpoint write a kill interrupted (export folders: files.folders)
        with contextlib.suppress(OSError):
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale)
            else:
                stale.unlink()
    atomic_write_text(run / "config.yaml", dump_yaml(resolved))
    return run, ckpt


def check_run_dir(cfg: TrainerConfig) -> None:
    """The run-folder mistakes `prepare_run_dir` refuses, found without writing anything: a file where a folder
    of the path should be, or a finished run's last.ckpt with `trainer.resume` false."""
    run = cfg.path
    refuse_shipped(run, "trainer.run_dir")
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


def resume_note(last: Path, failing: Path | None = None) -> str:
    """What a message about a failed write of `failing` (a run's file) says about resuming from `last`."""
    if not last.is_file():
        return "; training stopped before its first checkpoint"
    if failing is not None and Path(failing) == last:
        return "; training stopped, the previous one is intact: free space (or raise the limit) and re-run to resume"
    return (f"; training stopped, {last} keeps the last complete checkpoint: free space (or raise the limit) and "
            "re-run to resume")
