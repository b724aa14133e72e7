"""Google Gemini models via the official `google-genai` client (`pip install degusta_learn[gemini]`).

The client is imported lazily, so the rest of the toolkit works without it; n samples are n requests
(as in the paper). The key comes from the environment variable `api_key_env` (default GEMINI_API_KEY).

With `structured_output: true` the config carries `response_mime_type="application/json"` and
`response_schema` (sent as `generationConfig.responseMimeType` / `responseSchema`): the answer's JSON
schema in Gemini's OpenAPI subset (`gemini_schema`: no additionalProperties, integer enums written as
`format: enum` strings, `propertyOrdering` for the key order).

What it is: one request per sample; a paid service priced by model name (a `base_url` on this machine,
a proxy, is not priced unless `prices` names the model); 258 input tokens an image.

Example:
    backend = GeminiBackend.from_config(GeminiConfig(), ModelSettings(name="gemini-1.5-pro"))
"""

from __future__ import annotations

from dataclasses import dataclass

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import AnswerSchemas, BackendError, Completion, api_key
from degusta_learn.prompting.backends.remote import RemoteBackend, RemoteConfig
from degusta_learn.prompting.backends.transport import fault_reason, guarded_client, guarded_transport
from degusta_learn.task.prompt import ImagePart, Prompt
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings


@dataclass
class GeminiConfig(RemoteConfig):
    """The `backend:` keys of the gemini backend."""

    name: str = "gemini"


def _import():
    try:
        from google import genai
        from google.genai import errors, types
    except ImportError:
        raise DegustaError("backend.name: the gemini backend needs Google's google-genai client: "
                           "pip install degusta_learn[gemini]") from None
    return genai, types, errors


def _transient(e: Exception) -> bool:
    names = [c.__name__ for c in type(e).__mro__]
    return any(k in n for n in names for k in ("Timeout", "TransportError", "ConnectError", "NetworkError"))


class GeminiBackend(RemoteBackend):
    """Gemini via `client.models.generate_content`; n separate requests."""

    name = "gemini"
    config_class = GeminiConfig
    per_sample = True  # one candidate a request
    cacheable = True
    takes_schema = True  # response_mime_type + response_schema
    key_env = "GEMINI_API_KEY"

    @classmethod
    def image_tokens(cls, width: int, height: int, cfg: GeminiConfig, model: ModelSettings | None = None) -> int:
        return 258

    def __init__(self, model: str, client, schemas: AnswerSchemas | None = None):
        self.model, self.client = model, client
        self.schemas = schemas  # set: structured outputs (response_mime_type + response_schema)

    @classmethod
    def from_config(cls, cfg: GeminiConfig, model: ModelSettings, decoding: DecodingSettings | None = None,
                    grid=None, catalog=None) -> GeminiBackend:
        key = api_key(cfg.api_key_env or cls.key_env)
        genai, types, _ = _import()
        options = {"timeout": max(1, int(cfg.timeout * 1000)), **({"base_url": cfg.base_url} if cfg.base_url else {})}
        fields = getattr(types.HttpOptions, "model_fields", {})
        if "httpx_client" in fields:  # one deadline a request, bounded replies (transport.py)
            options["httpx_client"] = guarded_client(cfg.timeout)
        elif "client_args" in fields:  # an older google-genai: the client it builds gets the same transport
            options["client_args"] = {"transport": guarded_transport(cfg.timeout)}
        return cls(model.name, genai.Client(api_key=key, http_options=types.HttpOptions(**options)),
                   AnswerSchemas(grid, catalog) if cfg.structured_output else None)

    def complete(self, prompt: Prompt, n: int, temperature: float, max_tokens: int,
                 seed: int | None = None) -> list[Completion]:
        _, types, errors = _import()
        contents = [types.Part.from_bytes(data=p.encode(), mime_type=p.mime) if isinstance(p, ImagePart)
                    else types.Part.from_text(text=p) for p in prompt.parts]
        structured = {} if self.schemas is None else {
            "response_mime_type": "application/json", "response_schema": gemini_schema(self.schemas(prompt))}
        config = types.GenerateContentConfig(temperature=temperature, max_output_tokens=max_tokens, seed=seed,
                                             **structured)
        out = []
        for _ in range(n):
            try:
                resp = self.client.models.generate_content(model=self.model, contents=contents, config=config)
            except errors.APIError as e:
                if out:
                    break
                code = int(getattr(e, "code", 0) or 0)
                raise BackendError(f"gemini: HTTP {code} from {self.model}: {str(e)[:300]}", status=code,
                                   fatal=code in (401, 403, 404), retryable=code in (408, 429) or code >= 500) from None
            except ValueError as e:  # a 200 whose body is not JSON (an HTML page, a truncated body)
                if out:
                    break
                raise BackendError(f"gemini: {self.model} answered with a malformed body ({type(e).__name__}); "
                                   "retrying", retryable=True) from None
            except Exception as e:  # timeouts and dropped connections of google-genai's HTTP library
                why = fault_reason(e)  # the request's deadline, or a reply refused for its size (transport.py)
                if not (why or _transient(e)):
                    raise
                if out:
                    break
                raise BackendError(f"gemini: {self.model}: {why}" if why else
                                   f"gemini: {type(e).__name__}: {str(e)[:300]}", retryable=True) from None
            usage = getattr(resp, "usage_metadata", None)
            out.append(Completion(text=resp.text or "", input_tokens=getattr(usage, "prompt_token_count", None),
                                  output_tokens=getattr(usage, "candidates_token_count", None)))
        return out


def gemini_schema(schema: dict) -> dict:
    """A JSON schema (answers.answer_schema) in the OpenAPI subset of Gemini's `responseSchema`: object
    keys kept in order (`propertyOrdering`), `additionalProperties` dropped (Gemini adds no keys), integer
    enums written as `{"type": "integer", "format": "enum", "enum": ["0", "1", ...]}` (Gemini's enums are
    strings)."""
    if isinstance(schema, list):
        return [gemini_schema(s) for s in schema]
    if not isinstance(schema, dict):
        return schema
    out = {}
    for k, v in schema.items():
        if k == "additionalProperties":
            continue
        if k == "properties":
            out[k] = {name: gemini_schema(sub) for name, sub in v.items()}
            out["propertyOrdering"] = list(v)
        elif k == "enum" and schema.get("type") in ("integer", "number"):
            out["format"] = "enum"
            out[k] = [str(x) for x in v]
        else:
            out[k] = gemini_schema(v)
    return out
