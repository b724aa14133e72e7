"""Identify files by their bytes (`file_sha256`) or cheaply by size and time (`stat_tree`).

The dataset fingerprint (`scene.dataset.dataset_identity`) and compare's staleness records are built from them.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


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
