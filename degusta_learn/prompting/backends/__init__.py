"""VLM backends behind one protocol (see base.py): openai, anthropic, gemini, hf, replay."""

from degusta_learn.prompting.backends.base import (
    BACKENDS, Backend, BackendConfig, BackendError, Completion, make_backend, redact,
)

__all__ = ["BACKENDS", "Backend", "BackendConfig", "BackendError", "Completion", "make_backend", "redact"]
