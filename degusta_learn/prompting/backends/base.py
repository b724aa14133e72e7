"""What a backend is: the base class that declares its capabilities, the config keys every backend
takes, and the registry that finds a backend by name.

A backend is one file: a `Backend` subclass and its config dataclass (a `BackendConfig` subclass with its
own keys), registered by name in `BACKENDS` ("module:Class", imported on first use). The class says what
the backend is, and the runner and the cost estimator ask it, never its name, without building one (so a
dry run loads no model): `per_sample` (one request per sample, or n in one), `cacheable`, `takes_schema`
(structured outputs), `key_env`, `empty_is_fault` (an empty answer is the server's fault: retried),
`is_local(cfg)` (local backends cost nothing), `local_decoding` (it runs the model and decodes itself: hf),
`default_model`, `image_tokens` and `price` (what a request costs). `make_backend(cfg, model, decoding, grid,
catalog)` builds one (`from_config`; only the hf backend uses grid + catalog, for constrained decoding). Which model
answers and how it decodes are not backend keys but the run's `model:` and `decoding:` sections
(`vlm.settings`), handed to the backend beside its own section. Backends do no retrying and no caching: the
runner does both. A failed request raises `BackendError`; `retryable=True` (rate limits, server errors,
timeouts, dropped connections) makes the runner back off and retry, `fatal=True` (bad key, unknown
model) stops the run, anything else is recorded as a failure of that episode's samples.

A `backend:` config section is read into the config class of the backend it names
(`BackendConfig.section_class`), so a key of another backend is refused in one line naming it.
API keys are read only from the environment variable named by `api_key_env` (default: the backend's
`key_env`), and `redact` scrubs them (and any echoed Authorization / api-key header value) from every
message a backend raises and from everything the prompting package writes.

Example:
    backend = make_backend(backend_config("openai"), ModelSettings(name="gpt-4o"), grid=grid, catalog=ds.catalog)
    completions = backend.complete(prompt, n=5, temperature=1.0, max_tokens=1024)
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
from dataclasses import dataclass
from typing import Any, ClassVar

from degusta_learn.errors import DegustaError
from degusta_learn.prompting import costs
from degusta_learn.task.prompt import Completion, Prompt
from degusta_learn.vlm.settings import API_MAX_NEW_TOKENS, ON_REPEAT_RENAMED, DecodingSettings, ModelSettings

BACKENDS: dict[str, str] = {
    "openai": "degusta_learn.prompting.backends.openai:OpenAIBackend",
    "anthropic": "degusta_learn.prompting.backends.anthropic:AnthropicBackend",
    "gemini": "degusta_learn.prompting.backends.gemini:GeminiBackend",
    "hf": "degusta_learn.prompting.backends.hf:HFBackend",
    "replay": "degusta_learn.prompting.backends.replay:ReplayBackend",
}
DEFAULT_BACKEND = "openai"
"""The backend of a `backend:` section without `name`."""

# The response cache keys every answer by these backend keys (cache.sample_keys). They were once the keys
# of one flat config shared by every backend: a backend without one of them keys it at that config's
# default, so caches made before the per-backend configs stay valid. adapter, constrained, dtype and
# image_size are now the `model:` / `decoding:` sections' (an API backend takes them at these values).
KEYED_DEFAULTS: dict[str, Any] = {"base_url": None, "detail": None, "adapter": None, "constrained": False,
                                  "dtype": "auto", "image_size": None, "path": None}


def backend_class(name: Any, key: str = "backend.name") -> type[Backend]:
    """The class registered as `name` (imports its module; nothing is built)."""
    if not isinstance(name, str):
        raise DegustaError(f"{key}: expected the name of a backend (one of {', '.join(BACKENDS)}), got {name!r}")
    if name not in BACKENDS:
        raise DegustaError(f"{key}: unknown backend {name!r} (known: {', '.join(BACKENDS)})")
    module, attr = BACKENDS[name].split(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except ModuleNotFoundError as e:
        if e.name and e.name.startswith("degusta_learn"):
            raise DegustaError(f"{key}: backend {name!r} is not available ({e.name} missing)") from None
        raise


def _backends_with(test) -> list[str]:
    """Names of the registered backends whose class passes `test` (an entry that fails to import is skipped)."""
    found = []
    for name in list(BACKENDS):
        try:
            if test(backend_class(name)):
                found.append(name)
        except Exception:
            continue
    return found


_MODEL_HINT = {"hf": "a model folder or a Hugging Face id"}

RENAMED_KEYS: dict[str, str] = {
    "model": "model.name", "adapter": "model.adapter", "dtype": "model.dtype", "image_size": "model.image_size",
    "max_tokens": "decoding.max_new_tokens", "constrained": "decoding.constrained", "on_repeat": "decoding.on_repeat",
    "report_unconstrained": "decoding.report_unconstrained", "stop_on_repeat": ON_REPEAT_RENAMED}
"""The keys a `backend:` section had before the model and its decoding got one spelling in every config kind."""


@dataclass
class BackendConfig:
    """The keys of a `backend:` section every backend takes; each backend's config class adds its own."""

    name: str = DEFAULT_BACKEND
    """Which backend (a name in `BACKENDS`): openai (any OpenAI-compatible server), anthropic, gemini, hf, replay."""
    structured_output: bool = False
    """Force the answer to a JSON schema (`{"objects": [...]}`; openai json_schema strict, anthropic forced
    tool, gemini response_schema). Default false: the paper's free-text answers. hf: not available (use
    `decoding.constrained`); replay: ignored (recorded answers of either kind parse)."""

    answer_keys: ClassVar[tuple[str, ...]] = ()
    """This backend's own keys that change what the model answers (they join every cache key)."""
    RENAMED: ClassVar[dict[str, str]] = RENAMED_KEYS

    def __post_init__(self):
        cls = backend_class(self.name)
        if self.structured_output and not cls.takes_schema:
            raise DegustaError(f"backend.structured_output: the {self.name} backend takes no JSON schema; it works "
                               f"with {', '.join(_backends_with(lambda c: c.takes_schema))}{cls.schema_hint}")
        if not isinstance(self, cls.config_class):
            raise DegustaError(f"backend.name: the {self.name} backend is configured by {cls.config_class.__name__}, "
                               f"not {type(self).__name__} (build it with backend_config)")

    @classmethod
    def section_class(cls, data: dict, prefix: str = "") -> type[BackendConfig]:
        """The config class of the backend a `backend:` section names (the config loader builds the section
        into it); a key that is another backend's is refused in one line naming both."""
        name = data.get("name", cls.__dataclass_fields__["name"].default)
        config = backend_class(name, key=f"{prefix}name").config_class
        if not issubclass(config, cls):
            raise DegustaError(f"{prefix}name: expected a backend configured by {cls.__name__}, got {name!r}")
        own = {f.name for f in dataclasses.fields(config) if f.init}
        for key in data:
            owners = [] if key in own else _backends_with(
                lambda c, key=key: key in {f.name for f in dataclasses.fields(c.config_class)})
            if owners:  # e.g. `--set backend.name=replay` on a config written for openai
                section = prefix.rstrip(".") or "backend"
                raise DegustaError(f"{prefix}{key}: not a key of the {name} backend but of {', '.join(owners)} "
                                   f"({name} takes: {', '.join(sorted(own))}; to switch backends, replace the "
                                   f"whole section: --set '{section}={{name: {name}, ...}}')")
        return config

    def answer_fields(self, model: ModelSettings, decoding: DecodingSettings) -> dict[str, Any]:
        """The keys that change what the model answers, as the response cache keys them: the backend's, the model's
        name and (a backend that decodes itself adds them: hf) the model and decoding keys it reads."""
        return {"name": self.name, "model": model.name, **KEYED_DEFAULTS,
                **{k: getattr(self, k) for k in self.answer_keys}}


def backend_config(name: str = DEFAULT_BACKEND, **keys) -> BackendConfig:
    """The config of backend `name` with `keys` (its `backend:` section only: the model is a `ModelSettings`),
    checked as a `backend:` section of a config file is."""
    from degusta_learn.config import from_dict

    return from_dict(BackendConfig, {"name": name, **keys}, prefix="backend.")


class Backend:
    """A VLM that turns a `Prompt` into n sampled completions, and what it is (class attributes that the
    runner and the cost estimator read without building one). A subclass declares each of them."""

    name: ClassVar[str] = ""
    """The name it is registered under (`BACKENDS`) and written in configs, ledgers and diagnostics."""
    config_class: ClassVar[type[BackendConfig]] = BackendConfig
    """Its `backend:` section: a BackendConfig subclass whose `name` defaults to this backend's."""
    default_model: ClassVar[str] = ""
    """`model.name` when a config leaves it empty (openai: gpt-4o, the paper's; "": a model must be named)."""
    local_decoding: ClassVar[bool] = False
    """True: the model runs here and the backend decodes itself (hf), so the `model:` keys adapter / dtype /
    image_size and the `decoding:` keys constrained / on_repeat / report_unconstrained apply (`constrained` null is
    true); False: a service or a file answers, those keys stay at their defaults (`vlm.settings.check_api_settings`)
    and `decoding.max_new_tokens: auto` is `vlm.settings.API_MAX_NEW_TOKENS`."""
    per_sample: ClassVar[bool] = False
    """True: one request per sample (an API without `n`), so the runner asks for one answer at a time and
    caches each at once; False: n samples in one request (fewer returned are asked for again)."""
    cacheable: ClassVar[bool] = True
    """False: its answers are not kept in the response cache (replay: the file is the cache)."""
    takes_schema: ClassVar[bool] = False
    """True: `structured_output: true` is accepted (sent as a JSON schema, or ignored)."""
    schema_hint: ClassVar[str] = ""
    """Appended to the error refusing `structured_output: true` (what to use instead)."""
    key_env: ClassVar[str | None] = None
    """The environment variable its API key is read from when `api_key_env` is unset (None: no key)."""
    empty_is_fault: ClassVar[bool] = False
    """True (the backends that call a server): a reply without an answer -- no choices / content / candidates, a
    null message, empty or blank text -- is a server fault, retried with the backoff and, retries exhausted, an
    unanswered episode (never a failed sample); False: an empty answer is the model's (a local model, a recorded
    file), a counted failure."""

    @classmethod
    def is_local(cls, cfg: BackendConfig) -> bool:
        """True: requests stay on this machine (a local model or server) and cost nothing unless the
        config's `prices` names the model; False: a paid service, priced from `costs.DEFAULT_PRICES`."""
        return False

    @classmethod
    def image_tokens(cls, width: int, height: int, cfg: BackendConfig, model: ModelSettings) -> int:
        """Input tokens one image of a prompt costs (the provider's rule; an estimate for local models)."""
        return costs.tile_image_tokens(width, height)

    @classmethod
    def input_tokens(cls, prompt: Prompt, cfg: BackendConfig, model: ModelSettings) -> int:
        """Estimated input tokens of one request carrying `prompt`."""
        return costs.prompt_tokens(prompt, lambda w, h: cls.image_tokens(w, h, cfg, model))

    @classmethod
    def check_run(cls, cfg: BackendConfig, model: ModelSettings, ds, episodes: list, render_size: int) -> None:
        """Refuse, before anything is built or loaded, a run this backend must not serve (one line): no model
        named; the hf backend also refuses episodes of participants its fine-tuned model was trained or validated
        on, and images rendered at another `render_size` than in training."""
        if not isinstance(model.name, str) or not model.name.strip():
            raise DegustaError(f"model.name: required for the {cfg.name} backend "
                               f"({_MODEL_HINT.get(cfg.name, 'the model name at the service')})")

    @classmethod
    def price(cls, cfg: BackendConfig, model: ModelSettings, prices: dict[str, Any]) -> tuple[float, float] | None:
        """USD per 1M (input, output) tokens of a request (None: free or unknown); `prices` overrides the table."""
        if cls.is_local(cfg) and model.name not in prices:
            return None
        return costs.price(model.name, prices)

    @classmethod
    def from_config(cls, cfg: BackendConfig, model: ModelSettings, decoding: DecodingSettings, grid=None,
                    catalog=None) -> Backend:
        """Build the backend (clients, keys, a local model) from its section, the model and its decoding."""
        raise NotImplementedError

    def token_budget(self, ds, method: str) -> dict:
        """`decoding.max_new_tokens: auto` for this backend: {"max_new_tokens": ...} (an API backend's is
        `vlm.settings.API_MAX_NEW_TOKENS`; hf sizes it from `ds` with its tokenizer)."""
        return {"max_new_tokens": API_MAX_NEW_TOKENS}

    def complete(self, prompt: Prompt, n: int, temperature: float, max_tokens: int,
                 seed: int | None = None) -> list[Completion]:
        """Return up to n completions of `prompt` (fewer only if the service gave fewer)."""
        raise NotImplementedError


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
    """Text with every API key removed: the values of the key variables in use (and of every registered
    backend's `key_env`), any `Authorization` / `api-key` / `x-api-key` / `x-goog-api-key` header value,
    credentials in a URL (`https://user:password@host`, `?key=...`, `&token=...`), and sk-... / AIza...
    tokens. The one function every write point of the prompting package passes text through (cache,
    ledger, predictions diagnostics, error messages); non-text values are returned unchanged."""
    if not isinstance(text, str) or not text:
        return text
    for env in {*_default_key_envs(), *_extra_key_envs}:
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
_default_envs: tuple[tuple, frozenset[str]] = ((), frozenset())  # (the registry it was read from, its key_envs)


def _default_key_envs() -> frozenset[str]:
    """The `key_env` of every registered backend: their values are scrubbed even where they are not in use."""
    global _default_envs
    entries = tuple(BACKENDS.items())
    if _default_envs[0] != entries:
        _default_envs = (entries, frozenset(backend_class(n).key_env for n in _backends_with(lambda c: c.key_env)))
    return _default_envs[1]


def api_key(env: str, required: bool = True) -> str | None:
    """The API key in the environment variable `env` (never from a config file)."""
    _extra_key_envs.add(env)
    value = os.environ.get(env)
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
        from degusta_learn.task.answer_format import answer_schema
        from degusta_learn.task.answers import answer_kind

        if self.catalog is None:
            raise DegustaError("backend.structured_output: the answer schema needs the dataset catalog "
                               "(build the backend with make_backend(cfg, grid, catalog))")
        kind = answer_kind(prompt.method)
        if kind not in self._schemas:
            self._schemas[kind] = answer_schema(kind, self.catalog, self.grid)
        return self._schemas[kind]


def make_backend(cfg: BackendConfig, model: ModelSettings, decoding: DecodingSettings | None = None, grid=None,
                 catalog=None) -> Backend:
    """Build the backend `cfg` names (imports its module on first use) serving `model`, decoding as `decoding` says
    (None: the defaults, `constrained` null decided for the backend)."""
    cls = backend_class(cfg.name)
    decoding = (decoding or DecodingSettings()).resolved(local=cls.local_decoding)
    return cls.from_config(cfg, model, decoding, grid, catalog)
