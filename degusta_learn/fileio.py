"""Atomic file writing and strict, line-numbered JSON / JSONL reading (stdlib only).

Every file the toolkit writes goes through `atomic_write_*`: the content lands in a temporary file in
the same folder and is renamed over the target, so a reader never sees half a file and an interrupted
run never leaves a truncated output behind.

Every JSON file the toolkit reads goes through `read_json` / `read_jsonl`, which turn anything wrong
with the file into one `DegustaError` naming the file (and line, and where it can the field): a missing
file, a folder, a symbolic-link loop, a device, non-UTF-8 bytes, invalid JSON, NaN / Infinity, a float
that overflows to infinity, an integer of more than MAX_INT_DIGITS digits, a key given twice in one
object, nesting too deep for the parser, a lone-surrogate escape, a file or line over the size limits.

`file_sha256` and `stat_tree` identify files (by their bytes, or cheaply by size and time): the dataset
fingerprint (`scene.dataset.dataset_identity`) and compare's staleness records are built from them.
"""

from __future__ import annotations

import contextlib
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


def target_problem(path: str | os.PathLike) -> str | None:
    """Why a file cannot be written at `path` (a folder there, a parent that is a file), or None."""
    path = Path(path)
    if str(path) in ("", "."):
        return "is an empty path; give the path of a file to write"
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
    path = Path(path)
    problem = target_problem(path)
    if problem:
        raise DegustaError(f"{path}: {problem}")
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
    path = Path(out)
    problem = target_problem(path)
    if problem:
        raise DegustaError(f"{key}: {path}: {problem}")
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


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def atomic_write_jsonl(path: str | os.PathLike, rows: Iterable[Any]) -> None:
    with atomic_open(path, "w") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")


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
    most `limit` bytes; anything else (missing, a folder, a symlink loop, a device) is a one-line DegustaError."""
    try:
        st = path.stat()
    except FileNotFoundError:
        if path.is_symlink():
            raise DegustaError(f"{path}: broken symbolic link (its target does not exist)") from None
        raise DegustaError(f"{path}: file not found") from None
    except OSError as e:  # a symlink loop (ELOOP), a path through a file (ENOTDIR), no permission ...
        raise DegustaError(f"{path}: cannot read ({e.strerror or e})") from None
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


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; a missing, unreadable or malformed file raises DegustaError naming it (and the line).

    Strict: non-UTF-8 bytes, NaN/Infinity, numbers that overflow or have more than MAX_INT_DIGITS digits,
    deep nesting, folders, symlink loops and files over MAX_JSON_BYTES are errors, never tracebacks.
    """
    path = Path(path)
    with open_regular(path, MAX_JSON_BYTES) as f:
        try:
            data = f.read(MAX_JSON_BYTES + 1)
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
    except OSError:
        return None
    return h.hexdigest()


def stat_tree(path: str | os.PathLike, limit: int = 5000) -> list:
    """[relative path, size, mtime_ns] of a file, or of the files under a folder (sorted, at most `limit`):
    a cheap identity of a checkpoint or picture folder, without reading the bytes."""
    path = Path(path)
    if path.is_file():
        st = path.stat()
        return [[path.name, st.st_size, st.st_mtime_ns]]
    out = []
    for root, dirs, files in os.walk(path):
        dirs.sort()
        for name in sorted(files):
            full = Path(root) / name
            try:
                st = full.stat()
            except OSError:
                continue
            out.append([str(full.relative_to(path)), st.st_size, st.st_mtime_ns])
            if len(out) >= limit:
                return out
    return out
