"""A persistent response cache (SQLite), so an interrupted zero-shot run resumes without paying twice.

Each sampled answer is stored under a key hashing everything that determines it: the backend settings
that change answers (name, model, base_url, image detail, adapter, ...), the prompt (text parts in order
and the SHA-256 of every encoded image), the sampling parameters (temperature, max_tokens, seed) and the
sample index; a local model or adapter folder also contributes a fingerprint of its files, so a
retrained adapter at the same path does not hit stale answers. Answers are committed one by one as they arrive, so a killed run loses at most the
requests in flight. The cache holds answer texts and token counts only: no prompts, no images, no keys.

Example:
    cache = ResponseCache("runs/x/responses_cache.sqlite")
    keys = sample_keys(prompt, backend_cfg, temperature=1.0, max_tokens=1024, seed=0, n=5)
    hits = cache.get_many(keys)            # {key: Completion}
    cache.put(keys[3], completion, episode="p001/t2/k4")
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import threading
import time
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import BackendConfig, Completion
from degusta_learn.prompting.prompt import ImagePart, Prompt

# BackendConfig fields that change what the model answers (timeout, api_key_env, device do not).
ANSWER_FIELDS = ("name", "model", "base_url", "detail", "adapter", "constrained", "dtype", "image_size", "path")


def prompt_digest(prompt: Prompt) -> str:
    """SHA-256 over the prompt's parts in order: text as text, images as their name + bytes hash."""
    h = hashlib.sha256()
    for part in prompt.parts:
        if isinstance(part, ImagePart):
            h.update(f"\0image\0{part.name}\0{part.format}\0{part.sha256()}".encode())
        else:
            h.update(b"\0text\0" + part.encode("utf-8"))
    return h.hexdigest()


def folder_fingerprint(path: str | None) -> str | None:
    """A hash of a local model/adapter folder's file names, sizes and mtimes (retraining changes it)."""
    if not path or not Path(path).is_dir():
        return None
    h = hashlib.sha256()
    for f in sorted(Path(path).rglob("*")):
        if f.is_file():
            st = f.stat()
            h.update(f"{f.relative_to(path)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def sample_keys(prompt: Prompt, backend: BackendConfig, temperature: float, max_tokens: int,
                seed: int | None, n: int) -> list[str]:
    """One cache key per sample index 0..n-1 (growing n keeps the first answers)."""
    base = {"backend": {f: getattr(backend, f) for f in ANSWER_FIELDS}, "prompt": prompt_digest(prompt),
            "temperature": temperature, "max_tokens": max_tokens, "seed": seed,
            "model_files": folder_fingerprint(backend.model), "adapter_files": folder_fingerprint(backend.adapter)}
    head = json.dumps(base, sort_keys=True)
    return [hashlib.sha256(f"{head}\0sample={i}".encode()).hexdigest() for i in range(n)]


class ResponseCache:
    """Thread-safe SQLite store of completions; `readonly=True` never creates or writes the file."""

    def __init__(self, path: str | Path, readonly: bool = False):
        self.path = Path(path)
        self.readonly = readonly
        self._lock = threading.Lock()
        self._db: sqlite3.Connection | None = None
        if readonly and not self.path.exists():
            return
        try:
            if readonly:
                self._db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False)
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("CREATE TABLE IF NOT EXISTS responses (key TEXT PRIMARY KEY, episode TEXT, "
                                 "text TEXT NOT NULL, input_tokens INTEGER, output_tokens INTEGER, created REAL)")
            self._db.execute("SELECT count(*) FROM responses").fetchone()
        except sqlite3.DatabaseError as e:
            raise DegustaError(f"cache: {self.path} is not a usable response cache ({e}); "
                               "point `cache` elsewhere or delete the file") from None

    def get_many(self, keys: list[str]) -> dict[str, Completion]:
        if self._db is None or not keys:
            return {}
        marks = ",".join("?" * len(keys))
        with self._lock:
            rows = self._db.execute(f"SELECT key, text, input_tokens, output_tokens FROM responses "
                                    f"WHERE key IN ({marks})", keys).fetchall()
        return {k: Completion(text=t, input_tokens=i, output_tokens=o) for k, t, i, o in rows}

    def put(self, key: str, completion: Completion, episode: str | None = None) -> None:
        if self._db is None or self.readonly:
            return
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO responses VALUES (?, ?, ?, ?, ?, ?)",
                             (key, episode, completion.text, completion.input_tokens, completion.output_tokens,
                              time.time()))

    def __len__(self) -> int:
        if self._db is None:
            return 0
        with self._lock:
            return self._db.execute("SELECT count(*) FROM responses").fetchone()[0]

    def close(self) -> None:
        if self._db is not None:
            with self._lock:
                self._db.close()
            self._db = None
