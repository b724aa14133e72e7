"""Paths a user gives: checked once, where they are first touched, and shown safely in one-line messages.

Every path a user gives (a flag, a config's path key, a dataset or model folder) is checked once by `check_path` /
`user_path`: `~` expanded, and anything that would make `pathlib` or `os` raise (a NUL byte, a name or path longer
than the file system takes, a parent that is a file, a link loop, no permission) or that the toolkit could not write
back into its UTF-8 records (non-UTF-8 bytes) is one `DegustaError` naming the flag or key and the path. The readers
(`jsonio.open_regular`) and writers (`target_problem`, `atomic.atomic_open`) run the same check, so a library caller
gets the same one line. `shown_path` writes any path into a message as plain, escaped text.

Usage:
    from degusta_learn.files.paths import user_path
    folder = user_path("~/data/naturalistic", "dataset")      # Path, or DegustaError "dataset: ...: why"
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError

NAME_MAX = 255
"""Most bytes of one file or folder name (Linux and macOS file systems; `os.pathconf` is asked first)."""

PATH_MAX = 4096
"""Most bytes of a path the kernel takes (Linux PATH_MAX, its closing NUL included): longer ones are refused."""


def shown_path(path: Any, limit: int = 160) -> str:
    """`path` for a one-line message: as it is when it is plain text, else escaped (a NUL byte, a control character,
    non-UTF-8 bytes show as \\x00, \\n, \\udcff); a long one is cut to `limit` characters and says its length."""
    try:
        text = os.fsdecode(os.fspath(path))
    except TypeError:
        return repr(path)[:limit]
    shown = text if text.isprintable() and not_utf8(text) is None else repr(text)[1:-1]
    if len(shown) > limit:
        tail = 24 if limit >= 80 else 0
        shown = f"{shown[:limit - tail]}...{shown[len(shown) - tail:] if tail else ''} ({len(text):,} characters)"
    return shown


def not_utf8(text: str) -> str | None:
    """None for text that encodes as UTF-8; else what does not ("byte 0xff": an undecodable byte Python kept as a
    surrogate escape, as os.fsdecode and sys.argv do; "U+D800": any other lone surrogate)."""
    try:
        text.encode("utf-8")
        return None
    except UnicodeEncodeError as e:
        code = ord(text[e.start])
        return f"byte {code - 0xDC00:#04x}" if 0xDC80 <= code <= 0xDCFF else f"U+{code:04X}"


NOT_UTF8 = ("degusta writes paths into UTF-8 records (JSON, YAML, reports) that it must read back, so it takes "
            "UTF-8 paths only: rename it (or copy it to a UTF-8 name)")


def _name_max(text: str) -> int:
    folder = os.path.dirname(os.path.abspath(text))
    for _ in range(64):
        if os.path.isdir(folder):
            try:
                return int(os.pathconf(folder, "PC_NAME_MAX")) or NAME_MAX
            except (OSError, ValueError):
                return NAME_MAX
        if os.path.dirname(folder) == folder:
            break
        folder = os.path.dirname(folder)
    return NAME_MAX


def _file_parent(text: str) -> str | None:
    """The first parent of `text` (from the top) that exists and is not a folder."""
    parts = Path(text).parents
    for parent in reversed(parts):
        try:
            if os.path.lexists(parent) and not os.path.isdir(parent):
                return str(parent)
        except (OSError, ValueError):
            return None
    return None


def path_problem(path: Any, probe: bool = True) -> str | None:
    """Why `path` cannot name a file or folder whatever a command does with it, or None. Never raises.

    From its text: a NUL byte; non-UTF-8 (see NOT_UTF8); a name over the file system's limit (NAME_MAX bytes); a
    path over PATH_MAX bytes. From probing it (stat only, nothing written): a parent that is a file, a symbolic-link
    loop, a folder that may not be searched (never as root), a broken symbolic link (nothing to read; writing would
    replace the link, not make what it points to), a link that resolves to a non-UTF-8 name.
    A missing path is not a problem here: readers say "not found", writers make it. `probe=False`: the text
    checks only (a reader that stats the file itself and says what it finds).
    """
    try:
        text = os.fspath(path)
    except TypeError:
        return f"expected a path, got {type(path).__name__}"
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if "\0" in text:
        return "holds a NUL byte (\\0), which no file name may contain"
    bad = not_utf8(text)
    if bad:
        return f"is not UTF-8 ({bad}); {NOT_UTF8}"
    name_max = _name_max(text)
    for part in text.split(os.sep):
        size = len(part.encode("utf-8"))
        if size > name_max:
            return (f"holds a name of {size:,} bytes ({shown_path(part, 40)}); the file system takes names of at most "
                    f"{name_max} bytes")
    size = len(os.path.abspath(text).encode("utf-8"))
    if size >= PATH_MAX:
        return f"is {size:,} bytes long as an absolute path; paths may be at most {PATH_MAX - 1:,} bytes"
    if not probe:
        return None
    try:
        os.stat(text)
        exists = True
    except FileNotFoundError:
        exists = False
        if os.path.islink(text):
            try:
                to = f" (to {shown_path(os.readlink(text), 80)})"
            except OSError:
                to = ""
            return f"is a broken symbolic link{to}; remove the link or give another path"
    except NotADirectoryError:
        parent = _file_parent(text)
        return f"a parent, {shown_path(parent)}, is a file, not a folder" if parent else "a parent is not a folder"
    except PermissionError:
        return "cannot be reached: a folder on the way may not be searched (permission denied)"
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "goes through a symbolic-link loop"
        return f"cannot be used ({e.strerror or e})"
    except ValueError as e:  # pragma: no cover - the text checks above catch what os.stat refuses
        return f"is not a valid path ({e})"
    if exists:
        real = os.path.realpath(text)
        bad = not_utf8(real)
        if bad and not_utf8(os.path.abspath(text)) is None:
            return f"resolves (through a symbolic link) to {shown_path(real)}, which is not UTF-8 ({bad}); {NOT_UTF8}"
    return None


def check_path(value: Any, probe: bool = True) -> tuple[str, str | None]:
    """The one check of a path a user gives: (its text with a leading `~` or `~user` expanded, why it cannot be
    used or None). Used by the CLI's path flags, the config loader's path keys and `user_path`. `probe=False`:
    the text checks only (`path_problem`)."""
    try:
        text = os.fsdecode(os.fspath(value))
    except TypeError:
        return str(value), f"expected a path, got {type(value).__name__}"
    if "\0" in text:
        return text, path_problem(text)
    if text.startswith("~"):
        head = text.split(os.sep, 1)[0]
        bad = not_utf8(head)
        if bad:
            return text, f"is not UTF-8 ({bad}); {NOT_UTF8}"
        expanded = os.path.expanduser(text)
        if expanded.startswith("~"):
            if head == "~":
                return text, "starts with ~, but there is no home folder to expand it to (HOME is not set)"
            return text, (f"starts with {head}, but there is no user {head[1:]!r} whose home it could name (for a "
                          f"folder called {head}, write ./{head})")
        text = expanded
    return text, path_problem(text, probe=probe)


def user_path(value: Any, key: str) -> Path:
    """`value` (a path a user gave through `key`: a flag, a config key, an argument) with `~` expanded, or one
    DegustaError "KEY: PATH: why" (check_path)."""
    if not str(value).strip():
        raise DegustaError(f"{key}: the path is empty; give a file or folder")
    text, problem = check_path(value)
    if problem:
        raise DegustaError(f"{key}: {shown_path(value)}: {problem}")
    return Path(text)


def target_problem(path: str | os.PathLike) -> str | None:
    """Why a file cannot be written at `path` (a folder there, a parent that is a file, any `path_problem`), or None."""
    if str(path) in ("", "."):
        return "is an empty path; give the path of a file to write"
    problem = path_problem(path)
    if problem:
        return problem
    path = Path(path)
    if path.is_dir():
        return "is a folder; give the path of a file to write"
    try:
        mode = os.stat(path).st_mode
    except OSError:
        mode = None
    if mode is not None and not stat.S_ISREG(mode):
        return "exists and is not a regular file (a device, pipe or socket); give the path of a file to write"
    for parent in path.parents:
        if parent.is_dir():
            break
        if parent.exists() or parent.is_symlink():
            kind = "a broken link" if not parent.exists() else "a file"
            return f"a parent, {parent}, is {kind}, not a folder"
    return None


PACKAGE_DIR = Path(__file__).resolve().parents[1]
SHIPPED_ROOTS = (PACKAGE_DIR / "shipped_models", PACKAGE_DIR / "configs")
"""What is installed with degusta_learn (its models and configs): no command writes there, whatever path it is given,
except a pretraining run asked by name to replace the shipped base (`allow_shipped`)."""


def shipped_problem(out: str | os.PathLike) -> str | None:
    """Why `out` may not be written (it is, or is inside, a folder of models or configs shipped with the package),
    or None."""
    try:
        real = os.path.realpath(os.fspath(out))
    except (OSError, ValueError):
        return None  # path_problem names it
    for root in SHIPPED_ROOTS:
        folder = os.path.realpath(root)
        if real == folder or real.startswith(folder + os.sep):
            return (f"is {'inside ' if real != folder else ''}{root}, which holds the "
                    f"{'models' if root.name == 'shipped_models' else 'configs'} shipped with degusta_learn; "
                    "write to a folder of your own (training writes to runs/ by default)")
    return None


def refuse_shipped(out: str | os.PathLike, key: str | None = None) -> None:
    """Refuse (one DegustaError naming `key`) an output inside the package's shipped models or configs."""
    problem = shipped_problem(out)
    if problem:
        raise DegustaError(f"{key + ': ' if key else ''}{shown_path(out)} {problem}")
