"""A persistent response cache (SQLite), so an interrupted zero-shot run resumes without paying twice.

Each sampled answer is stored under a key hashing everything that determines it: the backend, model and
decoding settings that change answers (name, model.name, base_url, image detail, model.adapter,
decoding.constrained, ...), the prompt (text parts in order
and the SHA-256 of every encoded image), the sampling parameters (temperature, max_tokens, seed), the
JSON schema of a structured-output run (`backend.structured_output`) and the sample index; a local model or adapter folder also contributes a fingerprint of its files, so a
retrained adapter at the same path does not hit stale answers. The answers of one request are committed
(one transaction, synchronous=FULL) the moment the response is received, before anything parses them,
so a killed run loses at most the requests in flight. The cache holds answer texts and token counts
only: no prompts, no images, no keys (every text passes through `backends.base.redact` on its way in).

The file is made by this tool only: a new cache is built under a temporary name and linked into place
(never half-made), is marked with `APPLICATION_ID`, and an existing path that is not such a cache (a
user's file, another program's database, a folder) is refused, never overwritten.

Example:
    cache = ResponseCache("runs/x/responses_cache.sqlite")
    keys = sample_keys(prompt, backend_cfg, model, decoding, temperature=1.0, max_tokens=1024, seed=0, n=5)
    hits = cache.get_many(keys)            # {key: Completion}
    cache.put(keys[3], completion, episode="p001/t2/k4")
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import threading
import time
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import BackendConfig, Completion, redact
from degusta_learn.task.prompt import ImagePart, Prompt
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings

APPLICATION_ID = 0x44475343  # "DGSC": PRAGMA application_id of a degusta response cache
_SCHEMA = ("CREATE TABLE IF NOT EXISTS responses (key TEXT PRIMARY KEY, episode TEXT, text TEXT NOT NULL, "
           "input_tokens INTEGER, output_tokens INTEGER, created REAL)")
_COLUMNS = ["key", "episode", "text", "input_tokens", "output_tokens", "created"]
_SQLITE_MAGIC = b"SQLite format 3\x00"


def prompt_digest(prompt: Prompt) -> str:
    """SHA-256 over the prompt's parts in order: text as text, images as their name + bytes hash."""
    h = hashlib.sha256()
    for part in prompt.parts:
        if isinstance(part, ImagePart):
            h.update(f"\0image\0{part.name}\0{part.format}\0{part.sha256()}".encode())
        else:
            h.update(b"\0text\0" + part.encode("utf-8"))
    return h.hexdigest()


def folder_fingerprint(name: str | None) -> str | None:
    """A hash of a local model/adapter folder's file names, sizes and mtimes (retraining changes it); a shipped
    model's name counts as its folder; a hub id (None here) is keyed by the id itself."""
    from degusta_learn.vlm.hub import local_folder

    path = local_folder(name)
    if path is None:
        return None
    h = hashlib.sha256()
    for f in sorted(Path(path).rglob("*")):
        if f.is_file():
            st = f.stat()
            h.update(f"{f.relative_to(path)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def sample_keys(prompt: Prompt, backend: BackendConfig, model: ModelSettings, decoding: DecodingSettings,
                temperature: float, max_tokens: int, seed: int | None, n: int, schema: dict | None = None) -> list[str]:
    """One cache key per sample index 0..n-1 (growing n keeps the first answers).

    `schema`: the JSON schema a structured-output request sends (`backend.structured_output`); its
    SHA-256 joins the key, so free-text and structured answers never mix and a changed schema (catalog,
    grid) asks again. Free-text keys are what they always were (caches made before stay valid).
    """
    # the backend, model and decoding keys that change answers (timeout, api_key_env, device do not), as they were
    # keyed when they were all backend keys: the same settings key the same answers
    fields = backend.answer_fields(model, decoding)
    base = {"backend": fields, "prompt": prompt_digest(prompt),
            "temperature": temperature, "max_tokens": max_tokens, "seed": seed,
            "model_files": folder_fingerprint(model.name), "adapter_files": folder_fingerprint(fields["adapter"])}
    if schema is not None:
        base["structured_output"] = hashlib.sha256(json.dumps(schema, sort_keys=True).encode()).hexdigest()
    head = json.dumps(base, sort_keys=True)
    return [hashlib.sha256(f"{head}\0sample={i}".encode()).hexdigest() for i in range(n)]


def _refuse(path: Path, why: str) -> DegustaError:
    return DegustaError(f"cache: {path} {why}; it is not a response cache made by degusta, so it is left "
                        "untouched: point `cache` at a new file (or `cache: off`)")


def _check_existing(path: Path) -> None:
    """Refuse an existing path that is not a degusta response cache (checked before SQLite opens it)."""
    if path.is_dir():
        raise _refuse(path, "is a folder")
    if not path.is_file():
        raise _refuse(path, "is not a regular file")
    try:
        with open(path, "rb") as f:
            head = f.read(100)
    except OSError as e:
        raise DegustaError(f"cache: cannot read {path} ({e.strerror or e})") from None
    if len(head) < 100 or not head.startswith(_SQLITE_MAGIC):
        raise _refuse(path, f"exists and is not an SQLite database ({path.stat().st_size} bytes)")


def _check_schema(db: sqlite3.Connection, path: Path) -> None:
    app_id = db.execute("PRAGMA application_id").fetchone()[0]
    tables = {name for (name,) in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    columns = [r[1] for r in db.execute("PRAGMA table_info(responses)")] if "responses" in tables else []
    # a cache made before the application_id mark: exactly our one table with our columns
    ours = app_id == APPLICATION_ID or (app_id == 0 and tables == {"responses"})
    if not ours or columns != _COLUMNS:
        raise _refuse(path, "is an SQLite database of something else")


def _create(path: Path) -> None:
    """Make an empty cache at `path` atomically (build under a temporary name, then link; never overwrite)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        db = sqlite3.connect(tmp, isolation_level=None)
        try:
            db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(_SCHEMA)
        finally:
            db.close()
        try:
            os.link(tmp, path)  # fails if something appeared at `path` meanwhile: never replaces it
        except FileExistsError:
            pass
        except OSError:  # a filesystem without hard links
            if not path.exists():
                os.replace(tmp, path)
    finally:
        for leftover in (tmp, tmp.with_name(tmp.name + "-wal"), tmp.with_name(tmp.name + "-shm")):
            leftover.unlink(missing_ok=True)


class ResponseCache:
    """Thread-safe SQLite store of completions; `readonly=True` never creates or writes the file."""

    def __init__(self, path: str | Path, readonly: bool = False):
        self.path = Path(path)
        self.readonly = readonly
        self._lock = threading.Lock()
        self._db: sqlite3.Connection | None = None
        if readonly and not self.path.exists() and not self.path.is_symlink():
            return
        try:
            if not readonly and not self.path.exists() and not self.path.is_symlink():
                _create(self.path)
            _check_existing(self.path)
            if readonly:
                self._db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False)
            else:
                self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            _check_schema(self._db, self.path)
            if not readonly:
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("SELECT count(*) FROM responses").fetchone()
        except DegustaError:
            self.close()
            raise
        except (sqlite3.Error, OSError) as e:
            self.close()
            raise DegustaError(f"cache: {self.path} is not a usable response cache ({e}); "
                               "point `cache` elsewhere or delete the file") from None

    def get_many(self, keys: list[str]) -> dict[str, Completion]:
        if self._db is None or not keys:
            return {}
        marks = ",".join("?" * len(keys))
        with self._lock:
            if self._db is None:  # closed meanwhile (a run interrupted while a worker was still answering)
                return {}
            rows = self._db.execute(f"SELECT key, text, input_tokens, output_tokens FROM responses "
                                    f"WHERE key IN ({marks})", keys).fetchall()
        return {k: Completion(text=t if isinstance(t, str) else str(t), input_tokens=stored_count(i), output_tokens=stored_count(o))
                for k, t, i, o in rows}

    def put(self, key: str, completion: Completion, episode: str | None = None) -> None:
        self.put_many([(key, completion)], episode)

    def put_many(self, items: list[tuple[str, Completion]], episode: str | None = None) -> None:
        """Store completions in one committed transaction (texts redacted of any API key first)."""
        if self._db is None or self.readonly or not items:
            return
        now = time.time()
        rows = [(key, episode, redact(stored_text(c.text)), stored_count(c.input_tokens), stored_count(c.output_tokens), now) for key, c in items]
        with self._lock:
            if self._db is None:  # closed by an interrupted run: a request still in flight then is not kept
                return
            try:
                self._db.execute("BEGIN IMMEDIATE")
                self._db.executemany("INSERT OR REPLACE INTO responses VALUES (?, ?, ?, ?, ?, ?)", rows)
                self._db.execute("COMMIT")
            except sqlite3.Error as e:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                raise DegustaError(f"cache: cannot write to {self.path} ({e})") from None

    def __len__(self) -> int:
        if self._db is None:
            return 0
        with self._lock:
            return self._db.execute("SELECT count(*) FROM responses").fetchone()[0]

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None


def stored_text(v) -> str:
    """Answer text as stored: a str that is valid UTF-8 (lone surrogates from a JSON escape become '?')."""
    if not isinstance(v, str):
        v = "" if v is None else str(v)
    try:
        v.encode("utf-8")
        return v
    except UnicodeEncodeError:
        return v.encode("utf-8", "replace").decode("utf-8")


def stored_count(v) -> int | None:
    """A token count as stored: a non-negative int below 2**62, else None (unknown)."""
    return v if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2 ** 62 else None
