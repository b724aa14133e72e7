"""VLM backends, one file each (openai, anthropic, gemini, hf, replay), registered in base.BACKENDS.

See base.py for what a backend declares and docs/prompting.md ("Adding a backend") for how to add one.
"""

from degusta_learn.prompting.backends.base import (
    BACKENDS,
    Backend,
    BackendConfig,
    BackendError,
    Completion,
    backend_class,
    backend_config,
    make_backend,
    redact,
)

__all__ = ["BACKENDS", "Backend", "BackendConfig", "BackendError", "Completion", "backend_class", "backend_config",
           "make_backend", "redact"]
