"""Anthropic Claude models via the official `anthropic` client (`pip install degusta_learn[anthropic]`).

The Messages API returns one answer per request, so n samples are n requests (as in the paper's cost
table). Images go as base64 blocks, interleaved with the text parts. The key comes from the
environment variable `api_key_env` (default ANTHROPIC_API_KEY); `base_url` points at a proxy if set.

With `structured_output: true` the answer's JSON schema goes as the input schema of one tool the model is
forced to call (`tools=[{"name": "degusta_answer", "description", "input_schema"}]`,
`tool_choice={"type": "tool", "name": "degusta_answer"}`); the answer is that tool_use block's `input`,
kept as JSON text. A reply without the tool call (a proxy that drops tools) is read from its text.

What it is: one request per sample; a paid service priced by model name (a `base_url` on this machine,
a proxy, is not priced unless `prices` names the model); images counted by Anthropic's rule
(width x height / 750, after fitting the long side in 1568 px).

Example:
    backend = AnthropicBackend.from_config(AnthropicConfig(), ModelSettings(name="claude-3-haiku-20240307"))
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
from dataclasses import dataclass

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import AnswerSchemas, BackendError, Completion, api_key
from degusta_learn.prompting.backends.remote import RemoteBackend, RemoteConfig, retry_after
from degusta_learn.prompting.backends.transport import fault_reason, guarded_client
from degusta_learn.task.answers import STRUCTURED_KEY, STRUCTURED_NAME
from degusta_learn.task.prompt import ImagePart, Prompt
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings


@dataclass
class AnthropicConfig(RemoteConfig):
    """The `backend:` keys of the anthropic backend."""

    name: str = "anthropic"


def _import():
    try:
        import anthropic
    except ImportError:
        raise DegustaError("backend.name: the anthropic backend needs the anthropic client: "
                           "pip install degusta_learn[anthropic]") from None
    return anthropic


class AnthropicBackend(RemoteBackend):
    """Claude via the Messages API; n separate requests."""

    name = "anthropic"
    config_class = AnthropicConfig
    per_sample = True  # the Messages API has no `n`
    cacheable = True
    takes_schema = True  # a forced tool whose input schema is the answer's
    key_env = "ANTHROPIC_API_KEY"

    @classmethod
    def image_tokens(cls, width: int, height: int, cfg: AnthropicConfig, model: ModelSettings | None = None) -> int:
        scale = min(1.0, 1568 / max(width, height))
        return math.ceil(width * scale * height * scale / 750)

    def __init__(self, model: str, client, schemas: AnswerSchemas | None = None):
        self.model, self.client = model, client
        self.schemas = schemas  # set: structured outputs (a forced tool whose input schema is the answer's)

    @classmethod
    def from_config(cls, cfg: AnthropicConfig, model: ModelSettings, decoding: DecodingSettings | None = None,
                    grid=None, catalog=None) -> AnthropicBackend:
        key = api_key(cfg.api_key_env or cls.key_env)
        anthropic = _import()
        client = anthropic.Anthropic(api_key=key, base_url=cfg.base_url, timeout=cfg.timeout, max_retries=0,
                                     http_client=guarded_client(cfg.timeout, anthropic))  # transport.py
        return cls(model.name, client, AnswerSchemas(grid, catalog) if cfg.structured_output else None)

    @staticmethod
    def content(prompt: Prompt) -> list[dict]:
        out = []
        for part in prompt.parts:
            if isinstance(part, ImagePart):
                data = base64.b64encode(part.encode()).decode("ascii")
                out.append({"type": "image", "source": {"type": "base64", "media_type": part.mime, "data": data}})
            else:
                out.append({"type": "text", "text": part})
        return out

    def complete(self, prompt: Prompt, n: int, temperature: float, max_tokens: int,
                 seed: int | None = None) -> list[Completion]:
        anthropic = _import()
        if not 0.0 <= temperature <= 1.0:
            raise BackendError(f"anthropic: temperature must be in [0, 1], got {temperature}", fatal=True)
        messages = [{"role": "user", "content": self.content(prompt)}]
        extra = tool_request(self.schemas(prompt)) if self.schemas is not None else {}
        extra.update(sampling_arguments(self.client.messages.create, temperature))
        out = []
        for _ in range(n):
            try:
                resp = self.client.messages.create(model=self.model, max_tokens=max_tokens, messages=messages,
                                                   **extra)
            except anthropic.APIStatusError as e:
                status = e.status_code
                msg = f"anthropic: HTTP {status} from {self.model}: {str(e)[:300]}"
                if out:  # keep what we have; the runner asks again for the rest
                    break
                raise BackendError(msg, fatal=status in (401, 403, 404),
                                   retryable=status in (408, 409, 429) or status >= 500,
                                   retry_after=retry_after(e.response.headers), status=status) from None
            except (anthropic.APITimeoutError, anthropic.APIConnectionError) as e:
                if out:
                    break
                why = fault_reason(e)  # the request's deadline, or a reply refused for its size (transport.py)
                raise BackendError(f"anthropic: {self.model}: {why}" if why else
                                   f"anthropic: {type(e).__name__}: {str(e)[:300]}", retryable=True) from None
            except ValueError as e:  # a 200 whose body is not JSON (an HTML page, a truncated body)
                if out:
                    break
                raise BackendError(f"anthropic: {self.model} answered with a malformed body ({type(e).__name__}); "
                                   "retrying", retryable=True) from None
            text = answer_text(resp.content)
            usage = getattr(resp, "usage", None)
            out.append(Completion(text=text, input_tokens=getattr(usage, "input_tokens", None),
                                  output_tokens=getattr(usage, "output_tokens", None)))
        return out


def sampling_arguments(create, temperature: float) -> dict:
    """`temperature` as the installed client takes it: a keyword up to anthropic 1.x; 2.x dropped the
    keyword from `messages.create`, so it travels in the request body (`extra_body`) as the API reads it."""
    import inspect

    try:
        takes = "temperature" in inspect.signature(create).parameters
    except (TypeError, ValueError):  # a callable without a signature: pass it the usual way
        takes = True
    return {"temperature": temperature} if takes else {"extra_body": {"temperature": temperature}}


def tool_request(schema: dict) -> dict:
    """The forced-tool fields of a Messages request whose answer must follow `schema`."""
    return {"tools": [{"name": STRUCTURED_NAME, "input_schema": schema,
                       "description": "Give the table-setting plan: the objects to place, in placement order."}],
            "tool_choice": {"type": "tool", "name": STRUCTURED_NAME}}


def answer_text(blocks) -> str:
    """The answer in a response's content blocks: the forced tool call's input as JSON text, else the text."""
    for b in blocks or []:
        if getattr(b, "type", None) == "tool_use" and getattr(b, "name", None) == STRUCTURED_NAME:
            value = getattr(b, "input", None)
            if isinstance(value, dict) and isinstance(value.get(STRUCTURED_KEY), str):
                with contextlib.suppress(ValueError):  # a model that wrote the list as a JSON string
                    value = {**value, STRUCTURED_KEY: json.loads(value[STRUCTURED_KEY])}
            try:
                return json.dumps(value)
            except (TypeError, ValueError):
                return str(value)
    return "".join(t for b in blocks or [] if isinstance(t := getattr(b, "text", ""), str))
