"""Prices, token estimates and the per-run token + dollar ledger of zero-shot runs.

Prices are USD per 1M input / output tokens (`DEFAULT_PRICES`, list prices as of 2025; a config's
`prices` entries override them). A model is priced by its exact name, else by the longest known prefix
("gpt-4o-2024-08-06" -> "gpt-4o"); an unknown model (e.g. a local one) costs 0.

Estimates (for `--dry-run` and the budget check before each request): text ~3 characters a token;
images by the rule the backend declares (`Backend.image_tokens`: each provider's published rule, e.g.
OpenAI's 85 + 170 per 512-px tile, `tile_image_tokens`, which is also the estimate for local models).
Which model price applies is the backend's call too (`Backend.price`: a local backend costs nothing).
The paper's anchor (GPT-4o, one 4-context experiment, n = 5): 8,035 input + 6,250 output = 14,285
tokens, USD 0.15 at the 2024 price of 5 / 15.

Example:
    ledger = Ledger(price("gpt-4o", {}), budget_usd=1.0)
    ledger.reserve(0.01); ...; ledger.record(input_tokens=3000, output_tokens=900, reserved=0.01)
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

from degusta_learn.task.prompt import Prompt

DEFAULT_PRICES: dict[str, tuple[float, float]] = {
    "gpt-4o": (2.50, 10.00),
    "gpt-4o-2024-05-13": (5.00, 15.00),  # the price the paper paid
    "gpt-4o-mini": (0.15, 0.60),
    "gpt-4.1": (2.00, 8.00),
    "gpt-4.1-mini": (0.40, 1.60),
    "gpt-4.1-nano": (0.10, 0.40),
    "claude-3-haiku": (0.25, 1.25),
    "claude-3-5-haiku": (0.80, 4.00),
    "claude-3-5-sonnet": (3.00, 15.00),
    "claude-sonnet-4": (3.00, 15.00),
    "gemini-1.5-pro": (1.25, 5.00),
    "gemini-1.5-flash": (0.075, 0.30),
    "gemini-2.0-flash": (0.10, 0.40),
    "gemini-2.5-flash": (0.30, 2.50),
}


# Prompts and answers are JSON-like (quotes, brackets, ids): ~3 characters a token with GPT-4o's
# tokenizer, against ~4 for English prose; 3 errs on the expensive side.
CHARS_PER_TOKEN = 3.0


class BudgetExceeded(Exception):
    """Raised before a request that would take the run past `budget_usd`."""


def price(model: str, overrides: dict[str, Any] | None = None) -> tuple[float, float] | None:
    """(USD per 1M input tokens, per 1M output tokens) of `model`, or None when unknown."""
    table = {**DEFAULT_PRICES, **{k: tuple(v) for k, v in (overrides or {}).items()}}
    if model in table:
        return table[model]
    prefixes = [k for k in table if model.startswith(k)]
    return table[max(prefixes, key=len)] if prefixes else None


def tile_image_tokens(width: int, height: int, detail: str | None = None) -> int:
    """Input tokens of one image by OpenAI's published rule (85 + 170 per 512-px tile after fitting the
    image in 2048 px and its short side in 768 px; 85 at detail "low"); the estimate for local models."""
    if detail == "low":
        return 85
    scale = min(1.0, 2048 / max(width, height))
    w, h = width * scale, height * scale
    scale = min(1.0, 768 / min(w, h))
    w, h = w * scale, h * scale
    return 85 + 170 * math.ceil(w / 512) * math.ceil(h / 512)


def prompt_tokens(prompt: Prompt, image_tokens: Callable[[int, int], int] = tile_image_tokens) -> int:
    """Estimated input tokens of one request carrying `prompt`; `image_tokens(width, height)` counts an image."""
    text = sum(math.ceil(len(p) / CHARS_PER_TOKEN) for p in prompt.parts if isinstance(p, str))
    images = sum(image_tokens(*p.image.size) for p in prompt.images)
    return 10 + text + images


def cost(pr: tuple[float, float] | None, input_tokens: int, output_tokens: int) -> float:
    if pr is None:
        return 0.0
    return input_tokens * pr[0] / 1e6 + output_tokens * pr[1] / 1e6


class Ledger:
    """Thread-safe token and dollar accounting of one run, with the budget check."""

    def __init__(self, pr: tuple[float, float] | None, budget_usd: float | None = None):
        self.price, self.budget = pr, budget_usd
        self._lock = threading.Lock()
        self._reserved = 0.0
        self.stats: dict[str, Any] = {"requests": 0, "failed_requests": 0, "retries": 0, "samples_received": 0,
                                      "samples_cached": 0, "input_tokens": 0, "output_tokens": 0,
                                      "cost_usd": 0.0, "usage_missing": 0, "empty_answers": 0}

    def reserve(self, estimate_usd: float) -> None:
        """Book the estimate of a request about to start; BudgetExceeded if it would pass the budget."""
        with self._lock:
            if self.budget is not None and self.stats["cost_usd"] + self._reserved + estimate_usd > self.budget:
                raise BudgetExceeded(f"budget_usd {self.budget:.4f} reached (spent {self.stats['cost_usd']:.4f})")
            self._reserved += estimate_usd

    def release(self, estimate_usd: float) -> None:
        with self._lock:
            self._reserved = max(0.0, self._reserved - estimate_usd)

    def record(self, input_tokens: int | None, output_tokens: int | None, samples: int,
               fallback: tuple[int, int]) -> None:
        """Account one finished request (usage the server did not report is taken from `fallback`)."""
        with self._lock:
            if input_tokens is None or output_tokens is None:
                self.stats["usage_missing"] += 1
            i = fallback[0] if input_tokens is None else input_tokens
            o = fallback[1] if output_tokens is None else output_tokens
            self.stats["requests"] += 1
            self.stats["samples_received"] += samples
            self.stats["input_tokens"] += i
            self.stats["output_tokens"] += o
            self.stats["cost_usd"] += cost(self.price, i, o)

    def count(self, key: str, k: int = 1) -> None:
        with self._lock:
            self.stats[key] += k

    def summary(self) -> dict[str, Any]:
        with self._lock:
            out = dict(self.stats)
        out["cost_usd"] = round(out["cost_usd"], 6)
        out["total_tokens"] = out["input_tokens"] + out["output_tokens"]
        out["price_usd_per_1m"] = list(self.price) if self.price else None
        out["budget_usd"] = self.budget
        return out
