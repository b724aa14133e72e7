"""One writer at a time: an exclusive lock on every folder or file a command writes, refused in one line.

Usage:
    from degusta_learn.files.locks import hold
    with hold("runs/eval", "output folder"):      # lock file runs/.eval.degusta-lock, beside the folder
        ...                                         # a second `hold` of runs/eval, in any process: LockHeld

What it promises. `hold(path)` takes an exclusive, non-blocking lock for `path` (a folder or a file, existing
or not). A second process asking for the same path while the first holds it gets `LockHeld`, a DegustaError
whose one line names the path and the holder: its pid, command and start time (written into the lock file).
Nothing waits: the second writer is told at once. Two spellings of one path (relative / absolute, a symlink)
share one lock. The lock is the operating system's (POSIX `fcntl.flock`; Windows `msvcrt.locking`), so it is
released when the holder exits however it exits: a SIGKILL or a crash leaves at most a stale lock *file*,
which the next writer simply takes over. Within one process the lock is re-entrant for the thread holding it
(a trainer holds its run folder and `fit` asks again); another thread is refused like another process.

Where lock files live. Beside the path, never inside it: `<parent>/.<name>.degusta-lock`. An output folder
is swapped in whole (folders.write_folder), a model folder may be uploaded as it is, a dataset folder is read
by name: a lock file inside any of them would be replaced with it, uploaded with it or mistaken for a user's
file. The file is hidden (a leading dot), named for the tool, and removed when the lock is released; only a
killed holder leaves one behind (harmless, see above). `is_lock_file(name)` tells them apart.

Where locking is not possible (no fcntl and no msvcrt, or a file system that refuses locks, e.g. some NFS
mounts: ENOLCK / EOPNOTSUPP), `hold` goes on unlocked with one note on stderr per path; a lock file that cannot
be created at all (a read-only or full disk, a missing permission) is not an error here either: the write that
follows fails with its own one-line message naming the path.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import hashlib
import json
import os
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from degusta_learn.errors import DegustaError

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows and exotic platforms
    fcntl = None
try:  # Windows
    import msvcrt
except ImportError:
    msvcrt = None

SUFFIX = ".degusta-lock"
"""The end of every lock file's name (`.<name>.degusta-lock`)."""
_WINDOWS_BYTE = 2**31 - 2
"""Windows locks a byte range: one byte far past the holder record, so the record stays readable."""
_UNSUPPORTED = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, getattr(errno, "ENOTSUP", errno.EOPNOTSUPP)}
_HELD = {errno.EAGAIN, errno.EACCES, getattr(errno, "EWOULDBLOCK", errno.EAGAIN), getattr(errno, "EDEADLK", -1),
         getattr(errno, "EDEADLOCK", -1)}


class LockHeld(DegustaError):
    """Another process (or thread) is writing this path right now."""


@dataclass
class Lock:
    """A held lock: `path` (what it protects), `file` (the lock file), `made` (the outermost folder `hold` created
    to put the lock file in, None: it made none)."""

    path: Path
    file: Path
    made: Path | None = None
    fd: int | None = None
    depth: int = 1
    owner: int = 0


_held: dict[str, Lock] = {}
_registry = threading.Lock()
_noted: set[str] = set()


def lock_file(path: str | os.PathLike) -> Path:
    """The lock file of `path`: `.<name>.degusta-lock` beside it, symlinks resolved (so every spelling of one
    folder has one lock); a very long name is shortened with a hash (file names end at 255 bytes)."""
    real = Path(os.path.realpath(os.path.abspath(os.fspath(path))))
    name = real.name or "root"
    if len(name.encode()) > 200:
        name = name[:120] + "-" + hashlib.sha256(name.encode()).hexdigest()[:16]
    return real.parent / f".{name}{SUFFIX}"


def is_lock_file(name: str) -> bool:
    """Whether an entry name is one of these lock files (never a user's file or an output)."""
    return name.startswith(".") and name.endswith(SUFFIX)


def holder_record() -> dict:
    """What a lock file says about its holder: pid, command, start time, host."""
    first = sys.argv[0] if sys.argv else ""
    name = Path(first).name
    if name in ("", "-c"):
        name = "python -c"
    elif name in ("cli.py", "__main__.py") and "degusta_learn" in first:  # python -m degusta_learn.cli
        name = "degusta"
    command = " ".join(" ".join([name, *sys.argv[1:]]).split())
    return {"pid": os.getpid(), "command": command[:300],
            "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "host": socket.gethostname()}


def describe_holder(file: Path) -> str:
    """The holder of lock `file` in words, from its record ("pid 123 (degusta train ...), since ...")."""
    try:
        with open(file, encoding="utf-8", errors="replace") as f:
            record = json.loads(f.read(4096).strip() or "{}")
    except (OSError, ValueError):
        record = {}
    if not isinstance(record, dict) or "pid" not in record:
        return "another process (it has not recorded itself yet)"
    here = socket.gethostname()
    host = f" on {record['host']}" if record.get("host") and record.get("host") != here else ""
    command = " ".join(str(record.get("command", "")).split())[:160]
    return (f"pid {record['pid']}{host}" + (f" ({command})" if command else "")
            + (f", since {record['started']}" if record.get("started") else ""))


def _try_lock(fd: int) -> bool:
    """Lock `fd` exclusively without waiting: True when taken, False when another holds it."""
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        else:
            os.lseek(fd, _WINDOWS_BYTE, os.SEEK_SET)
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
    except OSError as e:
        if e.errno in _HELD:
            return False
        raise
    return True


def _unlock(fd: int) -> None:
    with contextlib.suppress(OSError):
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_UN)
        elif msvcrt is not None:
            os.lseek(fd, _WINDOWS_BYTE, os.SEEK_SET)
            msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def _same_file(fd: int, file: Path) -> bool:
    """Whether `file` still names the open file `fd` (a releasing holder may have just removed it)."""
    try:
        a, b = os.fstat(fd), os.stat(file)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _make_parents(folder: Path) -> Path | None:
    """Create `folder` and its missing parents; returns the outermost one created (None: it existed)."""
    missing = [p for p in [folder, *folder.parents] if not p.exists()]
    folder.mkdir(parents=True, exist_ok=True)
    return missing[-1] if missing else None


def _note(key: str, text: str) -> None:
    if key not in _noted:
        _noted.add(key)
        print(f"degusta: note: {text}", file=sys.stderr)


def _acquire(path: Path, what: str, file: Path) -> Lock:
    lock = Lock(path, file, owner=threading.get_ident())
    if fcntl is None and msvcrt is None:  # pragma: no cover
        _note(str(file), f"this platform has no file locking; {path} is written without a lock (do not run two "
                         "commands into it at once)")
        return lock
    try:
        lock.made = _make_parents(file.parent)
    except OSError:
        return lock  # the write itself will fail, naming the path (see the module docstring)
    for _ in range(20):  # a holder releasing right now removes the file we opened: open the new one
        flags = getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOINHERIT", 0)
        try:
            fd = os.open(file, os.O_RDWR | os.O_CREAT | flags, 0o666)
        except PermissionError:  # another user's lock file: a read-only descriptor locks it as well
            try:
                fd = os.open(file, os.O_RDONLY | flags)
            except OSError:
                return lock
        except OSError:
            return lock
        try:
            taken = _try_lock(fd)
        except OSError as e:
            os.close(fd)
            if e.errno in _UNSUPPORTED:
                _note(str(file), f"the file system of {path} refuses file locks ({e.strerror}); it is written "
                                 "without a lock (do not run two commands into it at once)")
                return lock
            return lock
        if not taken:
            os.close(fd)
            holder = describe_holder(file)
            for _ in range(10):  # the holder writes its record just after taking the lock: give it a moment
                if not holder.startswith("another process"):
                    break
                time.sleep(0.02)
                holder = describe_holder(file)
            raise LockHeld(f"{path}: {holder} is writing this {what} right now; wait for it to finish or write "
                           f"elsewhere (lock: {file})")
        if _same_file(fd, file):
            break
        _unlock(fd)
        os.close(fd)
    else:  # pragma: no cover - 20 holders in a row released under us
        raise LockHeld(f"{path}: other processes keep taking the lock of this {what}; try again (lock: {file})")
    lock.fd = fd
    with contextlib.suppress(OSError):  # the record is a courtesy to the refused: a full disk must not stop us
        data = (json.dumps(holder_record()) + "\n").encode()
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, data)
    return lock


def _release(lock: Lock) -> None:
    if lock.fd is None:
        return
    if os.name != "nt" and _same_file(lock.fd, lock.file):  # remove it while still holding it
        with contextlib.suppress(OSError):
            os.unlink(lock.file)
    _unlock(lock.fd)
    with contextlib.suppress(OSError):
        os.close(lock.fd)
    lock.fd = None


@contextlib.contextmanager
def hold(path: str | os.PathLike, what: str = "folder", enabled: bool = True) -> Iterator[Lock]:
    """Hold the exclusive lock of `path` inside the block (module docstring); `what` names it in the refusal
    ("run folder", "dataset", "ledger"). `enabled=False` yields without locking (the other ranks of a run).

    Raises:
        LockHeld: another process or thread holds it (one line: the path, the holder's pid, command and start
            time, the lock file).
    """
    path = Path(path)
    if not enabled:
        yield Lock(path, lock_file(path))
        return
    file = lock_file(path)
    key = str(file)
    with _registry:
        mine = _held.get(key)
        if mine is not None and mine.owner == threading.get_ident():
            mine.depth += 1
            reentered = mine
        else:
            reentered = None
    if reentered is not None:
        try:
            yield Lock(path, file, None, reentered.fd, reentered.depth, reentered.owner)
        finally:
            with _registry:
                reentered.depth -= 1
        return
    if mine is not None:  # another thread of this process
        raise LockHeld(f"{path}: another thread of this process (pid {os.getpid()}) is writing this {what} "
                       f"right now (lock: {file})")
    lock = _acquire(path, what, file)
    with _registry:
        _held[key] = lock
    try:
        yield lock
    finally:
        with _registry:
            _held.pop(key, None)
        _release(lock)


def remove_made(lock: Lock) -> None:
    """After release: remove the folders `hold` made for the lock file, while they are empty."""
    if lock.made is None:
        return
    for p in [lock.file.parent, *lock.file.parent.parents]:
        if p != lock.made and lock.made not in p.parents:
            break
        try:
            p.rmdir()
        except OSError:
            break
