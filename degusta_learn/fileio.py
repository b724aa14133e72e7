"""Atomic file writing and strict, line-numbered JSON / JSONL reading (stdlib only).

Every file the toolkit writes goes through `atomic_write_*`: the content lands in a temporary file in
the same folder and is renamed over the target, so a reader never sees half a file and an interrupted
run never leaves a truncated output behind.

Every JSON file the toolkit reads goes through `read_json` / `read_jsonl`, which turn anything wrong
with the file into one `DegustaError` naming the file (and line, and where it can the field): a missing
file, a folder, a symbolic-link loop, a device, non-UTF-8 bytes, invalid JSON, NaN / Infinity, a float
that overflows to infinity, an integer of more than MAX_INT_DIGITS digits, a key given twice in one
object, nesting too deep for the parser, a lone-surrogate escape, a file or line over the size limits.

Every path a user gives (a flag, a config's path key, a dataset or model folder) is checked once, where it is first
touched, by `check_path` / `user_path`: `~` expanded, and anything that would make `pathlib` or `os` raise (a NUL
byte, a name or path longer than the file system takes, a parent that is a file, a link loop, no permission) or
that the toolkit could not write back into its UTF-8 records (non-UTF-8 bytes) is one `DegustaError` naming the
flag or key and the path. The readers (`open_regular`) and writers (`target_problem`, `atomic_open`) run the same
check, so a library caller gets the same one line; and no JSON writer ever writes a record its reader refuses.

`file_sha256` and `stat_tree` identify files (by their bytes, or cheaply by size and time): the dataset
fingerprint (`scene.dataset.dataset_identity`) and compare's staleness records are built from them.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


UMASK = _current_umask()  # the process's umask, read once (os.umask can only be read by setting it)


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


def _why(e: OSError) -> str:
    return f"cannot write here: {e.strerror or e}" if not isinstance(e, IsADirectoryError) else \
        "is a folder; give the path of a file to write"


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w") -> Iterator[Any]:
    """Open a temporary file beside `path`; on success rename it over `path`, on error remove it.

    A path that cannot be written (a folder, under a file, a read-only or virtual file system, a full
    disk) raises DegustaError naming the path and the reason; no temporary file is left behind.
    """
    problem = target_problem(path)
    if problem:
        raise DegustaError(f"{shown_path(path)}: {problem}")
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise DegustaError(f"{path}: {_why(e)}") from None
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~UMASK)  # mkstemp makes 0600 files; outputs get the usual permissions
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise DegustaError(f"{path}: {_why(e)}") from None
        if isinstance(e, UnicodeEncodeError):  # text holding a lone surrogate (a non-UTF-8 name): never half-written
            raise DegustaError(f"{shown_path(path)}: the text to write is not UTF-8 ({not_utf8(e.object)}), so "
                               "nothing was written; " + NOT_UTF8) from None
        raise


DATASET_FILES = ("catalog.json", "tables.json", "arrangements.jsonl", "ratings.jsonl", "meta.json")
"""The files of a dataset folder (scene/dataset.py); with the files its meta.json names and everything in its
subfolders (pictures), an output never replaces them."""


def _real(path: str | os.PathLike) -> str:
    return os.path.realpath(os.path.abspath(path))


def _inside(path: str, folder: str) -> bool:
    return path.startswith(folder.rstrip(os.sep) + os.sep)


def _looks_like_dataset(folder: str) -> bool:
    return all(os.path.isfile(os.path.join(folder, n)) for n in ("catalog.json", "arrangements.jsonl"))


def _dataset_part(root: str, out: str) -> str | None:
    """What of the dataset folder `root` writing `out` (real paths) would replace, or None."""
    if out == root or _inside(root, out):
        return f"holds the dataset folder {root}"
    if not _inside(out, root):
        return None
    rel = Path(os.path.relpath(out, root))
    if len(rel.parts) == 1 and rel.name in DATASET_FILES:
        return f"is the dataset file {rel} of {root}"
    if len(rel.parts) > 1 and os.path.lexists(out):
        return f"is {rel}, a file of the dataset {root}"
    try:
        meta = read_json(Path(root) / "meta.json") if os.path.isfile(os.path.join(root, "meta.json")) else {}
    except DegustaError:
        meta = {}
    if isinstance(meta, dict):
        for key, value in meta.items():
            if isinstance(value, str) and value and _real(os.path.join(root, value)) == out:
                return f"is {rel}, the file the dataset's meta.json names as '{key}'"
    return None


def refuse_overwriting_inputs(out: str | os.PathLike, inputs: Iterable[tuple[str, Any]] = (), key: str = "out",
                              datasets: Iterable[Any] = ()) -> None:
    """Refuse (DegustaError naming `key` and both paths) an output path that would replace an input.

    `out` is a file the command writes (or an entry of an output folder it replaces). `inputs` are
    (what, path) pairs of the files the command reads (its config, episodes, predictions, response cache,
    ...; None skipped): `out` may be none of them (same path, a link to it, or a folder holding it).
    `datasets` are the dataset folders it reads; any dataset folder enclosing `out` counts too: `out`
    may not be one of its files (DATASET_FILES, a file meta.json names, anything in its subfolders), but a
    new file beside them is fine. The one guard of every command that writes (predict, data episodes,
    evaluate, compare, render).
    """
    if str(out).strip() in ("", "."):
        raise DegustaError(f"{key}: the output path is empty; give the path of a file to write")
    target = _real(out)
    for what, path in inputs:
        if path is None or not str(path).strip():
            continue
        real = _real(path)
        same = real == target
        if not same and os.path.exists(path) and os.path.exists(out):
            with contextlib.suppress(OSError):
                same = os.path.samefile(path, out)
        if same:
            raise DegustaError(f"{key}: {out} is {what} ({path}); writing there would destroy it, so nothing "
                               "was written: choose another path")
        if _inside(real, target):
            raise DegustaError(f"{key}: {out} holds {what} ({path}); writing there would remove it, so nothing "
                               "was written: choose another path")
    roots = {_real(d) for d in datasets if d is not None and str(d).strip()}
    parent = os.path.dirname(target)
    for _ in range(64):  # every dataset folder above `out`, named or not
        if _looks_like_dataset(parent):
            roots.add(parent)
        if os.path.dirname(parent) == parent:
            break
        parent = os.path.dirname(parent)
    for root in sorted(roots):
        part = _dataset_part(root, target)
        if part:
            raise DegustaError(f"{key}: {out} {part}; writing it would change a dataset, so nothing was written: "
                               "choose a path outside the dataset's files")


def check_output_file(out: str | os.PathLike, inputs: Iterable[tuple[str, Any]] = (), key: str = "out",
                      datasets: Iterable[Any] = ()) -> Path:
    """Before any work: refuse an output file that would replace an input (refuse_overwriting_inputs) or
    that cannot be written (a folder, under a file, a folder where files cannot be made); returns the path.
    Probing makes and removes one temporary file in the output's folder when that folder exists."""
    if str(out).strip() in ("", "."):
        raise DegustaError(f"{key}: the output path is empty; give the path of a file to write")
    if isinstance(out, str) and out.endswith(("/", os.sep)):
        raise DegustaError(f"{key}: {out} ends in a slash, a folder; give the path of a file to write (e.g. "
                           f"{out}predictions.jsonl)")
    problem = target_problem(out)
    if problem:
        raise DegustaError(f"{key}: {shown_path(out)}: {problem}")
    path = Path(out)
    refuse_overwriting_inputs(out, inputs, key, datasets)
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if folder == path.parent:
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
            os.close(fd)
            os.unlink(tmp)
        except OSError as e:
            raise DegustaError(f"{key}: {path}: {_why(e)}") from None
    elif not os.access(folder, os.W_OK | os.X_OK):
        raise DegustaError(f"{key}: {path}: cannot write here: {folder} is not writable")
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_open(path, "w") as f:
        f.write(text)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_open(path, "wb") as f:
        f.write(data)


def _refuse_unreadable(path: str | os.PathLike, text: str, obj: Any, where: str = "") -> None:
    """Refuse to write JSON that `read_json` / `read_jsonl` would refuse: a string holding a lone surrogate (a
    non-UTF-8 file name, as os.fsdecode gives it), which json.dumps escapes as \\udcff. The JSON writers call this
    before the file is opened, so a record that said it was written can always be read back."""
    if not _SURROGATE.search(text):
        return
    field = _non_utf8_field(obj)
    if field is not None:
        name, bad = field
        raise DegustaError(f"{shown_path(path)}: {where}{f'field {name!r}' if name else 'a value'} is not UTF-8 "
                           f"({bad}), so the record was not written (its reader would refuse it); {NOT_UTF8}")


def _non_utf8_field(obj: Any) -> tuple[str, str] | None:
    """(dotted name, what) of the first string (key or value) of `obj` that is not UTF-8, or None."""
    stack: list[tuple[Any, str]] = [(obj, "")]
    while stack:
        o, name = stack.pop()
        if isinstance(o, str):
            bad = not_utf8(o)
            if bad:
                return name, bad
        elif isinstance(o, dict):
            for k, v in o.items():
                sub = f"{name}.{k}" if name else str(k)
                stack.append((k, sub))
                stack.append((v, sub))
        elif isinstance(o, (list, tuple)):
            stack.extend((v, f"{name}[{i}]") for i, v in enumerate(o))
    return None


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    text = json.dumps(obj, indent=2) + "\n"
    _refuse_unreadable(path, text, obj)
    atomic_write_text(path, text)


def atomic_write_jsonl(path: str | os.PathLike, rows: Iterable[Any]) -> None:
    with atomic_open(path, "w") as f:
        for i, row in enumerate(rows, start=1):
            line = json.dumps(row)
            _refuse_unreadable(path, line, row, where=f"line {i}: ")
            f.write(line + "\n")


# Limits of the readers: anything beyond them is refused with a DegustaError naming the file (and line).
# Module-level so a caller (or a test) can change them.
MAX_JSON_BYTES = 256 * 2**20  # one JSON file
MAX_JSONL_BYTES = 4 * 2**30  # one JSONL file
MAX_LINE_BYTES = 64 * 2**20  # one JSONL line
MAX_INT_DIGITS = 20  # any integer the toolkit reads fits in 64 bits (seeds up to 2**64 included)


class _BadValue(ValueError):
    """Raised by the parse hooks; `token` is the offending literal (to find its line)."""

    def __init__(self, message: str, token: str):
        super().__init__(message)
        self.token = token


def _parse_int(s: str) -> int:
    if len(s.lstrip("-")) > MAX_INT_DIGITS:
        raise _BadValue(f"integer with {len(s.lstrip('-'))} digits is out of range", s)
    return int(s)


def _parse_float(s: str) -> float:
    value = float(s)
    if not math.isfinite(value):
        raise _BadValue(f"expected a finite number, got {_short(s)} (it overflows to infinity)", s)
    return value


def _parse_constant(s: str):
    raise _BadValue(f"expected a finite number, got {s}", s)


class _Marker:
    """Stands for an offending literal in the second, lenient parse that finds its field."""


def _mark_int(s: str):
    return _Marker() if len(s.lstrip("-")) > MAX_INT_DIGITS else 0


def _mark_float(s: str):
    return 0.0 if math.isfinite(float(s)) else _Marker()


def _object(pairs: list) -> dict:
    obj = dict(pairs)
    if len(obj) != len(pairs):  # {"x": 0.1, "x": 0.9} would silently keep the last value
        seen = set()
        dup = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise ValueError(f"duplicate key {_short(repr(dup), 40)} in one object")
    return obj


_DECODER = json.JSONDecoder(parse_int=_parse_int, parse_float=_parse_float, parse_constant=_parse_constant,
                            object_pairs_hook=_object)
_LENIENT = json.JSONDecoder(parse_int=_mark_int, parse_float=_mark_float, parse_constant=lambda s: _Marker())
_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[^"\s,:\[\]{}]+')
_SURROGATE = re.compile(r"\\u[dD][89a-fA-F]")


def _field_of(text: str) -> str:
    """'entry 4: field 'id'' / 'field 'placements[0].y'': where the first offending literal sits, or ''."""
    try:
        obj = _LENIENT.decode(text)
    except (ValueError, RecursionError, MemoryError):
        return ""
    stack: list[tuple[Any, tuple]] = [(obj, ())]
    while stack:  # depth-first in document order (dicts keep their keys' order)
        o, trail = stack.pop()
        if isinstance(o, _Marker):
            break
        if isinstance(o, dict):
            stack.extend(reversed([(v, (*trail, str(k))) for k, v in o.items()]))
        elif isinstance(o, list):
            stack.extend(reversed([(v, (*trail, i)) for i, v in enumerate(o)]))
    else:
        return ""
    prefix = ""
    if trail and isinstance(trail[0], int):  # a top-level list: entry i, as the dataset checks name them
        prefix, trail = f"entry {trail[0]}: ", trail[1:]
    name = "".join(f"[{t}]" if isinstance(t, int) else f".{t}" for t in trail).lstrip(".")
    return f"{prefix}field '{name}': " if name else prefix


def _short(s: str, n: int = 20) -> str:
    return s if len(s) <= n else f"{s[:n]}... ({len(s)} characters)"


def _line_of(text: str, token: str) -> int | None:
    """Line (1-based) of the first occurrence of the bare literal `token` in JSON `text` (not in a string)."""
    for m in _TOKENS.finditer(text):
        if m.group() == token:
            return text.count("\n", 0, m.start()) + 1
    return None


def _check_strings(obj: Any) -> None:
    """Reject strings holding lone surrogates (valid JSON escapes, but not writable as UTF-8)."""
    stack = [obj]
    while stack:
        o = stack.pop()
        if isinstance(o, str):
            o.encode("utf-8")
        elif isinstance(o, dict):
            stack.extend(o.keys())
            stack.extend(o.values())
        elif isinstance(o, list):
            stack.extend(o)


def _loads(text: str) -> Any:
    """Strict JSON: finite numbers of sane size only, bounded nesting, no lone surrogates.

    Raises _BadValue (with `.token`), json.JSONDecodeError, or ValueError with a message for the user.
    """
    try:
        obj = _DECODER.decode(text)
    except RecursionError:
        raise ValueError("nested too deeply") from None
    except MemoryError:
        raise ValueError("too large to parse") from None
    if _SURROGATE.search(text):
        try:
            _check_strings(obj)
        except UnicodeEncodeError:
            raise ValueError("a string holds an invalid \\u escape (a lone surrogate)") from None
    return obj


def open_regular(path: Path, limit: int, what: str = "a file"):
    """Open `path` for binary reading after checking that it is a regular file (`what`, for messages) of at
    most `limit` bytes; anything else (missing, a folder, a symlink loop, a device, any `path_problem`) is a one-line
    DegustaError."""
    problem = path_problem(path, probe=False)  # what makes os.stat raise other than OSError, or ENAMETOOLONG
    if problem:
        raise DegustaError(f"{shown_path(path)}: {problem}")
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        if path.is_symlink():
            raise DegustaError(f"{path}: broken symbolic link (its target does not exist)") from None
        raise DegustaError(f"{path}: file not found") from None
    except (OSError, ValueError) as e:  # a symlink loop (ELOOP), a path through a file (ENOTDIR), no permission ...
        raise DegustaError(f"{shown_path(path)}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise DegustaError(f"{path}: is a folder, expected {what}")
    if not stat.S_ISREG(st.st_mode):
        raise DegustaError(f"{path}: not a regular file")
    if st.st_size > limit:
        raise DegustaError(f"{path}: file too large ({st.st_size} bytes; the limit is {limit})")
    try:
        return open(path, "rb")
    except OSError as e:
        raise DegustaError(f"{path}: cannot read ({e.strerror or e})") from None


def read_at_most(f, limit: int, chunk: int = 2**20) -> bytes:
    """Up to `limit` bytes of `f`, read in chunks: memory grows with what the file holds (a plain `f.read(limit)`
    reserves `limit` bytes at once, 256 MiB for every small JSON file)."""
    parts, size = [], 0
    while size < limit:
        part = f.read(min(chunk, limit - size))
        if not part:
            break
        parts.append(part)
        size += len(part)
    return b"".join(parts)


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; a missing, unreadable or malformed file raises DegustaError naming it (and the line).

    Strict: non-UTF-8 bytes, NaN/Infinity, numbers that overflow or have more than MAX_INT_DIGITS digits,
    deep nesting, folders, symlink loops and files over MAX_JSON_BYTES are errors, never tracebacks.
    """
    path = Path(path)
    with open_regular(path, MAX_JSON_BYTES) as f:
        try:
            data = read_at_most(f, MAX_JSON_BYTES + 1)
        except OSError as e:
            raise DegustaError(f"{path}: cannot read ({e.strerror or e})") from None
    if len(data) > MAX_JSON_BYTES:
        raise DegustaError(f"{path}: file too large (over {MAX_JSON_BYTES} bytes)")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise DegustaError(f"{path}:{line}: not UTF-8 text (byte {data[e.start]:#04x} at offset {e.start})") from None
    try:
        return _loads(text)
    except json.JSONDecodeError as e:
        raise DegustaError(f"{path}:{e.lineno}: invalid JSON ({e.msg})") from None
    except _BadValue as e:
        line, where = _line_of(text, e.token), _field_of(text)
        raise DegustaError(f"{path}{f':{line}' if line else ''}: {where}{e}") from None
    except ValueError as e:
        raise DegustaError(f"{path}: invalid JSON ({e})") from None


def read_jsonl(path: str | os.PathLike) -> Iterator[tuple[int, Any]]:
    """Yield (line number, parsed object) for every non-blank line; errors name file and line.

    The same strict rules as `read_json`, per line; lines over MAX_LINE_BYTES and files over
    MAX_JSONL_BYTES are refused.
    """
    path = Path(path)
    with open_regular(path, MAX_JSONL_BYTES) as f:
        lineno = 0
        while True:
            try:
                raw = f.readline(MAX_LINE_BYTES + 1)
            except OSError as e:
                raise DegustaError(f"{path}:{lineno + 1}: cannot read ({e.strerror or e})") from None
            if not raw:
                return
            lineno += 1
            if len(raw) > MAX_LINE_BYTES:
                raise DegustaError(f"{path}:{lineno}: line too long (over {MAX_LINE_BYTES} bytes)")
            try:
                line = raw.decode("utf-8-sig" if lineno == 1 else "utf-8")
            except UnicodeDecodeError as e:
                raise DegustaError(f"{path}:{lineno}: not UTF-8 text (byte {raw[e.start]:#04x} at column "
                                   f"{e.start + 1})") from None
            if not line.strip():
                continue
            try:
                obj = _loads(line)
            except json.JSONDecodeError as e:
                raise DegustaError(f"{path}:{lineno}: invalid JSON ({e.msg})") from None
            except _BadValue as e:
                raise DegustaError(f"{path}:{lineno}: {_field_of(line)}{e}") from None
            except ValueError as e:
                raise DegustaError(f"{path}:{lineno}: invalid JSON ({e})") from None
            yield lineno, obj


def file_sha256(path: str | os.PathLike) -> str | None:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks; None if it cannot be read."""
    h = hashlib.sha256()
    try:
        with Path(path).open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except (OSError, ValueError):
        return None
    return h.hexdigest()


def _utf8_name(name: str) -> str:
    """A file name as UTF-8 text for an identity record: undecodable bytes as \\xff escapes (never a lone surrogate,
    which no JSON reader of the toolkit accepts); UTF-8 names are unchanged."""
    return os.fsencode(name).decode("utf-8", "backslashreplace")


def stat_tree(path: str | os.PathLike, limit: int = 5000) -> list:
    """[relative path, size, mtime_ns] of a file, or of the files under a folder (sorted, at most `limit`):
    a cheap identity of a checkpoint or picture folder, without reading the bytes. Names that are not UTF-8 are
    written with \\xff escapes (`_utf8_name`), so the identity can be stored in a JSON record and read back."""
    path = Path(path)
    if path.is_file():
        st = path.stat()
        return [[_utf8_name(path.name), st.st_size, st.st_mtime_ns]]
    out = []
    for root, dirs, files in os.walk(path):
        dirs.sort()
        for name in sorted(files):
            full = Path(root) / name
            try:
                st = full.stat()
            except OSError:
                continue
            out.append([_utf8_name(str(full.relative_to(path))), st.st_size, st.st_mtime_ns])
            if len(out) >= limit:
                return out
    return out
