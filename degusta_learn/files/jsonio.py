"""Strict, line-numbered JSON / JSONL reading, and JSON writing that its reader always accepts (stdlib only).

Every JSON file the toolkit reads goes through `read_json` / `read_jsonl`, which turn anything wrong with the file
into one `DegustaError` naming the file (and line, and where it can the field): a missing file, a folder, a
symbolic-link loop, a device, non-UTF-8 bytes, invalid JSON, NaN / Infinity, a float that overflows to infinity, an
integer of more than MAX_INT_DIGITS digits, a key given twice in one object, nesting too deep for the parser, a
lone-surrogate escape, a file or line over the size limits.

Every JSON file it writes goes through `atomic_write_json` / `atomic_write_jsonl` (atomically, `atomic.atomic_open`),
which refuse a record the readers would refuse (a non-UTF-8 string), so a record that said it was written can always
be read back.

Usage:
    from degusta_learn.files.jsonio import atomic_write_json, read_json, read_jsonl
    atomic_write_json("runs/x/meta.json", {"seed": 0})
    for line, row in read_jsonl("data/naturalistic/arrangements.jsonl"): ...
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import atomic_open, atomic_write_text
from degusta_learn.files.paths import NOT_UTF8, not_utf8, path_problem, shown_path

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
