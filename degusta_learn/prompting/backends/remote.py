"""What the backends that call a service over HTTP share (openai, anthropic, gemini): their config keys
(`RemoteConfig`: base_url, api_key_env, timeout), whether a base_url is this machine, and how long a
rate-limited server asks to wait (`retry_after`).

Example:
    @dataclass
    class MyConfig(RemoteConfig):
        name: str = "mine"
    retry_after({"retry-after": "2"})  # 2.0
"""

from __future__ import annotations

import email.utils
import math
import time
from dataclasses import dataclass
from urllib.parse import urlparse

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import Backend, BackendConfig

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1", "0.0.0.0")


@dataclass
class RemoteConfig(BackendConfig):
    """The `backend:` keys of a backend that calls a service."""

    base_url: str | None = None
    """The service's endpoint (openai: any OpenAI-compatible server, e.g. http://127.0.0.1:8000/v1 for vLLM,
    :11434/v1 for Ollama; anthropic / gemini: a proxy); unset: the provider's own."""
    api_key_env: str | None = None
    """Environment variable holding the API key (default: the backend's, e.g. OPENAI_API_KEY)."""
    timeout: float = 120.0
    """Seconds a request may take in all -- connecting, sending, the status line and the whole reply (also
    each wait for a byte) -- before it counts as timed out and is retried (backends/transport.py)."""

    answer_keys = ("base_url",)

    def __post_init__(self):
        super().__post_init__()
        if self.timeout <= 0:
            raise DegustaError(f"backend.timeout: expected > 0, got {self.timeout}")
        if self.base_url is not None:
            url = urlparse(self.base_url) if isinstance(self.base_url, str) else None
            if url is None or url.scheme not in ("http", "https") or not url.hostname:
                raise DegustaError(f"backend.base_url: expected an http(s) URL such as http://127.0.0.1:8000/v1, "
                                   f"got {str(self.base_url)[:200]!r}")


def is_loopback(base_url: str | None) -> bool:
    """Whether `base_url` is a server on this machine."""
    return bool(base_url) and (urlparse(base_url).hostname or "") in LOCAL_HOSTS


class RemoteBackend(Backend):
    """A backend reached over HTTP at `base_url`: local (free unless `prices` names the model) when that is a
    server or proxy on this machine, a paid service otherwise."""

    empty_is_fault = True  # a 200 without an answer is the server's fault (retried), not the model's

    @classmethod
    def is_local(cls, cfg: RemoteConfig) -> bool:
        return is_loopback(cfg.base_url)


def retry_after(headers) -> float | None:
    """Seconds from a Retry-After (seconds or HTTP date) or retry-after-ms header, if any (None when absent
    or unreadable: a malformed header never raises)."""
    try:
        if headers is None:
            return None
        ms = headers.get("retry-after-ms")
        if ms:
            try:
                value = float(ms) / 1000.0
                if math.isfinite(value):
                    return max(0.0, value)
            except ValueError:
                pass
        value = headers.get("retry-after")
        if not value:
            return None
        try:
            seconds = float(value)
            return max(0.0, seconds) if math.isfinite(seconds) else None
        except ValueError:
            parsed = email.utils.parsedate_to_datetime(value)
            return max(0.0, parsed.timestamp() - time.time()) if parsed else None
    except Exception:  # a garbled date or header object
        return None
