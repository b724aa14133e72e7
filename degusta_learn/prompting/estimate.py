"""`--dry-run`: how many requests a zero-shot run makes and what it will cost, calling nothing.

Prompts are built exactly as in the real run (so image sizes and text lengths are the real ones) and the
response cache is opened read-only (never created), so samples already answered are not counted.
Output tokens per sample are estimated from the canonical answers of the dataset's own arrangements
(`est_output_tokens` overrides that). What a request takes and costs (image tokens, one request per sample
or n in one, the price) is asked of the backend's class, which is never built: a dry run loads no model
and needs no key. The input tokens a request would take under each prompt style (`prompt_style`: clarified,
paper) are shown beside the configured one's (`tokens_by_style`).

Example:
    degusta predict --config configs/zeroshot_mogma_gpt4o.yaml --dry-run
"""

from __future__ import annotations

import math
from typing import Any

from degusta_learn.prompting.cache import ResponseCache
from degusta_learn.prompting.costs import CHARS_PER_TOKEN, cost
from degusta_learn.scene import Dataset
from degusta_learn.task.answer_format import answer_items, format_answer

PAPER_ANCHOR = ("paper anchor, GPT-4o, one 4-context experiment, n=5: 8,035 in + 6,250 out = 14,285 tokens, "
                "USD 0.15 at 2024 prices")


def output_tokens_per_sample(ds: Dataset, kind: str, grid, max_arrangements: int = 50) -> int:
    """Tokens of a canonical answer for an average arrangement of `ds` (CHARS_PER_TOKEN) + 10%."""
    arrs = ds.arrangements[:max_arrangements]
    if not arrs:
        return 200
    chars = [len(format_answer(answer_items(list(a.placements), ds.catalog, kind, grid), kind)) for a in arrs]
    return math.ceil(1.1 * sum(chars) / len(chars) / CHARS_PER_TOKEN) + 5


def estimate_run(run, episodes: list) -> dict[str, Any]:
    """Requests, samples (new and cached), tokens and USD of running `run` (a ZeroShotRun) on `episodes`."""
    cache = ResponseCache(run.cache_path, readonly=True) if run.cache_path else None
    est = {"episodes": len(episodes), "episodes_to_run": 0, "samples": 0, "cached": 0, "requests": 0, "input_tokens": 0,
           "output_tokens": 0, "output_tokens_per_sample": run.est_out}
    per_prompt = []
    for ep in episodes:
        prompt, keys = run.prompt(ep)
        hits = cache.get_many(keys) if cache else {}
        missing = len(keys) - len(hits)
        tokens = run.input_tokens(prompt)
        per_prompt.append(tokens)
        sampled = sum(k not in hits for k in keys[:run.cfg.decoding.n])  # greedy_votes_pooled's greedy answer: a request of its own
        requests = missing if run.per_sample else int(sampled > 0) + (missing - sampled)
        est["episodes_to_run"] += int(missing > 0)
        est["samples"] += missing
        est["cached"] += len(hits)
        est["requests"] += requests
        est["input_tokens"] += requests * tokens
        est["output_tokens"] += missing * run.est_out
    if cache:
        cache.close()
    est["input_tokens_per_request"] = round(sum(per_prompt) / max(1, len(per_prompt)))
    est["prompt_style"] = run.cfg.prompt_style
    est["input_tokens_per_request_by_style"] = tokens_by_style(run, episodes, per_prompt)
    est["cost_usd"] = cost(run.price, est["input_tokens"], est["output_tokens"])
    est["price_usd_per_1m"] = list(run.price) if run.price else None
    return est


def tokens_by_style(run, episodes: list, own_tokens: list[int]) -> dict[str, int]:
    """Mean input tokens a request of `run` would take under each prompt style (`task.prompt.PROMPT_STYLES`).

    `own_tokens` are the episodes' counts under the configured style. The styles differ only in their text parts
    (the same images in the same order), and that text depends on the context length alone, so another style's
    count is each episode's own plus the difference measured on the first episode of its context length: one
    extra prompt per context length, not one per episode.
    """
    from degusta_learn.task.prompt import PROMPT_STYLES

    if not episodes:
        return {}
    first: dict[int, int] = {}
    for i, ep in enumerate(episodes):
        first.setdefault(len(ep.context), i)
    out = {}
    for style in PROMPT_STYLES:
        delta = {k: 0 if style == run.cfg.prompt_style else
                 run.input_tokens(run.prompt(episodes[i], style)[0]) - own_tokens[i] for k, i in first.items()}
        out[style] = round(sum(t + delta[len(ep.context)] for t, ep in zip(own_tokens, episodes)) / len(episodes))
    return out


def print_estimate(cfg, est: dict[str, Any]) -> None:
    """Print the dry-run summary (stdout)."""
    todo = max(1, est["episodes_to_run"])
    per_ep = est["cost_usd"] / todo
    tokens_per_ep = (est["input_tokens"] + est["output_tokens"]) / todo
    pr = est["price_usd_per_1m"]
    priced = f"at USD {pr[0]:g} / {pr[1]:g} per 1M input / output tokens" if pr else \
        "(no price known for this model: set prices.<model> to estimate dollars)"
    print(f"dry run: {cfg.method} with {cfg.backend.name} {cfg.model.name}, {est['episodes']} episodes x "
          f"n={cfg.decoding.n} "
          f"({est['episodes_to_run']} still to run)")
    print(f"  requests: {est['requests']} for {est['samples']} samples ({est['cached']} samples already cached)")
    print(f"  estimated tokens: {est['input_tokens']:,} input ({est['input_tokens_per_request']:,} a request) + "
          f"{est['output_tokens']:,} output ({est['output_tokens_per_sample']} a sample) "
          f"= {tokens_per_ep:,.0f} an episode")
    by_style = est.get("input_tokens_per_request_by_style") or {}
    if by_style:
        shown = ", ".join(f"{style} {tokens:,}" for style, tokens in by_style.items())
        print(f"  prompt_style: {est['prompt_style']} (input tokens a request by prompt style: {shown})")
    print(f"  estimated cost: USD {est['cost_usd']:.4f} {priced}; about USD {per_ep:.4f} an episode")
    print(f"  ({PAPER_ANCHOR})")
