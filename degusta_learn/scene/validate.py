"""Field checks shared by the dataset, episode and prediction readers.

Each check raises `DegustaError` whose message starts with ``file:line: field 'name'`` so a user knows
exactly which entry to fix.

Text is printable: every string field read through `get` (names, words, ids, episode ids, method names) and
every path refuses control and invisible characters (Unicode categories Cc, Cf, Cs, Zl, Zp: newline, tab, NUL,
U+2028, bidi overrides, zero-width characters, lone surrogates; textsafe.unprintable), so a dataset's words
cannot break a report line, a prompt or a picture's label, and two ids that look the same are the same.
"""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from degusta_learn.errors import DegustaError
from degusta_learn.textsafe import unprintable

MAX_ID = 999_999  # object and table ids: 0..MAX_ID
MAX_TRIAL = 999_999_999  # trial numbers: 0..MAX_TRIAL
MAX_STR = 1000  # characters in any string field
MAX_IMAGE_PIXELS = 50_000_000  # width x height of a catalog or table picture (also the renderer's limit)
MAX_IMAGE_BYTES = 64 * 2**20  # file size of a catalog or table picture
_PNG = b"\x89PNG\r\n\x1a\n"


class Where:
    """Location of the entry under validation: file, optional line (1-based) or list index."""

    def __init__(self, path: Any, line: int | None = None, index: int | None = None):
        self.path, self.line, self.index = path, line, index

    def __str__(self) -> str:
        if self.line is not None:
            return f"{self.path}:{self.line}"
        if self.index is not None:
            return f"{self.path}: entry {self.index}"
        return str(self.path)

    def fail(self, field: str | None, message: str) -> DegustaError:
        return DegustaError(f"{self}: field '{field}': {message}" if field else f"{self}: {message}")


def require_mapping(obj: Any, where: Where) -> dict:
    if not isinstance(obj, dict):
        raise where.fail(None, f"expected a JSON object, got {type(obj).__name__}")
    return obj


def _show(value: Any) -> str:
    """repr of a value for a message, cut short (a user's 10 MB string must not flood the terminal)."""
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:50]}... ({len(text)} characters)"


def get(obj: dict, key: str, kind: str, where: Where, optional: bool = False, default: Any = None,
        lo: float | None = None, hi: float | None = None) -> Any:
    """Fetch obj[key] checked as `kind` in {'int', 'number', 'str', 'prose', 'list', 'id', 'bool'}; NaN/inf
    rejected.

    `lo`/`hi` bound an 'int' or 'number' (inclusive); strings and ids are at most MAX_STR characters and
    printable (`printable_text`); 'prose' is a 'str' that may also hold newlines and tabs (a description).
    """
    if key not in obj or obj[key] is None:
        if optional:
            return default
        raise where.fail(key, "missing")
    value = obj[key]
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.fail(key, f"expected an integer, got {_show(value)}")
    elif kind == "bool":
        if not isinstance(value, bool):
            raise where.fail(key, f"expected true or false, got {_show(value)}")
    elif kind == "number":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise where.fail(key, f"expected a number, got {_show(value)}")
        try:
            value = float(value)
        except OverflowError:  # an integer too large for a float
            raise where.fail(key, f"expected a finite number, got {_show(value)}") from None
        if not math.isfinite(value):
            raise where.fail(key, f"expected a finite number, got {value!r}")
    elif kind in ("str", "prose"):
        if not isinstance(value, str) or not value:
            raise where.fail(key, f"expected a non-empty string, got {_show(value)}")
    elif kind == "id":  # participant ids: strings, or integers taken as their decimal string
        if isinstance(value, bool) or not isinstance(value, (str, int)) or value == "":
            raise where.fail(key, f"expected a string id, got {_show(value)}")
        value = str(value)
    elif kind == "list":
        if not isinstance(value, list):
            raise where.fail(key, f"expected a list, got {type(value).__name__}")
    else:  # pragma: no cover - programming error
        raise ValueError(kind)
    if isinstance(value, str) and len(value) > MAX_STR:
        raise where.fail(key, f"string of {len(value)} characters is too long (at most {MAX_STR})")
    if isinstance(value, str):
        printable_text(value, key, where, allow="\n\r\t" if kind == "prose" else "")
    if kind in ("int", "number") and ((lo is not None and value < lo) or (hi is not None and value > hi)):
        span = f"[{lo}, {hi}]" if lo is not None and hi is not None else f">= {lo}" if lo is not None else f"<= {hi}"
        raise where.fail(key, f"{_show(value)} is out of range (expected {span})")
    return value


def printable_text(value: str, key: str, where: Where, allow: str = "") -> str:
    """`value` must hold no control or invisible character but those in `allow` (textsafe.unprintable): one
    line, nothing hidden."""
    problem = unprintable(value, allow)
    if problem:
        raise where.fail(key, f"{_show(value)} holds {problem}; text fields must be printable (no newlines, tabs, "
                              "control or invisible characters)")
    return value


def in_vocabulary(value: str, vocabulary, key: str, where: Where) -> str:
    """`value` must be one of `vocabulary` (the dataset's words for classes, colours or materials)."""
    if value not in vocabulary:
        raise where.fail(key, f"{_show(value)} is not in the vocabulary (expected one of {', '.join(vocabulary)})")
    return value


def relative_path(value: Any, key: str, where: Where) -> str:
    """A dataset-relative path: a non-empty string, not absolute, without '..' (it must stay inside)."""
    if not isinstance(value, str) or not value:
        raise where.fail(key, f"expected a relative path string, got {_show(value)}")
    if len(value) > MAX_STR or unprintable(value):
        why = unprintable(value)
        raise where.fail(key, f"{_show(value)} is not a valid path" + (f" (it holds {why})" if why else ""))
    posix, windows = PurePosixPath(value), PureWindowsPath(value)
    if posix.is_absolute() or windows.is_absolute() or windows.drive or value.startswith(("/", "\\")):
        raise where.fail(key, f"{_show(value)} is an absolute path; paths must be relative to the dataset folder")
    if ".." in posix.parts or ".." in windows.parts:
        raise where.fail(key, f"{_show(value)} leaves the dataset folder ('..' is not allowed)")
    return value


def file_inside(root: Path, value: str, key: str, where: Where, max_bytes: int | None = None) -> Path:
    """The regular file `root/value`, which (after following symbolic links) must lie inside `root`."""
    path = Path(root) / relative_path(value, key, where)
    try:
        resolved = path.resolve(strict=True)
        inside = resolved.is_relative_to(Path(root).resolve(strict=True))
    except FileNotFoundError:
        raise where.fail(key, f"file {path} not found") from None
    except (OSError, RuntimeError) as e:  # a symlink loop: RuntimeError before Python 3.13, OSError after
        raise where.fail(key, f"cannot read {path} ({getattr(e, 'strerror', None) or e})") from None
    if not inside:
        raise where.fail(key, f"{path} is a symbolic link to {resolved}, outside the dataset folder")
    if not resolved.is_file():
        raise where.fail(key, f"{path} is not a regular file")
    if max_bytes is not None and os.path.getsize(resolved) > max_bytes:
        raise where.fail(key, f"{path} is too large ({os.path.getsize(resolved)} bytes; the limit is {max_bytes})")
    return path


def check_picture(root: Path, value: Any, key: str, where: Where) -> str:
    """A picture inside the dataset folder: its file, size and (for PNG, read from the header) pixel count.

    The full decode happens when rendering (render.sprites.open_picture, with the same pixel limit); this
    numpy-only check catches what can be seen without decoding: empty files, decompression bombs.
    """
    path = file_inside(root, value, key, where, MAX_IMAGE_BYTES)
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError as e:
        raise where.fail(key, f"cannot read {path} ({e.strerror or e})") from None
    if not head:
        raise where.fail(key, f"{path} is an empty file, not an image")
    if head.startswith(_PNG):
        if len(head) < 24 or head[12:16] != b"IHDR":
            raise where.fail(key, f"{path} is a broken PNG file")
        width, height = struct.unpack(">II", head[16:24])
        if width * height > MAX_IMAGE_PIXELS:
            raise where.fail(key, f"{path} is {width} x {height} pixels, over the limit of {MAX_IMAGE_PIXELS} "
                                  "pixels (a decompression bomb?)")
    return value


def unit_interval(value: float, key: str, where: Where) -> float:
    if not 0.0 <= value <= 1.0:
        raise where.fail(key, f"{value} is outside [0, 1] (normalized image coordinates)")
    return value
