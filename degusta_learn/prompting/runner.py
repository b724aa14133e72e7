"""The zero-shot predict method (louma, logma, mouma, mogma): prompts -> VLM -> parsed, aggregated plans.

Usage:
    export OPENAI_API_KEY=...
    degusta predict --config configs/zeroshot_mogma_gpt4o.yaml --dry-run     # requests + cost, calls nothing
    degusta predict --config configs/zeroshot_mogma_gpt4o.yaml
    degusta predict --config configs/zeroshot_mogma_local.yaml --set backend.base_url=http://127.0.0.1:8000/v1

For each episode the runner builds the method's prompt (main thread), looks every sample up in the
SQLite response cache, asks the backend for the missing ones on a bounded thread pool (retrying rate
limits, server errors and timeouts with exponential backoff + jitter, honouring Retry-After), caches
each answer the moment it arrives, parses and aggregates the n answers, and finally writes
predictions.jsonl (through `methods.run_predict`) and `ledger.json` (tokens and dollars) beside it.
A `budget_usd` cap or a fatal API error (bad key) stops the run cleanly: finished answers stay cached,
the ledger is written, no predictions file is written, and re-running resumes where it stopped.
"""

from __future__ import annotations

import random
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from degusta_learn.errors import DegustaError
from degusta_learn.fileio import atomic_write_json
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.prompting.aggregate import aggregate
from degusta_learn.prompting.answers import AnswerParseError, answer_kind, parse_answer
from degusta_learn.prompting.backends.base import BackendConfig, BackendError, Completion, make_backend, redact
from degusta_learn.prompting.backends.openai import is_local
from degusta_learn.prompting.cache import ResponseCache, sample_keys
from degusta_learn.prompting.costs import BudgetExceeded, Ledger, cost, price
from degusta_learn.prompting.estimate import estimate_run, output_tokens_per_sample, print_estimate
from degusta_learn.prompting.prompt import IMAGE_FORMATS, Prompt, build_prompt
from degusta_learn.scene import Dataset, Episode, Prediction

PER_SAMPLE_BACKENDS = ("anthropic", "gemini")  # one request per sample (no `n` in their APIs)


@dataclass
class GridSize:
    """The labelled grid of grid methods (logma, mogma)."""

    rows: int = 8
    """Rows, numbered 1.. from the top."""
    cols: int = 8
    """Columns, lettered A.. from the left (at most 26)."""


@dataclass
class ZeroShotConfig(PredictConfig):
    """A zero-shot prompting run: the common predict keys plus backend, sampling and run control."""

    backend: BackendConfig = field(default_factory=BackendConfig)
    """Which VLM answers (see docs/prompting.md)."""
    n: int = 5
    """Sampled answers per episode, aggregated (the paper: 5)."""
    temperature: float = 1.0
    """Sampling temperature (the APIs' default 1.0; 0 makes the n samples near-identical)."""
    concurrency: int = 4
    """Requests in flight at once."""
    cache: str | None = None
    """SQLite response cache; unset: responses_cache.sqlite beside `out`; "off": no cache."""
    image_size: int = 448
    """Side of the rendered images in pixels (more pixels: more image tokens)."""
    image_format: str = "jpeg"
    """jpeg or png (the names in the prompt follow: final_state_1.jpg / .png)."""
    grid: GridSize = field(default_factory=GridSize)
    """Grid of grid methods."""
    max_retries: int = 5
    """Retries of a request after a rate limit, server error or timeout (then its samples fail)."""
    backoff: float = 1.0
    """First retry delay in seconds; doubles each retry, with +-50% jitter."""
    backoff_max: float = 60.0
    """Longest wait between retries (a Retry-After header is honoured up to this)."""
    budget_usd: float | None = None
    """Stop cleanly before a request that would take this run's spend past this (unset: no cap)."""
    dry_run: bool = False
    """Print the number of requests and the estimated cost; call nothing, write nothing."""
    prices: dict[str, list[float]] = field(default_factory=dict)
    """USD per 1M [input, output] tokens by model name, over the built-in table (costs.DEFAULT_PRICES)."""
    est_output_tokens: int | None = None
    """Output tokens a sample is assumed to take in estimates (unset: from the dataset's arrangements)."""

    def __post_init__(self):
        super().__post_init__()
        checks = [("n", self.n >= 1, ">= 1"), ("concurrency", self.concurrency >= 1, ">= 1"),
                  ("temperature", self.temperature >= 0, ">= 0"), ("image_size", self.image_size >= 64, ">= 64"),
                  ("max_retries", self.max_retries >= 0, ">= 0"), ("backoff", self.backoff >= 0, ">= 0"),
                  ("budget_usd", self.budget_usd is None or self.budget_usd >= 0, ">= 0"),
                  ("image_format", self.image_format in IMAGE_FORMATS, f"one of {list(IMAGE_FORMATS)}")]
        for key, ok, expected in checks:
            if not ok:
                raise DegustaError(f"{key}: expected {expected}, got {getattr(self, key)!r}")
        for model, pr in self.prices.items():
            if len(pr) != 2 or min(pr) < 0:
                raise DegustaError(f"prices.{model}: expected [usd_per_1m_input, usd_per_1m_output], got {pr!r}")


class _Stopped(Exception):
    """An episode left unfinished because the run is stopping."""


class ZeroShotRun:
    """One run's state: backend, cache, ledger and the stop flag shared by the worker threads."""

    def __init__(self, cfg: ZeroShotConfig, ds: Dataset):
        from degusta_learn.render.grid import Grid
        from degusta_learn.render.lifting import Renderer

        self.cfg, self.ds = cfg, ds
        self.kind = answer_kind(cfg.method)
        self.grid = Grid(cfg.grid.rows, cfg.grid.cols)
        self.renderer = Renderer.for_dataset(ds, size=cfg.image_size)
        self.out = Path(cfg.out)
        self.cache_path = None if cfg.cache == "off" else Path(cfg.cache or self.out.parent / "responses_cache.sqlite")
        local = cfg.backend.name in ("hf", "replay") or is_local(cfg.backend.base_url)
        # A local model (hf, replay, a loopback server) costs nothing unless priced explicitly.
        self.price = None if local and cfg.backend.model not in cfg.prices else price(cfg.backend.model, cfg.prices)
        self.per_sample = cfg.backend.name in PER_SAMPLE_BACKENDS
        self.est_out = cfg.est_output_tokens or output_tokens_per_sample(ds, self.kind, self.grid)
        self.stop = threading.Event()

    def prompt(self, ep: Episode) -> tuple[Prompt, list[str]]:
        c = self.cfg
        prompt = build_prompt(c.method, self.ds, ep, self.renderer, self.grid, c.image_format)
        return prompt, sample_keys(prompt, c.backend, c.temperature, c.backend.max_tokens, c.seed, c.n)

    # ------------------------------------------------------------------------- requests

    def request(self, prompt: Prompt, k: int, seed: int | None) -> list[Completion]:
        """Ask for k samples, retrying transient errors; raises BudgetExceeded, _Stopped or BackendError."""
        from degusta_learn.prompting.costs import prompt_tokens

        c = self.cfg
        est_in = prompt_tokens(prompt, c.backend.name, c.backend.detail) * (k if self.per_sample else 1)
        est_out = self.est_out * k
        est_usd = cost(self.price, est_in, est_out)
        for attempt in range(c.max_retries + 1):
            if self.stop.is_set():
                raise _Stopped()
            self.ledger.reserve(est_usd)
            try:
                got = self.backend.complete(prompt, k, c.temperature, c.backend.max_tokens, seed)
            except BackendError as e:
                self.ledger.release(est_usd)
                if e.fatal or not e.retryable or attempt == c.max_retries:
                    if not e.fatal:
                        self.ledger.count("failed_requests")
                    raise
                delay = min(c.backoff_max, c.backoff * 2 ** attempt) * (0.5 + random.random())
                if e.retry_after is not None:
                    delay = min(c.backoff_max, e.retry_after) * (1.0 + 0.1 * random.random())
                self.ledger.count("retries")
                self.stop.wait(delay)
                continue
            self.ledger.release(est_usd)
            ins = [x.input_tokens for x in got]
            outs = [x.output_tokens for x in got]
            self.ledger.record(None if None in ins else sum(ins), None if None in outs else sum(outs), len(got),
                               fallback=(est_in, self.est_out * len(got)))
            return got
        raise AssertionError("unreachable")

    def episode(self, ep: Episode, prompt: Prompt, keys: list[str], hits: dict[str, Completion]) -> Prediction:
        """Fetch the missing samples of one episode, then parse and aggregate all n (worker thread)."""
        c = self.cfg
        samples: list[Completion | None] = [hits.get(k) for k in keys]
        reasons: dict[int, str] = {}
        missing = [i for i, s in enumerate(samples) if s is None]
        while missing:
            seed = None if c.seed is None else c.seed + missing[0]
            try:
                got = self.request(prompt, len(missing), seed)
            except BudgetExceeded:
                self.stop.set()  # at once, so no other worker starts a request
                raise
            except BackendError as e:
                if e.fatal:
                    self.stop.set()
                    raise
                for i in missing:
                    reasons[i] = f"request failed: {e}"
                break
            if not got:
                for i in missing:
                    reasons[i] = "the backend returned no answer"
                break
            for i, comp in zip(missing, got):
                samples[i] = comp
                if self.cache is not None:
                    self.cache.put(keys[i], comp, ep.id)
            missing = missing[len(got):]
            if not self.cacheable:  # replay: one look-up, whatever is missing stays missing
                for i in missing:
                    reasons[i] = "no recorded answer"
                break
        return self.predict(ep, samples, reasons, cached=len(hits))

    def predict(self, ep: Episode, samples: list[Completion | None], reasons: dict[int, str],
                cached: int) -> Prediction:
        parsed = []
        for i, s in enumerate(samples):
            if s is None:
                parsed.append(None)
                continue
            try:
                parsed.append(parse_answer(s.text, self.kind, self.ds.catalog, self.grid))
            except AnswerParseError as e:
                reasons[i] = f"unparseable answer: {e}"
                parsed.append(None)
        placements, agg = aggregate(parsed, self.kind, self.grid)
        diag = {"backend": self.cfg.backend.name, "model": self.cfg.backend.model, "n": self.cfg.n,
                "cached": cached, "responses": [redact(s.text) if s else None for s in samples],
                "failures": [{"sample": i, "reason": redact(r)} for i, r in sorted(reasons.items())], **agg}
        return Prediction(episode=ep.id, participant=ep.participant, target=ep.target, method=self.cfg.method,
                          placements=placements, failed=agg["failed"], diagnostics=diag)

    # ------------------------------------------------------------------------- the run

    def run(self, episodes: list[Episode]) -> list[Prediction]:
        c = self.cfg
        self.backend = make_backend(c.backend, self.grid, self.ds.catalog)
        self.cacheable = getattr(self.backend, "cacheable", True)
        self.cache = ResponseCache(self.cache_path) if self.cache_path and self.cacheable else None
        self.ledger = Ledger(self.price, c.budget_usd)
        results: dict[str, Prediction] = {}
        stopped: str | None = None
        reused = [0, 0]  # tokens of cached answers (paid in an earlier run)
        start = time.time()
        todo = iter(episodes)
        bar = tqdm(total=len(episodes), desc=f"{c.method} {c.backend.model}", unit="ep", disable=None)
        pool = ThreadPoolExecutor(max_workers=c.concurrency, thread_name_prefix="degusta-zeroshot")
        pending: dict = {}

        def submit_next() -> bool:
            ep = next(todo, None)
            if ep is None:
                return False
            prompt, keys = self.prompt(ep)
            hits = self.cache.get_many(keys) if self.cache else {}
            self.ledger.count("samples_cached", len(hits))
            for h in hits.values():
                reused[0] += h.input_tokens or 0
                reused[1] += h.output_tokens or 0
            pending[pool.submit(self.episode, ep, prompt, keys, hits)] = ep
            return True

        try:
            while len(pending) < 2 * c.concurrency and submit_next():
                pass
            while pending:
                done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                for fut in done:
                    ep = pending.pop(fut)
                    try:
                        results[ep.id] = fut.result()
                        bar.update(1)
                    except _Stopped:
                        pass
                    except BudgetExceeded as e:
                        stopped = stopped or f"budget: {e}"
                        self.stop.set()
                    except BackendError as e:  # fatal (bad key, unknown model)
                        stopped = stopped or f"error: {e}"
                        self.stop.set()
                bar.set_postfix_str(f"${self.ledger.summary()['cost_usd']:.4f}")
                while not self.stop.is_set() and len(pending) < 2 * c.concurrency and submit_next():
                    pass
        except KeyboardInterrupt:
            self.stop.set()
            stopped = "interrupted"
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            bar.close()
            self.write_ledger(episodes, results, stopped, time.time() - start, reused)
            if self.cache is not None:
                self.cache.close()
        if stopped:
            done_n = len(results)
            raise DegustaError(f"zero-shot run stopped ({stopped}) after {done_n} of {len(episodes)} episodes; "
                               f"finished answers are cached in {self.cache_path} and the spend is in "
                               f"{self.ledger_path}; re-run the same command to resume (nothing was written to "
                               f"{self.out})")
        return [results[ep.id] for ep in episodes]

    @property
    def ledger_path(self) -> Path:
        return self.out.parent / "ledger.json"

    def write_ledger(self, episodes, results, stopped, wall_s, reused) -> None:
        c = self.cfg
        summary = self.ledger.summary()
        atomic_write_json(self.ledger_path, {
            "method": c.method, "backend": c.backend.name, "model": c.backend.model, "base_url": c.backend.base_url,
            "n": c.n, "episodes": len(episodes), "episodes_done": len(results),
            "episodes_failed": sum(p.failed for p in results.values()), "stopped": stopped,
            "wall_s": round(wall_s, 3), "cache": str(self.cache_path) if self.cache is not None else None,
            **summary,
            "cost_usd_per_episode": round(summary["cost_usd"] / max(1, len(results)), 6),
            "reused_from_cache": {"input_tokens": reused[0], "output_tokens": reused[1],
                                  "cost_usd": round(cost(self.price, *reused), 6)},
        })


def run_zeroshot(cfg: ZeroShotConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction] | None:
    """The MethodSpec entry point; returns None for a dry run (run_predict then writes nothing)."""
    run = ZeroShotRun(cfg, ds)
    if cfg.dry_run:
        print_estimate(cfg, estimate_run(run, episodes))
        return None
    return run.run(episodes)


_DESCRIPTION = "zero-shot VLM prompting (DegustaBot {}: {} objects, {} arrangements)"
LOUMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("LOUMA", "language", "unmarked"))
LOGMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("LOGMA", "language", "grid-marked"))
MOUMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("MOUMA", "marked", "unmarked"))
MOGMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("MOGMA", "marked", "grid-marked"))
