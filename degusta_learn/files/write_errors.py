"""Failed writes as one line: a full disk, a file-size limit, a quota, a read-only disk, wherever they happen.

A write can fail inside our own code (an `OSError`), inside `torch.save` (which wraps the OSError of a failed
write in a `RuntimeError`, "PytorchStreamWriter failed writing file ..." or "unexpected pos ...", or loses it
when it writes to a path itself), inside safetensors (`SafetensorError: ... I/O error: ... (os error 28)`) or
in a logger's background thread. `write_failure(exc)` finds the cause in all of them (the errno of the OSError
in the chain, or of the "os error N" text; for a torch write error that lost its OSError, the full disk or the
file-size limit found right now); `writing(path, what)` turns such a failure inside its block into
`DegustaError("<path>: cannot write the <what> (<cause>)...")`, one line; anything else passes unchanged.

A file-size limit (`ulimit -f`, RLIMIT_FSIZE) makes the kernel send SIGXFSZ, which kills a process by default;
CPython ignores SIGXFSZ at start-up, so in `degusta` the write fails with EFBIG instead and is reported here.

Usage:
    from degusta_learn.files.write_errors import writing
    with writing(run / "last.ckpt", "checkpoint", after="; the previous one is kept"):
        torch.save(state, f)
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
from collections.abc import Iterator
from pathlib import Path

from degusta_learn.errors import DegustaError

WRITE_ERRNOS = frozenset(e for e in (errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", None), errno.EROFS,
                                     errno.EIO, errno.EACCES, errno.EPERM, errno.ENXIO) if e is not None)
"""Errnos that mean "this write cannot succeed here" wherever they come from (a read cannot fail with them,
except EIO / EACCES / EPERM, which are refusals of the disk or of a permission either way)."""
_TORCH_WRITE = re.compile(r"PytorchStreamWriter failed|file write failed|unexpected pos \d+ vs \d+|"
                          r"failed writing (?:file|data)", re.I)
_OS_ERROR = re.compile(r"os error (\d+)", re.I)


def _chain(exc: BaseException) -> Iterator[BaseException]:
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def describe_errno(code: int, strerror: str | None = None) -> str:
    """The cause of a failed write in words, e.g. "No space left on device", "File too large: the file-size limit
    (ulimit -f) is 60,000 bytes"."""
    text = strerror or os.strerror(code)
    if code == errno.EFBIG:
        with contextlib.suppress(ImportError, OSError, ValueError):
            import resource

            soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
            if soft != resource.RLIM_INFINITY:
                text += f": the file-size limit (ulimit -f) is {soft:,} bytes"
    return text


def _diagnose(path: str | os.PathLike | None) -> str:
    """Why a write whose OSError was lost failed, judged now: a full disk, a file-size limit, or unknown."""
    folder = Path(path).parent if path else Path.cwd()
    with contextlib.suppress(OSError, AttributeError):
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        st = os.statvfs(folder)
        if st.f_bavail * st.f_frsize < 1 << 20:
            return os.strerror(errno.ENOSPC)
    with contextlib.suppress(ImportError, OSError, ValueError):
        import resource

        if resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY:
            return describe_errno(errno.EFBIG)
    return "the write failed (a full disk or a file-size limit?)"


def write_failure(exc: BaseException, path: str | os.PathLike | None = None, any_oserror: bool = True) -> str | None:
    """The cause of `exc` in words when it is a failed write, else None.

    `any_oserror`: every OSError counts (inside a block known to write); False: only WRITE_ERRNOS (a block that
    reads too, e.g. a whole training run). `path` helps judge a torch write error that lost its OSError.
    """
    if isinstance(exc, DegustaError) or not isinstance(exc, Exception):
        return None
    for e in _chain(exc):
        if isinstance(e, OSError) and e.errno is not None and (any_oserror or e.errno in WRITE_ERRNOS):
            return describe_errno(e.errno, e.strerror)
    text = str(exc)
    if type(exc).__name__ == "SafetensorError" or "I/O error" in text:
        m = _OS_ERROR.search(text)
        if m and (any_oserror or int(m.group(1)) in WRITE_ERRNOS):
            return describe_errno(int(m.group(1)))
        if type(exc).__name__ == "SafetensorError" and "I/O error" in text:
            return " ".join(text.split("I/O error:", 1)[1].split())[:160] or _diagnose(path)
    if isinstance(exc, RuntimeError) and _TORCH_WRITE.search(text):
        return _diagnose(path)
    return None


@contextlib.contextmanager
def writing(path: str | os.PathLike, what: str, after: str = "", any_oserror: bool = True) -> Iterator[None]:
    """Inside the block, a failed write (`write_failure`) becomes one DegustaError: "<path>: cannot write the
    <what> (<cause>)<after>"; a DegustaError or any other exception passes unchanged."""
    try:
        yield
    except Exception as e:
        cause = write_failure(e, path, any_oserror=any_oserror)
        if cause is None:
            raise
        named = getattr(e, "filename", None) if isinstance(e, OSError) else None
        where = named if named and not Path(str(named)).name.startswith(".") else path  # not a hidden temp file
        raise DegustaError(f"{where}: cannot write the {what} ({cause}){after}") from None
