"""The backend protocol: a VLM that turns a `Prompt` into n sampled completions.

Backends are small classes, one file each, registered by name in `BACKENDS` ("module:Class") and built
with `make_backend(cfg, grid, catalog)` (each class has `from_config(cfg, grid, catalog)`; only the hf
backend uses grid + catalog, for constrained decoding). They do no retrying and no caching: the runner
does both. A failed request raises `BackendError`; `retryable=True` (rate limits, server errors,
timeouts, dropped connections) makes the runner back off and retry, `fatal=True` (bad key, unknown
model) stops the run, anything else is recorded as a failure of that episode's samples.

API keys are read only from the environment variable named by `api_key_env`, and `redact` scrubs them
(and any echoed Authorization / api-key header value) from every message a backend raises and from
everything the prompting package writes.

Example:
    backend = make_backend(BackendConfig(name="openai", model="gpt-4o"), grid, ds.catalog)
    completions = backend.complete(prompt, n=5, temperature=1.0, max_tokens=1024)
"""

from __future__ import annotations

import importlib
import os
import re
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.prompt import Completion, Prompt

BACKENDS: dict[str, str] = {
    "openai": "degusta_learn.prompting.backends.openai:OpenAIBackend",
    "anthropic": "degusta_learn.prompting.backends.anthropic:AnthropicBackend",
    "gemini": "degusta_learn.prompting.backends.gemini:GeminiBackend",
    "hf": "degusta_learn.prompting.backends.hf:HFBackend",
    "replay": "degusta_learn.prompting.backends.replay:ReplayBackend",
}
STRUCTURED_BACKENDS = ("openai", "anthropic", "gemini", "replay")
"""Backends that take `structured_output: true` (replay ignores it: recorded answers of both kinds parse)."""
DEFAULT_KEY_ENV = {"openai": "OPENAI_API_KEY", "anthropic": "ANTHROPIC_API_KEY", "gemini": "GEMINI_API_KEY"}


@runtime_checkable
class Backend(Protocol):
    name: str
    model: str

    def complete(self, prompt: Prompt, n: int, temperature: float, max_tokens: int,
                 seed: int | None = None) -> list[Completion]:
        """Return up to n completions of `prompt` (fewer only if the service gave fewer)."""
        ...


@dataclass
class BackendConfig:
    """The `backend:` section of a zero-shot predict config."""

    name: str = "openai"
    """Which backend: openai (any OpenAI-compatible server), anthropic, gemini, hf (local), replay."""
    model: str = "gpt-4o"
    """Model name at the service (or a hub id / folder for hf)."""
    base_url: str | None = None
    """OpenAI-compatible endpoint, e.g. http://127.0.0.1:8000/v1 for vLLM, :11434/v1 for Ollama."""
    api_key_env: str | None = None
    """Environment variable holding the API key (default OPENAI_API_KEY / ANTHROPIC_API_KEY / GEMINI_API_KEY)."""
    max_tokens: int = 1024
    """Most tokens per sampled answer."""
    timeout: float = 120.0
    """Seconds before a request counts as timed out (then retried)."""
    detail: str | None = None
    """openai only: image detail "low" (85 tokens an image), "high" or "auto" (unset: the server default)."""
    adapter: str | None = None
    """hf only: a peft LoRA adapter folder (from `degusta train`)."""
    constrained: bool = False
    """hf only: constrain decoding to the answer grammar."""
    device: str = "auto"
    """hf only: cpu, cuda, auto."""
    dtype: str = "auto"
    """hf only: float32, bfloat16, float16, auto."""
    image_size: int | None = None
    """hf only: the processor's image size budget (unset: the model's default)."""
    path: str | None = None
    """replay only: the JSONL file of recorded answers."""
    structured_output: bool = False
    """Force the answer to a JSON schema (`{"objects": [...]}`; openai json_schema strict, anthropic forced
    tool, gemini response_schema). Default false: the paper's free-text answers. hf: not available (use
    `constrained`); replay: ignored (recorded answers of either kind parse)."""

    def __post_init__(self):
        if self.name not in BACKENDS:
            raise DegustaError(f"backend.name: unknown backend {self.name!r} (known: {', '.join(BACKENDS)})")
        if self.max_tokens < 1:
            raise DegustaError(f"backend.max_tokens: expected >= 1, got {self.max_tokens}")
        if self.timeout <= 0:
            raise DegustaError(f"backend.timeout: expected > 0, got {self.timeout}")
        if self.detail not in (None, "low", "high", "auto"):
            raise DegustaError(f"backend.detail: expected low, high or auto, got {self.detail!r}")
        if self.structured_output and self.name not in STRUCTURED_BACKENDS:
            hint = (" (the hf backend constrains decoding itself: set backend.constrained: true)"
                    if self.name == "hf" else "")
            raise DegustaError(f"backend.structured_output: the {self.name} backend takes no JSON schema; "
                               f"it works with {', '.join(STRUCTURED_BACKENDS)}{hint}")

    @property
    def key_env(self) -> str | None:
        """The environment variable the key is read from (None: this backend needs no key)."""
        return self.api_key_env or DEFAULT_KEY_ENV.get(self.name)


class BackendError(Exception):
    """A request that failed; see the module docstring for what `retryable` and `fatal` mean."""

    def __init__(self, message: str, retryable: bool = False, retry_after: float | None = None,
                 fatal: bool = False, status: int | None = None):
        super().__init__(redact(message))
        self.retryable, self.retry_after, self.fatal, self.status = retryable, retry_after, fatal, status


_KEY_PATTERN = re.compile(r"\b(sk-[A-Za-z0-9_\-*]{4,}|AIza[A-Za-z0-9_\-]{10,})")
# The value of an auth header wherever it appears: `Authorization: Bearer X`, `"api-key": "X"`,
# `x-api-key=X`, `'X-Goog-Api-Key': 'X'` (HTTP dumps, JSON, Python reprs, query strings).
_HEADER_PATTERN = re.compile(
    r"""(?i)((?:proxy-)?authorization|x-api-key|x-goog-api-key|api[-_]?key|access[-_]token)"""
    r"""(["']?\s*[:=]\s*["']?)((?:bearer|basic|token)\s+)?([^\s"',;&}\])]+)""")
# Credentials inside a URL: `scheme://user:password@host` and secret query parameters (`?key=...&token=...`).
_URL_USERINFO = re.compile(r"(?i)\b([a-z][a-z0-9+.\-]*://)[^/\s@'\"]+@")
_QUERY_SECRET = re.compile(r"(?i)([?&](?:key|token|secret|password|passwd|sig|signature|auth)=)([^&#\s\"']+)")
REDACTED = "***"


def redact(text):
    """Text with every API key removed: the values of the key variables in use (and the known defaults),
    any `Authorization` / `api-key` / `x-api-key` / `x-goog-api-key` header value, credentials in a URL
    (`https://user:password@host`, `?key=...`, `&token=...`), and sk-... / AIza... tokens. The one function every write point of the prompting package passes text through (cache,
    ledger, predictions diagnostics, error messages); non-text values are returned unchanged."""
    if not isinstance(text, str) or not text:
        return text
    for env in {*DEFAULT_KEY_ENV.values(), *_extra_key_envs}:
        value = os.environ.get(env)
        if value and len(value) >= 4 and value in text:
            text = text.replace(value, REDACTED)
    text = _HEADER_PATTERN.sub(lambda m: m.group(1) + m.group(2) + (m.group(3) or "") + REDACTED, text)
    text = _URL_USERINFO.sub(lambda m: m.group(1) + REDACTED + "@", text)
    text = _QUERY_SECRET.sub(lambda m: m.group(1) + REDACTED, text)
    return _KEY_PATTERN.sub(REDACTED, text)


def redact_json(value):
    """`redact` applied to every string (keys and values) of a JSON-like value."""
    if isinstance(value, str):
        return redact(value)
    if isinstance(value, dict):
        return {redact(k) if isinstance(k, str) else k: redact_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [redact_json(v) for v in value]
    return value


_extra_key_envs: set[str] = set()


def api_key(cfg: BackendConfig, required: bool = True) -> str | None:
    """The API key from the environment variable `cfg.key_env` (never from a config file)."""
    env = cfg.key_env
    if env:
        _extra_key_envs.add(env)
    value = os.environ.get(env) if env else None
    if not value and required:
        raise DegustaError(f"backend.api_key_env: environment variable {env} is not set "
                           f"(export {env}=... ; keys are never read from config files)")
    return value or None


class AnswerSchemas:
    """The JSON schema of a prompt's answer (`answers.answer_schema`), built once per answer kind: what a
    structured-output backend sends with every request (the runner builds the same one for cache keys)."""

    def __init__(self, grid=None, catalog=None):
        self.grid, self.catalog, self._schemas = grid, catalog, {}

    def __call__(self, prompt: Prompt) -> dict:
        from degusta_learn.prompting.answers import answer_kind, answer_schema

        if self.catalog is None:
            raise DegustaError("backend.structured_output: the answer schema needs the dataset catalog "
                               "(build the backend with make_backend(cfg, grid, catalog))")
        kind = answer_kind(prompt.method)
        if kind not in self._schemas:
            self._schemas[kind] = answer_schema(kind, self.catalog, self.grid)
        return self._schemas[kind]


def make_backend(cfg: BackendConfig, grid=None, catalog=None) -> Backend:
    """Build the backend named by `cfg.name` (imports its module on first use)."""
    if cfg.name not in BACKENDS:
        raise DegustaError(f"backend.name: unknown backend {cfg.name!r} (known: {', '.join(BACKENDS)})")
    module, attr = BACKENDS[cfg.name].split(":")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except ModuleNotFoundError as e:
        if e.name and e.name.startswith("degusta_learn"):
            raise DegustaError(f"backend.name: backend {cfg.name!r} is not available ({e.name} missing)") from None
        raise
    return cls.from_config(cfg, grid, catalog)
