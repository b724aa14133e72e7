"""Any OpenAI-compatible chat-completions endpoint via the official `openai` client.

GPT-4o by default; with `base_url` also vLLM (`vllm serve Qwen/Qwen2.5-VL-7B-Instruct`), Ollama
(http://127.0.0.1:11434/v1) or LM Studio, so open models served locally work the same way. The prompt
goes as one user message whose content interleaves text parts and images (base64 data URLs); the n
samples are asked for in one request (`n`), and a server that returns fewer choices (Ollama ignores
`n`) is asked again by the runner for the rest.

The key comes from the environment variable `api_key_env` (default OPENAI_API_KEY, which is sent to
api.openai.com only). Any other `base_url` gets a key only when `api_key_env` names its variable, so a
local server runs without one and your OpenAI key never reaches a third-party endpoint.

With `structured_output: true` every request carries the answer's JSON schema as
`response_format={"type": "json_schema", "json_schema": {"name": "degusta_answer", "strict": true,
"schema": ...}}` (OpenAI Structured Outputs; vLLM, SGLang and Ollama take the same field). A server that
ignores it and answers free text is parsed as usual; one that refuses it (HTTP 400 naming the schema)
stops the run with one line naming `backend.structured_output`.

What it is: n samples in one request; a paid service (priced by model name), except a server on this
machine (loopback `base_url`), which costs nothing unless `prices` names the model; images counted by
OpenAI's tile rule (`costs.tile_image_tokens`, at the configured `detail`).

Example:
    backend = OpenAIBackend.from_config(OpenAIConfig(), ModelSettings(name="gpt-4o"), DecodingSettings())
    backend.complete(prompt, n=5, temperature=1.0, max_tokens=1024)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Literal
from urllib.parse import urlparse

from degusta_learn.config import check_choices
from degusta_learn.prompting import costs
from degusta_learn.prompting.backends.base import AnswerSchemas, BackendError, Completion, api_key
from degusta_learn.prompting.backends.remote import RemoteBackend, RemoteConfig, retry_after
from degusta_learn.prompting.backends.transport import fault_reason, guarded_client
from degusta_learn.task.answers import STRUCTURED_NAME
from degusta_learn.task.prompt import ImagePart, Prompt
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings


@dataclass
class OpenAIConfig(RemoteConfig):
    """The `backend:` keys of the openai backend (GPT-4o or any OpenAI-compatible server)."""

    name: str = "openai"
    detail: Literal["low", "high", "auto"] | None = None
    """Image detail "low" (85 tokens an image), "high" or "auto" (unset: the server default)."""

    answer_keys = ("base_url", "detail")

    def __post_init__(self):
        super().__post_init__()
        check_choices(self, "backend")


def split_usage(total: int | None, k: int) -> list[int | None]:
    """Spread a request's token count over its k samples (sums to the total)."""
    if total is None or k == 0:
        return [None] * k
    return [total // k + (1 if i < total % k else 0) for i in range(k)]


class OpenAIBackend(RemoteBackend):
    """Chat completions with images as data URLs; `n` samples per request."""

    name = "openai"
    config_class = OpenAIConfig
    per_sample = False  # `n` answers in one request
    cacheable = True
    takes_schema = True  # response_format json_schema
    key_env = "OPENAI_API_KEY"
    default_model = "gpt-4o"  # the paper's

    @classmethod
    def image_tokens(cls, width: int, height: int, cfg: OpenAIConfig, model: ModelSettings | None = None) -> int:
        return costs.tile_image_tokens(width, height, cfg.detail)

    def __init__(self, model: str, client, detail: str | None = None, schemas: AnswerSchemas | None = None):
        self.model, self.client, self.detail = model, client, detail
        self.schemas = schemas  # set: structured outputs (response_format json_schema, strict)
        self.max_tokens_key = "max_tokens"

    @classmethod
    def from_config(cls, cfg: OpenAIConfig, model: ModelSettings, decoding: DecodingSettings | None = None,
                    grid=None, catalog=None) -> OpenAIBackend:
        import openai

        # The default OPENAI_API_KEY is only ever sent to OpenAI itself; another server (vLLM, Ollama, a
        # proxy) gets a key only from a variable named explicitly in backend.api_key_env.
        official = cfg.base_url is None or (urlparse(cfg.base_url).hostname or "").endswith("api.openai.com")
        key = (api_key(cfg.api_key_env or cls.key_env) if cfg.api_key_env or official else None) or "not-needed"
        client = openai.OpenAI(api_key=key, base_url=cfg.base_url, timeout=cfg.timeout, max_retries=0,
                               http_client=guarded_client(cfg.timeout, openai))  # a deadline, bounded replies
        return cls(model.name, client, cfg.detail,
                   AnswerSchemas(grid, catalog) if cfg.structured_output else None)

    def messages(self, prompt: Prompt) -> list[dict]:
        content = []
        for part in prompt.parts:
            if isinstance(part, ImagePart):
                image = {"url": part.data_url()}
                if self.detail:
                    image["detail"] = self.detail
                content.append({"type": "image_url", "image_url": image})
            else:
                content.append({"type": "text", "text": part})
        return [{"role": "user", "content": content}]

    def complete(self, prompt: Prompt, n: int, temperature: float, max_tokens: int,
                 seed: int | None = None) -> list[Completion]:
        import openai

        kwargs = {"model": self.model, "messages": self.messages(prompt), "n": n, "temperature": temperature,
                  self.max_tokens_key: max_tokens}
        if seed is not None:
            kwargs["seed"] = seed
        if self.schemas is not None:
            kwargs["response_format"] = response_format(self.schemas(prompt))
        try:
            try:
                resp = self.client.chat.completions.create(**kwargs)
            except openai.BadRequestError as e:  # newer OpenAI models only take max_completion_tokens
                if self.max_tokens_key != "max_tokens" or "max_completion_tokens" not in str(e):
                    raise
                self.max_tokens_key = "max_completion_tokens"
                kwargs["max_completion_tokens"] = kwargs.pop("max_tokens")
                resp = self.client.chat.completions.create(**kwargs)
        except openai.APIStatusError as e:
            status = e.status_code
            msg = f"openai: HTTP {status} from {self.model}: {_message(e)}"
            if status in (401, 403):
                raise BackendError(msg + " (check the API key variable)", fatal=True, status=status) from None
            if status == 404:
                raise BackendError(msg + " (unknown model or endpoint?)", fatal=True, status=status) from None
            if status in (400, 422) and self.schemas is not None and _about_schema(msg):
                raise BackendError(f"backend.structured_output: the server refused the JSON schema ({msg}); "
                                   "enable structured outputs on the server (docs/prompting.md) or set "
                                   "backend.structured_output=false", fatal=True, status=status) from None
            raise BackendError(msg, retryable=status in (408, 409, 429) or status >= 500,
                               retry_after=retry_after(e.response.headers), status=status) from None
        except openai.APITimeoutError as e:
            why = fault_reason(e)
            raise BackendError(f"openai: request to {self.model} timed out" + (f" ({why})" if why else ""),
                               retryable=True) from None
        except openai.APIConnectionError as e:
            why = fault_reason(e)  # a reply refused for its size or encoding (transport.py)
            raise BackendError(f"openai: {self.model}: {why}" if why else
                               f"openai: cannot reach the server ({_message(e)})", retryable=True) from None
        except openai.OpenAIError as e:
            raise BackendError(f"openai: {_message(e)}") from None
        except ValueError as e:  # a 200 whose JSON body is malformed (JSONDecodeError, pydantic errors)
            raise BackendError(f"openai: {self.model} answered with a malformed body ({type(e).__name__}); "
                               "retrying", retryable=True) from None
        return completions(resp, self.model)


def response_format(schema: dict) -> dict:
    """OpenAI's structured-output request field for `schema` (strict: the model cannot leave it)."""
    return {"type": "json_schema", "json_schema": {"name": STRUCTURED_NAME, "strict": True, "schema": schema}}


def _about_schema(message: str) -> bool:
    m = message.lower()
    return any(w in m for w in ("response_format", "json_schema", "schema", "guided", "structured", "grammar"))


def completions(resp, model: str) -> list[Completion]:
    """The samples of a chat-completions response; a body that is not one (an HTML error page, a proxy's
    text, JSON of another shape, all with status 200) raises a retryable BackendError, as real clients
    retry it."""
    if isinstance(resp, (str, bytes)) or not isinstance(getattr(resp, "choices", None), list):
        head = str(resp)[:80] if isinstance(resp, (str, bytes)) else type(resp).__name__
        raise BackendError(f"openai: {model} answered 200 with a body that is not a chat completion "
                           f"({head!r}...)", retryable=True)
    try:
        choices = list(resp.choices)
        usage = getattr(resp, "usage", None)
        ins = split_usage(_count(getattr(usage, "prompt_tokens", None)), len(choices))
        outs = split_usage(_count(getattr(usage, "completion_tokens", None)), len(choices))
        out = []
        for c, i, o in zip(choices, ins, outs):
            if not hasattr(c, "message"):
                raise TypeError("a choice without a message")
            message = c.message
            text = getattr(message, "content", None) if message is not None else None
            if text is None and message is not None:  # a structured-output refusal: kept as the answer text
                text = getattr(message, "refusal", None)
            out.append(Completion(text=_text(text), input_tokens=i, output_tokens=o))
        return out
    except BackendError:
        raise
    except Exception as e:  # a JSON body of the right keys but wrong types
        raise BackendError(f"openai: {model} answered with a malformed chat completion ({type(e).__name__})",
                           retryable=True) from None


def _count(v) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2 ** 62 else None


def _text(v) -> str:
    if v is None:
        return ""
    if isinstance(v, str):
        return v
    try:  # content given as parts or any other JSON: keep it as text (it will fail to parse, counted)
        return json.dumps(v, default=str)[:1_000_000]
    except Exception:
        return str(type(v).__name__)


def _message(e: Exception) -> str:
    text = str(getattr(e, "message", None) or e)
    return text if len(text) < 300 else text[:300] + "..."

