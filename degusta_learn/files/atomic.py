"""Atomic file writing: the one mechanism behind every file the toolkit writes (stdlib only).

A file is written into a temporary file in the same folder, flushed to disk and renamed over the target
(`os.replace`), so a reader never sees half a file and an interrupted run never leaves a truncated output behind.

- `replacing(path)`: the mechanism itself; errors pass through unchanged (the training harness words them with
  the run's state: `training.checkpoint_io`, `training.loggers`).
- `atomic_open(path)` and `atomic_write_text` / `atomic_write_bytes`: the same, for a command's outputs: a path that
  cannot be written (a folder, under a file, a read-only or full disk) is one `DegustaError` naming the path and why.
  JSON goes through `jsonio.atomic_write_json` / `atomic_write_jsonl`; whole folders through `folders.write_folder`.

Usage:
    from degusta_learn.files.atomic import atomic_write_text
    atomic_write_text("runs/eval/report.md", text)
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError
from degusta_learn.files.paths import NOT_UTF8, not_utf8, shown_path, target_problem


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


UMASK = _current_umask()  # the process's umask, read once (os.umask can only be read by setting it)


@contextlib.contextmanager
def replacing(path: str | os.PathLike, mode: str = "w", prefix: str | None = None, suffix: str = ".tmp",
              sync_folder: bool = False, newline: str | None = None) -> Iterator[Any]:
    """Open a temporary file beside `path` (`prefix` + random + `suffix`, default `.NAME.<random>.tmp`); when the
    block ends, flush and fsync it, give it the usual permissions (0666 less the umask) and rename it over `path`.
    `sync_folder`: fsync the folder after the rename as well (the rename itself survives a power cut). On any
    exception the temporary file is removed and the exception passes unchanged. The folder must exist."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}." if prefix is None else prefix, suffix=suffix, dir=path.parent)
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8", "newline": newline})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~UMASK)  # mkstemp makes 0600 files; outputs get the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if sync_folder:
        with contextlib.suppress(OSError):
            dfd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)


def write_problem(e: OSError) -> str:
    """Why a write failed with `e`, in the words of every output's message ("cannot write here: ...")."""
    return f"cannot write here: {e.strerror or e}" if not isinstance(e, IsADirectoryError) else \
        "is a folder; give the path of a file to write"


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w") -> Iterator[Any]:
    """Open a temporary file beside `path`; on success rename it over `path`, on error remove it (`replacing`).

    A path that cannot be written (a folder, under a file, a read-only or virtual file system, a full
    disk) raises DegustaError naming the path and the reason; no temporary file is left behind.
    """
    problem = target_problem(path)
    if problem:
        raise DegustaError(f"{shown_path(path)}: {problem}")
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DegustaError(f"{path}: {write_problem(e)}") from None
    try:
        with replacing(path, mode) as f:
            yield f
    except OSError as e:
        raise DegustaError(f"{path}: {write_problem(e)}") from None
    except UnicodeEncodeError as e:  # text holding a lone surrogate (a non-UTF-8 name): never half-written
        raise DegustaError(f"{shown_path(path)}: the text to write is not UTF-8 ({not_utf8(e.object)}), so "
                           "nothing was written; " + NOT_UTF8) from None


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write `text` (UTF-8) to `path` atomically (`atomic_open`)."""
    with atomic_open(path, "w") as f:
        f.write(text)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` atomically (`atomic_open`)."""
    with atomic_open(path, "wb") as f:
        f.write(data)
