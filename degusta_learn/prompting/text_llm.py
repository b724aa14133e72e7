"""`text_llm`: a text-only LLM in the TidyBot style -- summarise the person's preference, then set the table.

Usage:
    export OPENAI_API_KEY=...
    degusta predict --config configs/text_llm_gpt4o.yaml --dry-run     # both prompts' requests + cost, calls nothing
    degusta predict --config configs/text_llm_gpt4o.yaml
    degusta predict --config configs/text_llm_local.yaml --set backend.base_url=http://127.0.0.1:11434/v1

Two requests an episode (task/text_llm_prompt.py has the prompts): step 1 shows the catalog and the k context tables
written as text and asks for a short summary of the person's preference (one answer, `summary.temperature`); step 2
shows the catalog, that summary and the target table and asks for the placements in the unmarked answer format
(n answers, parsed by `task.answers.read_answer` and aggregated as the zero-shot methods' are, `decoding:`). At
context 0 there is nothing to summarise: step 1 is skipped and step 2 says so. No image is sent.

Everything else is the zero-shot runner's (`runner.ZeroShotRun`, which `TextLLMRun` extends): the backends (openai,
anthropic, gemini, hf, replay), the response cache (both steps' answers, each committed when received), retries, the
ledger and `budget_usd` (both steps' requests), the interrupt and resume rules, and the diagnostics of every
prediction, to which it adds `summary` (the text step 2 was given), `summary_cached` and `summary_failure`. A
summary that could not be had (a refused request, no recorded answer, an empty text) fails the episode, counted
as every unparseable answer is: each of its n samples fails with "no summary: <why>". ledger.json adds `steps`:
each step's answers received and cached and the tokens the backend reported for them.

`backend.structured_output` is refused (the summary is prose, which no answer schema fits), and so is
`decoding.constrained: true` for the hf backend (null is false here, not true), and `image_format` at any value
but its default (no image is drawn). `render_size` draws nothing either; only the hf backend reads it, comparing it
with a degusta-trained model's record (`Backend.check_run`: set the trained value, e.g. 256 for tiny_vlm_base).
"""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field
from typing import Literal

from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec
from degusta_learn.prompting.backends.base import Completion, backend_class, redact_json
from degusta_learn.prompting.cache import ResponseCache, sample_keys
from degusta_learn.prompting.costs import CHARS_PER_TOKEN, cost
from degusta_learn.prompting.runner import ZeroShotConfig, ZeroShotRun, cut_answer, fit_line
from degusta_learn.scene import Dataset, Episode, Prediction
from degusta_learn.task.prompt import Prompt
from degusta_learn.task.text_llm_prompt import ANSWER_METHOD, placement_prompt, summary_prompt

SUMMARY_MAX_CHARS = 8000
"""A longer summary is cut to this many characters (with a note of its length) before step 2 is given it."""
STEPS = ("summary", "placement")


@dataclass
class SummarySettings:
    """The `summary:` section: how step 1, the preference summary, is asked for."""

    max_new_tokens: int = bounded(512, 16, 8192)
    """Most tokens of the summary (a few sentences take 100-200)."""
    temperature: float = bounded(0.0, 0.0, 10.0)
    """Temperature of the one summary an episode gets (0: greedy, as TidyBot; the placements are sampled at decoding.temperature)."""
    est_output_tokens: int = bounded(200, 1, 8192)
    """Tokens a summary is assumed to take: the dry run's estimate, the budget check and step 2's estimated length."""


@dataclass
class TextLLMConfig(ZeroShotConfig):
    """A `text_llm` run: the zero-shot keys (backend, model, decoding, cache, budget, ...) plus the `summary:` step.
    Structured outputs and the image keys do not apply (`render_size` only meets the hf backend's record check)."""

    modality: Literal["text"] = "text"
    """How the context tables are shown: as text, the only way this method has."""
    prompt_style: Literal["clarified"] = "clarified"
    """The prompt's text: clarified (the one text of task/text_llm_prompt.py; the paper has no text-only prompt)."""
    summary: SummarySettings = field(default_factory=SummarySettings)
    """Step 1: the summary's token budget, temperature and assumed length."""

    def __post_init__(self):
        if backend_class(self.backend.name).local_decoding and self.decoding.constrained is None:
            self.decoding = dataclasses.replace(self.decoding, constrained=False)  # the summary is prose
        super().__post_init__()
        if self.backend.structured_output:
            raise DegustaError("backend.structured_output: text_llm's first step answers in prose (the summary), "
                               "which no answer schema fits; set backend.structured_output: false")
        if self.decoding.constrained:
            raise DegustaError("decoding.constrained: the answer grammar cannot hold text_llm's summary (prose); set "
                               "decoding.constrained: false")
        default = ZeroShotConfig.__dataclass_fields__["image_format"].default
        if self.image_format != default:
            raise DegustaError(f"image_format: text_llm sends no images; remove it (default: {default})")


class TextLLMRun(ZeroShotRun):
    """A zero-shot run whose episodes take two requests: the summary (submitted with its cache look-up, as the
    zero-shot prompt is), then the placements the summary leads to (looked up and asked for on the worker)."""

    answer_method = ANSWER_METHOD  # the placements' answer format: unmarked

    def __init__(self, cfg: TextLLMConfig, ds: Dataset):
        super().__init__(cfg, ds)
        self.tally = {step: {"samples_received": 0, "samples_cached": 0, "input_tokens": 0, "output_tokens": 0}
                      for step in STEPS}
        self._tally_lock = threading.Lock()

    def prompt(self, ep: Episode, style: str | None = None) -> tuple[Prompt | None, list[str]]:
        """Step 1's prompt and its one cache key; (None, []) at context 0 (no summary to ask for)."""
        prompt = summary_prompt(self.ds, ep)
        return prompt, ([] if prompt is None else self.summary_keys(prompt))

    def summary_keys(self, prompt: Prompt) -> list[str]:
        c, s = self.cfg, self.cfg.summary
        return sample_keys(prompt, c.backend, c.model, c.decoding, s.temperature, s.max_new_tokens, c.seed, 1)

    def placement(self, ep: Episode, summary: str | None) -> tuple[Prompt, list[str]]:
        """Step 2's prompt given the summary (None at context 0) and its samples' cache keys."""
        prompt = placement_prompt(self.ds, ep, summary)
        return prompt, self.keys(prompt)

    @staticmethod
    def summary_of(answer: Completion | None, why: str | None) -> tuple[str | None, str | None]:
        """(the summary step 2 is given, None) from step 1's answer, or (None, why there is none)."""
        if answer is None:
            return None, why or "no answer"
        text = answer.text.strip()
        return (cut_answer(text, SUMMARY_MAX_CHARS), None) if text else (None, "an empty summary")

    def add_tally(self, step: str, keys: list[str], samples: list, hits: dict) -> None:
        """Add one step's answers to `tally`: those cached, and those received now with their reported tokens."""
        new = [s for k, s in zip(keys, samples) if s is not None and k not in hits]
        with self._tally_lock:
            t = self.tally[step]
            t["samples_cached"] += len(hits)
            t["samples_received"] += len(new)
            t["input_tokens"] += sum(s.input_tokens or 0 for s in new)
            t["output_tokens"] += sum(s.output_tokens or 0 for s in new)

    def episode(self, ep: Episode, prompt: Prompt | None, keys: list[str], hits: dict[str, Completion]) -> Prediction:
        """Step 1 (unless context 0), then step 2 on the summary, then parse and aggregate (worker thread)."""
        c = self.cfg
        n = c.decoding.n
        summary, failure, cached = None, None, None
        if prompt is not None:
            samples: list[Completion | None] = [hits.get(k) for k in keys]
            reasons: dict[int, str] = {}
            self.fetch(ep, prompt, keys, samples, reasons, [0], c.summary.temperature,
                       max_tokens=c.summary.max_new_tokens, est_out=c.summary.est_output_tokens)
            self.add_tally("summary", keys, samples, hits)
            summary, failure = self.summary_of(samples[0], reasons.get(0))
            cached = keys[0] in hits
        if failure is not None:  # no step 2: every sample of the episode fails, counted
            pred = self.predict(ep, [None] * n, {i: f"no summary: {failure}" for i in range(n)}, cached=0)
        else:
            place, place_keys = self.placement(ep, summary)
            place_hits = self.lookup(place_keys)
            samples = [place_hits.get(k) for k in place_keys]
            reasons = {}
            self.fetch(ep, place, place_keys, samples, reasons, list(range(n)), c.decoding.sampling_temperature)
            if len(place_keys) > n:  # greedy_votes_pooled: the greedy answer, asked apart at temperature 0
                self.fetch(ep, place, place_keys, samples, reasons, [n], 0.0)
            self.add_tally("placement", place_keys, samples, place_hits)
            pred = self.predict(ep, samples, reasons, cached=len(place_hits))
        pred.diagnostics = {**pred.diagnostics, **redact_json({"summary": summary, "summary_cached": cached,
                                                               "summary_failure": failure})}
        return fit_line(pred)

    def ledger_extra(self, results: dict[str, Prediction]) -> dict:
        diags = [p.diagnostics for p in results.values()]
        with self._tally_lock:
            steps = {step: dict(t) for step, t in self.tally.items()}
        steps["summary"]["episodes_failed"] = sum(d.get("summary_failure") is not None for d in diags)
        steps["summary"]["episodes_without_context"] = sum(d.get("summary") is None and d.get("summary_failure") is None
                                                           for d in diags)
        return {"steps": steps}


# ----------------------------------------------------------------------------- the dry run

def estimate(run: TextLLMRun, episodes: list[Episode]) -> dict:
    """Requests, answers (new and cached), tokens and USD of each step of `run` on `episodes`, calling nothing.

    A cached summary gives step 2 its real prompt (and its cached answers); otherwise step 2 is priced with a
    summary of `summary.est_output_tokens` tokens. The cache is opened read-only (never created).
    """
    c = run.cfg
    cache = ResponseCache(run.cache_path, readonly=True) if run.cache_path else None
    placeholder = "x" * math.ceil(c.summary.est_output_tokens * CHARS_PER_TOKEN)
    steps = {step: {"requests": 0, "samples": 0, "cached": 0, "input_tokens": 0, "output_tokens": 0, "per_request": []}
             for step in STEPS}
    to_run = 0
    for ep in episodes:
        prompt, keys = run.prompt(ep)
        summary, todo = None, False
        if prompt is not None:
            hits = cache.get_many(keys) if cache else {}
            s, tokens = steps["summary"], run.input_tokens(prompt)
            s["per_request"].append(tokens)
            if hits:
                s["cached"] += 1
                summary = run.summary_of(hits[keys[0]], None)[0]
            else:
                todo = True
                s["requests"] += 1
                s["samples"] += 1
                s["input_tokens"] += tokens
                s["output_tokens"] += c.summary.est_output_tokens
        place, place_keys = run.placement(ep, summary if summary is not None or prompt is None else placeholder)
        hits = cache.get_many(place_keys) if cache and not todo else {}
        p, tokens = steps["placement"], run.input_tokens(place)
        p["per_request"].append(tokens)
        missing = len(place_keys) - len(hits)
        sampled = sum(k not in hits for k in place_keys[:c.decoding.n])  # the greedy answer: a request of its own
        requests = missing if run.per_sample else int(sampled > 0) + (missing - sampled)
        p["requests"] += requests
        p["samples"] += missing
        p["cached"] += len(hits)
        p["input_tokens"] += requests * tokens
        p["output_tokens"] += missing * run.est_out
        to_run += int(todo or missing > 0)
    if cache:
        cache.close()
    for s in steps.values():
        per = s.pop("per_request")
        s["input_tokens_per_request"] = round(sum(per) / max(1, len(per)))
        s["cost_usd"] = cost(run.price, s["input_tokens"], s["output_tokens"])
    return {"episodes": len(episodes), "episodes_to_run": to_run, "steps": steps,
            "output_tokens_per_sample": run.est_out, "summary_tokens": c.summary.est_output_tokens,
            "cost_usd": sum(s["cost_usd"] for s in steps.values()),
            "price_usd_per_1m": list(run.price) if run.price else None}


def print_estimate(cfg: TextLLMConfig, est: dict) -> None:
    """Print the dry-run summary (stdout): one line per step, then the cost."""
    pr = est["price_usd_per_1m"]
    priced = f"at USD {pr[0]:g} / {pr[1]:g} per 1M input / output tokens" if pr else \
        "(no price known for this model: set prices.<model> to estimate dollars)"
    s, p = est["steps"]["summary"], est["steps"]["placement"]
    print(f"dry run: {cfg.method} with {cfg.backend.name} {cfg.model.name}, {est['episodes']} episodes x "
          f"n={cfg.decoding.n} ({est['episodes_to_run']} still to run); two text prompts an episode, no images")
    if s["requests"] or s["cached"]:
        print(f"  step 1, summary: {s['requests']:,} requests for {s['samples']:,} summaries ({s['cached']:,} already "
              f"cached); estimated tokens {s['input_tokens']:,} input ({s['input_tokens_per_request']:,} a request) + "
              f"{s['output_tokens']:,} output ({est['summary_tokens']} a summary): USD {s['cost_usd']:.4f}")
    else:
        print("  step 1, summary: none (context 0: nothing to summarise)")
    print(f"  step 2, placement: {p['requests']:,} requests for {p['samples']:,} samples ({p['cached']:,} already cached); "
          f"estimated tokens {p['input_tokens']:,} input ({p['input_tokens_per_request']:,} a request, an uncached "
          f"summary counted at {est['summary_tokens']} tokens) + {p['output_tokens']:,} output "
          f"({est['output_tokens_per_sample']} a sample): USD {p['cost_usd']:.4f}")
    per_ep = est["cost_usd"] / max(1, est["episodes_to_run"])
    print(f"  estimated cost: USD {est['cost_usd']:.4f} {priced}; about USD {per_ep:.4f} an episode")


# ----------------------------------------------------------------------------- the method

def run_text_llm(cfg: TextLLMConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction] | None:
    """The MethodSpec entry point; returns None for a dry run (run_predict then writes nothing)."""
    run = TextLLMRun(cfg, ds)
    if cfg.dry_run:  # a dry run refuses what the real run would refuse before estimating
        backend_class(cfg.backend.name).check_run(cfg.backend, cfg.model, ds, episodes, cfg.render_size)
        print_estimate(cfg, estimate(run, episodes))
        return None
    from degusta_learn.files.locks import hold

    with hold(run.ledger_path, "text-LLM ledger"):  # a second run writing the same ledger and predictions: refused
        return run.run(episodes)


TEXT_LLM = MethodSpec(TextLLMConfig, run_text_llm,
                      "a text-only LLM, TidyBot-style: a preference summary from the context tables as text, then "
                      "the placements")
