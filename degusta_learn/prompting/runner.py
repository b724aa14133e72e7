"""The zero-shot predict method (louma, logma, mouma, mogma): prompts -> VLM -> parsed, aggregated plans.

Usage:
    export OPENAI_API_KEY=...
    degusta predict --config configs/zeroshot_mogma_gpt4o.yaml --dry-run     # requests + cost, calls nothing
    degusta predict --config configs/zeroshot_mogma_gpt4o.yaml
    degusta predict --config configs/zeroshot_mogma_local.yaml --set backend.base_url=http://127.0.0.1:8000/v1

For each episode the runner builds the method's prompt (main thread), looks every sample up in the
SQLite response cache, asks the backend for the missing ones on a bounded pool of daemon threads (retrying
rate limits, 408/409/5xx, timeouts -- a request has one deadline, backends/transport.py --, dropped
connections, replies refused for their size, 200s whose body is not a completion and, from a server, 200s
without an answer, with bounded exponential backoff + jitter, honouring Retry-After), commits each
response's answers to the cache the moment it is received (before parsing anything; an answer longer than
the parser reads is kept cut, with a note of its length), parses and aggregates the n answers (a bad item is
dropped and counted in `diagnostics.item_errors`; an answer with no valid item is a failed sample; model
text never raises), and finally writes predictions.jsonl (through `methods.run_predict`; every line fits
what `read_predictions` reads, `fit_line`) and `ledger.json` (tokens and dollars) beside it.

Ctrl-C or SIGTERM (`errors.Terminated`) stops the run at once: the requests in flight get
`INTERRUPT_GRACE_S` to land, a stalled one is left to its daemon thread, and the ledger of every request
already paid is written (the answers are in the cache already).

A run that could not get every answer writes NO predictions file and exits with a one-line
`DegustaError`: a `budget_usd` cap, a fatal API error (bad key), a server that kept failing (retries
exhausted: 5xx, unreachable, malformed bodies) for some episodes, or for several episodes in a row (then
it stops early). Finished answers stay cached, the ledger is written, and re-running the same command
asks only for the answers still missing. A request the server refuses for good (e.g. 400) is not a
server fault: its samples are counted failures of that episode, as unparseable answers are.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import queue
import random
import re
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

from tqdm import tqdm

from degusta_learn.errors import DegustaError, Terminated
from degusta_learn.files.guard import refuse_replacing_inputs
from degusta_learn.files.jsonio import MAX_LINE_BYTES, atomic_write_json, read_json
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.prompting.backends.base import (
    BackendConfig,
    BackendError,
    Completion,
    backend_class,
    backend_config,
    make_backend,
    redact,
    redact_json,
)
from degusta_learn.prompting.cache import ResponseCache, sample_keys
from degusta_learn.prompting.costs import CHARS_PER_TOKEN, BudgetExceeded, Ledger, cost
from degusta_learn.prompting.estimate import estimate_run, output_tokens_per_sample, print_estimate
from degusta_learn.render.grid import Grid
from degusta_learn.scene import Dataset, Episode, Prediction
from degusta_learn.task.aggregate import ANCHORED, combine, decoding_diagnostics
from degusta_learn.task.answer_format import answer_schema
from degusta_learn.task.answers import MAX_CHARS, AnswerParseError, answer_kind, is_repeat, read_answer
from degusta_learn.task.prompt import IMAGE_FORMATS, MODALITY_RENAMED, Prompt, build_prompt
from degusta_learn.vlm.settings import API_MAX_NEW_TOKENS, DecodingSettings, ModelSettings, check_api_settings

LEDGER_MARK = "degusta zero-shot ledger"
"""The `kind` of every ledger.json the runner writes: only such a file (or one with the keys of ledgers written
before the mark) is replaced by a later run."""
_LEDGER_KEYS = {"method", "backend", "model", "n", "episodes", "episodes_done", "cost_usd"}


def is_degusta_ledger(path: Path) -> bool:
    """Whether `path` is a ledger.json a zero-shot run wrote (a file holding the mark or the ledger keys)."""
    try:
        if not path.is_file() or path.stat().st_size > 2**20:
            return False
        data = read_json(path)
    except (OSError, DegustaError):
        return False
    return isinstance(data, dict) and (data.get("kind") == LEDGER_MARK or set(data) >= _LEDGER_KEYS)


@dataclass
class ZeroShotConfig(PredictConfig):
    """A zero-shot prompting run: the common predict keys plus which model answers (`model:`), how it decodes
    (`decoding:`), how it is reached (`backend:`) and run control."""

    backend: BackendConfig = field(default_factory=backend_config)
    """How the model is reached: `name` picks the backend, whose own keys the section then takes (docs/prompting.md)."""
    model: ModelSettings = field(default_factory=ModelSettings)
    """Which model answers (`name`: an API model id such as gpt-4o, or for hf a hub id / folder; empty: the backend's
    default, openai's gpt-4o); adapter, dtype and image_size are the hf backend's (a local model)."""
    decoding: DecodingSettings = field(default_factory=DecodingSettings)
    """n, aggregation, temperature, max_new_tokens (auto: hf sizes it from the dataset, an API backend takes
    API_MAX_NEW_TOKENS); constrained (null: true for hf, false for an API backend), on_repeat and report_unconstrained
    steer the hf backend's decoding. `aggregation` is applied to the stored answers, so changing it re-uses the
    response cache (greedy_votes_pooled asks only for the greedy answers a cache lacks)."""
    concurrency: int = 4
    """Requests in flight at once."""
    cache: str | None = None
    """SQLite response cache; unset: responses_cache.sqlite beside `out`; "off": no cache."""
    render_size: int = 448
    """Side in pixels the lifted images are rendered at (more pixels: more image tokens); a fine-tuned model's own."""
    image_format: str = "jpeg"
    """jpeg or png (the names in the prompt follow: final_state_1.jpg / .png)."""
    decoding_from: Literal["config", "adapter"] = "config"
    """config: decode as `decoding:` says (a warning names the keys where it differs from the validation decoding that
    selected `model.adapter`); adapter: decode exactly as that validation did (the `decoding` of the adapter's
    degusta_selection.json, replacing the `decoding:` section; hf backend, a best_adapter/ or best_model/ folder)."""
    prompt_style: Literal["clarified", "paper"] = "clarified"
    """The prompt's text (task.prompt.PROMPT_STYLES): clarified (the appendix prompt with cell naming, the object types,
    the coordinate convention and the placement-order request added) or paper (the appendix prompts verbatim)."""
    modality: Literal["images", "text", "both"] | None = None
    """How the context tables are shown (task.prompt.MODALITIES): images (the paper's prompt), text (each written in the
    answer format, the context images left out) or both; null: as the local model was trained (its degusta_finetune.json
    or degusta_base.json: `data.modality`), images for any other model. The same decoding and episodes in every
    modality: only the prompt changes. Predictions and the ledger record the one used."""
    grid: Grid = field(default_factory=Grid)
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

    RENAMED: ClassVar[dict[str, str]] = {"image_size": "render_size", "n": "decoding.n",
                                         "temperature": "decoding.temperature", "aggregation": "decoding.aggregation",
                                         "context_answers": MODALITY_RENAMED}

    def __post_init__(self):
        super().__post_init__()
        cls = backend_class(self.backend.name)
        if not cls.local_decoding:  # a service or a recorded file answers: the local model's keys are refused
            check_api_settings(self.model, self.decoding, self.backend.name)
        self.decoding = self.decoding.resolved(local=cls.local_decoding)
        if cls.local_decoding:  # the validation decoding that selected the adapter: compared, or taken (decoding_from)
            from degusta_learn.prompting.backends.hf import adapter_decoding

            self.decoding = adapter_decoding(self.model, self.decoding, self.decoding_from)
        elif self.decoding_from != "config":
            raise DegustaError(f"decoding_from: adapter reads a local model's adapter (backend.name: hf), not the "
                               f"{self.backend.name} backend's; set decoding_from: config")
        if not self.model.name:
            self.model = dataclasses.replace(self.model, name=cls.default_model)  # "": check_run says it is required
        checks = [("concurrency", self.concurrency >= 1, ">= 1"), ("render_size", self.render_size >= 64, ">= 64"),
                  ("max_retries", self.max_retries >= 0, ">= 0"), ("backoff", self.backoff >= 0, ">= 0"),
                  ("backoff_max", self.backoff_max >= 0, ">= 0"),
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


class _Unanswered(Exception):
    """An episode some of whose answers the server did not give (retries exhausted); asked again on re-run."""


_CUT = "\n[degusta: answer cut here; {n} characters in all, the first {keep} kept]"
_CUT_PATTERN = re.compile(r"\n\[degusta: answer cut here; (\d+) characters in all, the first (\d+) kept\]\Z")
LINE_BUDGET = MAX_LINE_BYTES // 2
"""The most bytes one prediction's JSON line may take (half what `read_predictions` reads, jsonio.MAX_LINE_BYTES):
past it the stored answers are cut further and the item errors listed are capped (`diagnostics.line_cut`)."""


def cut_answer(text: str, keep: int = MAX_CHARS) -> str:
    """`text` if it has at most `keep` characters, else its first `keep` and a note of its full length (the note
    of an answer cut before keeps the length it had when received)."""
    if len(text) <= keep:
        return text
    n = answer_length(text)
    m = _CUT_PATTERN.search(text)
    return (text[:m.start()] if m else text)[:keep] + _CUT.format(n=n, keep=keep)


def answer_length(text: str) -> int:
    """The length of an answer as received (its cut note says, if it was cut)."""
    m = _CUT_PATTERN.search(text) if len(text) > 80 else None
    return int(m.group(1)) if m else len(text)


def _sanitize(got) -> list[Completion]:
    """A backend's return value as a list of Completions with text and sane token counts (a bad reply
    from a server or a buggy backend becomes text that fails to parse, never an exception later). An answer of
    more than answers.MAX_CHARS characters (more than the parser reads) is cut to its first MAX_CHARS with a note
    of its length (`cut_answer`) here, before the cache, the predictions or anything else holds it."""
    from degusta_learn.prompting.cache import stored_count, stored_text

    if not isinstance(got, (list, tuple)):
        raise BackendError(f"the backend returned {type(got).__name__}, not a list of answers")
    out = []
    for c in got:
        decoding = getattr(c, "decoding", None)  # what a local model's decoding did (vlm.generate)
        text = getattr(c, "text", None)
        if isinstance(text, str) and len(text) > MAX_CHARS:
            text = cut_answer(text)
        out.append(Completion(text=stored_text(text), input_tokens=stored_count(getattr(c, "input_tokens", None)),
                              output_tokens=stored_count(getattr(c, "output_tokens", None)),
                              decoding=decoding if isinstance(decoding, dict) else None))
    return out


def fit_line(pred: Prediction, budget: int = LINE_BUDGET) -> Prediction:
    """`pred` with diagnostics small enough that its JSON line takes at most `budget` bytes, so the predictions
    file is always one `read_predictions` reads (many samples of long answers, escaped to 6-12 bytes a character,
    could pass jsonio.MAX_LINE_BYTES): first the item errors listed are capped at 100 (their count stays), then
    every stored answer is cut shorter (`cut_answer`), a quarter each round; `diagnostics.line_cut` says what was
    cut. Scores never change: the answers were parsed before."""
    size = len(json.dumps(pred.to_json()))
    if size <= budget:
        return pred
    d = pred.diagnostics
    note: dict = {"bytes_before": size}
    if len(d.get("item_errors") or []) > 100:
        d["item_errors"], note["item_errors_kept"] = d["item_errors"][:100], 100
    keep = MAX_CHARS
    while len(json.dumps(pred.to_json())) > budget and keep > 100:
        keep //= 4
        d["responses"] = [cut_answer(t, keep) if isinstance(t, str) else t for t in d.get("responses") or []]
        if isinstance(d.get("greedy_response"), str):
            d["greedy_response"] = cut_answer(d["greedy_response"], keep)
        note["responses_cut_to_chars"] = keep
    d["line_cut"] = note
    return pred


INTERRUPT_GRACE_S = 1.0
"""How long an interrupted run waits for the requests in flight (an answer arriving then is still cached and in the
ledger) before it writes the ledger and lets go: never longer, however stalled a server is."""


class _Workers:
    """The request threads of a run: daemons, so an interrupt (Ctrl-C, SIGTERM) never waits on a request that
    is stalled at a server (each ends by itself at its deadline, or with the process). `submit` returns a
    `concurrent.futures.Future`; `shutdown` cancels what has not started, then joins the threads, for at most
    `grace` seconds if given."""

    def __init__(self, n: int, name: str):
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._threads = [threading.Thread(target=self._work, name=f"{name}_{i}", daemon=True) for i in range(n)]
        self._queued: list[Future] = []
        for t in self._threads:
            t.start()

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        self._queued = [f for f in self._queued if not f.done() and not f.running()] + [fut]
        self._jobs.put((fut, fn, args))
        return fut

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            fut, fn, args = job
            if not fut.set_running_or_notify_cancel():  # cancelled while queued
                continue
            try:
                result = fn(*args)
            except BaseException as e:  # handed to the main thread, which raises or records it
                fut.set_exception(e)
            else:
                fut.set_result(result)

    def shutdown(self, grace: float | None = None) -> None:
        for fut in self._queued:
            fut.cancel()  # not started: never will
        for _ in self._threads:
            self._jobs.put(None)
        end = None if grace is None else time.monotonic() + grace
        try:
            for t in self._threads:
                t.join(None if end is None else max(0.0, end - time.monotonic()))
        except KeyboardInterrupt:  # a second Ctrl-C while waiting: stop waiting, the caller still keeps its books
            pass


class ZeroShotRun:
    """One run's state: backend, cache, ledger and the stop flag shared by the worker threads."""

    def __init__(self, cfg: ZeroShotConfig, ds: Dataset):
        from degusta_learn.render.lifting import Renderer

        self.cfg, self.ds = cfg, ds
        self.kind = answer_kind(self.answer_method)
        self.grid = Grid(cfg.grid.rows, cfg.grid.cols)
        self.renderer = Renderer.for_dataset(ds, size=cfg.render_size)
        self.out = Path(cfg.out)
        self.cache_path = None if cfg.cache == "off" else Path(cfg.cache or self.out.parent / "responses_cache.sqlite")
        # What the backend is, asked of its class (nothing is built, no model loaded, until `run`).
        self.backend_cls = backend_class(cfg.backend.name)
        self.price = self.backend_cls.price(cfg.backend, cfg.model, cfg.prices)  # None: a local backend, not priced
        # decoding.max_new_tokens: a number, or auto: an API backend's API_MAX_NEW_TOKENS now, hf's budget once the
        # model is loaded (`run`; a dry run keys its cache look-ups with "auto")
        asked = cfg.decoding.max_new_tokens
        self.max_tokens = asked if asked != "auto" or self.backend_cls.local_decoding else API_MAX_NEW_TOKENS
        self.per_sample = self.backend_cls.per_sample
        self.cacheable = self.backend_cls.cacheable
        self.est_out = cfg.est_output_tokens or output_tokens_per_sample(ds, self.kind, self.grid)
        # structured outputs: the schema the backend sends (it builds the same one from grid + catalog)
        self.schema = answer_schema(self.kind, ds.catalog, self.grid) if cfg.backend.structured_output else None
        self.schema_tokens = 0 if self.schema is None else math.ceil(len(json.dumps(self.schema)) / CHARS_PER_TOKEN)
        self.stop = threading.Event()
        self.reused = [0, 0]  # input, output tokens of cached answers (paid in an earlier run)
        self._reused_lock = threading.Lock()
        self.check_paths()

    @property
    def answer_method(self) -> str:
        """The prompting method whose answer format the answers take (task.answers.answer_kind; hf's token budget):
        the config's `method` (a method with a prompt of its own, such as text_llm, names the format it asks for)."""
        return self.cfg.method

    def check_paths(self) -> None:
        """Refuse, before any request, a run whose outputs would destroy an input or a user's file: the
        predictions `out` may not be the response cache or the ledger, the cache may not be the ledger,
        and an existing ledger.json beside `out` must be a degusta ledger (LEDGER_MARK or its keys)."""
        refuse_replacing_inputs(self.out, [("the response cache", self.cache_path),
                                           ("the ledger.json the run writes beside it", self.ledger_path)])
        if self.cache_path is not None:
            refuse_replacing_inputs(self.cache_path, [("the ledger.json the run writes beside `out`",
                                                        self.ledger_path)], key="cache")
        path = self.ledger_path
        if (path.exists() or path.is_symlink()) and not is_degusta_ledger(path):
            raise DegustaError(f"{path}: exists and is not a ledger degusta wrote (no {LEDGER_MARK!r} mark or "
                               "ledger keys); the zero-shot run writes its ledger.json beside `out`, so it is "
                               "left untouched and nothing was run: choose another `out` folder or move it")

    def input_tokens(self, prompt: Prompt) -> int:
        """Estimated input tokens of one request carrying `prompt` (with the answer schema it sends)."""
        return self.backend_cls.input_tokens(prompt, self.cfg.backend, self.cfg.model) + self.schema_tokens

    @functools.cached_property
    def trained_modality(self) -> str | None:
        """The modality the local model was trained with (`data.modality` in its record, `vlm.record`); None for a
        model without a record or a backend that runs no local model. Read when the first prompt is built, after
        `check_run` has read the same record."""
        if not self.backend_cls.local_decoding:
            return None
        from degusta_learn.vlm.hub import metadata_folder
        from degusta_learn.vlm.record import locate_record, read_record

        m = self.cfg.model
        path = locate_record(metadata_folder(m.adapter, "model.adapter", adapter=True),
                             metadata_folder(m.name, "model.name"))
        return read_record(path).prompt.modality if path is not None else None

    @property
    def modality(self) -> str:
        """The modality this run's prompts show: the config's, else the model's trained one, else images."""
        return self.cfg.modality or self.trained_modality or "images"

    def prompt(self, ep: Episode, style: str | None = None) -> tuple[Prompt, list[str]]:
        """The prompt of `ep` (its context tables shown as `modality`) and its samples' cache keys; `style` (default:
        the config's `prompt_style`) lets the dry run price the other prompt style."""
        c = self.cfg
        prompt = build_prompt(c.method, self.ds, ep, self.renderer, self.grid, c.image_format,
                              structured=c.backend.structured_output, style=style or c.prompt_style,
                              modality=self.modality)
        return prompt, self.keys(prompt)

    def keys(self, prompt: Prompt) -> list[str]:
        """The cache keys of `prompt`'s n samples (+ the greedy answer's, for an anchored aggregation)."""
        c = self.cfg
        d = c.decoding
        keys = sample_keys(prompt, c.backend, c.model, d, d.sampling_temperature, self.max_tokens, c.seed, d.n,
                           schema=self.schema)
        if d.aggregation in ANCHORED:  # + the greedy answer: the key a greedy run (n 1, temperature 0) gives it
            keys += sample_keys(prompt, c.backend, c.model, d, 0.0, self.max_tokens, c.seed, 1, schema=self.schema)
        if self.modality == "images" and self.trained_modality not in (None, "images"):
            # the images-only prompt of a model trained with text: before `modality`, the backend added the text to
            # this very prompt, so its key held answers to the trained prompt; this key is its own
            keys = [hashlib.sha256(f"{k}\0modality=images".encode()).hexdigest() for k in keys]
        return keys

    def lookup(self, keys: list[str]) -> dict[str, Completion]:
        """The cached answers of `keys` (none without a cache), counted in the ledger (`samples_cached`) and in the
        tokens reused from earlier runs (any thread)."""
        hits = self.cache.get_many(keys) if self.cache else {}
        self.ledger.count("samples_cached", len(hits))
        with self._reused_lock:
            for h in hits.values():
                self.reused[0] += h.input_tokens or 0
                self.reused[1] += h.output_tokens or 0
        return hits

    # ------------------------------------------------------------------------- requests

    def sleep(self, seconds: float) -> None:
        """Wait between retries (interrupted by a stop); tests replace it or set backoff 0."""
        self.stop.wait(seconds)

    def request(self, prompt: Prompt, k: int, seed: int | None, keys: list[str] | None = None,
                episode: str | None = None, temperature: float | None = None, max_tokens: int | None = None,
                est_out: int | None = None) -> list[Completion]:
        """Ask for k samples, retrying transient errors; raises BudgetExceeded, _Stopped or BackendError.
        `max_tokens` and `est_out` (output tokens a sample is assumed to take) default to the run's.

        The answers are committed to the cache under `keys` the moment they are received, before the
        ledger, parsing or aggregation touch them (the smallest window a kill can lose a paid answer in).
        """
        c = self.cfg
        est_in = self.input_tokens(prompt) * (k if self.per_sample else 1)
        per_sample_out = self.est_out if est_out is None else est_out
        est_out = per_sample_out * k
        est_usd = cost(self.price, est_in, est_out)
        for attempt in range(c.max_retries + 1):
            if self.stop.is_set():
                raise _Stopped()
            self.ledger.reserve(est_usd)
            try:
                try:
                    got = _sanitize(self.backend.complete(prompt, k, c.decoding.sampling_temperature
                                                          if temperature is None else temperature,
                                                          self.max_tokens if max_tokens is None else max_tokens,
                                                          seed))
                except (BackendError, DegustaError, KeyboardInterrupt):
                    raise
                except Exception as e:  # a client library's own exception, a local model's OOM: stop cleanly
                    raise BackendError(f"{c.backend.name}: {type(e).__name__}: {str(e)[:300]}", fatal=True) from None
                got = self.received(got, keys, episode, est_in, per_sample_out)
            except BackendError as e:
                self.ledger.release(est_usd)
                if e.fatal or not e.retryable or attempt == c.max_retries:
                    if not e.fatal:
                        self.ledger.count("failed_requests")
                    raise
                delay = c.backoff * 2 ** min(attempt, 30) * (0.5 + random.random())
                if e.retry_after is not None:
                    delay = e.retry_after * (1.0 + 0.1 * random.random())
                self.ledger.count("retries")
                self.sleep(max(0.0, min(c.backoff_max, delay)))  # never longer than backoff_max
                continue
            except BaseException:
                self.ledger.release(est_usd)
                raise
            self.ledger.release(est_usd)
            return got
        raise AssertionError("unreachable")

    def received(self, got: list[Completion], keys: list[str] | None, episode: str | None,
                 est_in: int, est_out: int | None = None) -> list[Completion]:
        """Keep a reply: its answers committed to the cache first, then the request in the ledger (paid, whatever
        it holds). A reply without an answer from a backend whose empty answers are the server's (`empty_is_fault`:
        no choices, a null message, empty or blank text) raises a retryable BackendError, retried as any server
        fault; the empty answers of a reply that also holds others are dropped (the runner asks again for them)."""
        fault = self.backend_cls.empty_is_fault
        answered = [c for c in got if c.text.strip()] if fault else got
        if self.cache is not None and keys is not None:
            self.cache.put_many(list(zip(keys, answered)), episode)  # committed before anything else
        ins = [x.input_tokens for x in got]
        outs = [x.output_tokens for x in got]
        unknown = fault and not got  # a server's reply without choices (nor usage): the input it was sent is billed
        self.ledger.record(None if unknown or None in ins else sum(ins), None if unknown or None in outs else sum(outs),
                           len(answered), fallback=(est_in, (self.est_out if est_out is None else est_out) * len(got)))
        if fault and (len(answered) < len(got) or not got):
            self.ledger.count("empty_answers", len(got) - len(answered) if got else 1)
        if fault and not answered:
            what = "no choices" if not got else "an empty answer"
            raise BackendError(f"{self.cfg.backend.name}: {self.cfg.model.name} answered 200 with {what} (no "
                               "choices / content / candidates, a null message or blank text): a server fault",
                               retryable=True)
        return answered

    def episode(self, ep: Episode, prompt: Prompt, keys: list[str], hits: dict[str, Completion]) -> Prediction:
        """Fetch the missing samples of one episode, then parse and aggregate all n (worker thread).

        Raises _Unanswered when the server kept failing (retries exhausted) for some sample: the episode
        is left for a re-run instead of being written as failed.
        """
        c = self.cfg
        samples: list[Completion | None] = [hits.get(k) for k in keys]
        reasons: dict[int, str] = {}
        n = c.decoding.n
        self.fetch(ep, prompt, keys, samples, reasons, list(range(n)), c.decoding.sampling_temperature)
        if len(keys) > n:  # greedy_votes_pooled: the greedy answer, asked apart at temperature 0
            self.fetch(ep, prompt, keys, samples, reasons, [n], 0.0)
        return self.predict(ep, samples, reasons, cached=len(hits))

    def fetch(self, ep: Episode, prompt: Prompt, keys: list[str], samples: list, reasons: dict[int, str],
              indices: list[int], temperature: float, max_tokens: int | None = None,
              est_out: int | None = None) -> None:
        """Ask for the samples `indices` that `samples` lacks, at `temperature`, into `samples` (or `reasons`);
        `max_tokens` and `est_out` as `request` takes them."""
        c = self.cfg
        missing = [i for i in indices if samples[i] is None]
        while missing:
            seed = None if c.seed is None else c.seed + missing[0] - indices[0]  # the anchor: a greedy run's seed
            ask = missing[:1] if self.per_sample else missing  # per-sample APIs: each answer cached at once
            try:
                got = self.request(prompt, len(ask), seed, [keys[i] for i in ask], ep.id, temperature,
                                   max_tokens, est_out)
            except BudgetExceeded:
                self.stop.set()  # at once, so no other worker starts a request
                raise
            except BackendError as e:
                if e.fatal:
                    self.stop.set()
                    raise
                if e.retryable:  # retries exhausted: a server fault, not an answer
                    raise _Unanswered(str(e)) from None
                for i in missing:
                    reasons[i] = f"request failed: {e}"
                break
            got = got[:len(ask)]
            if not got:
                for i in missing:
                    reasons[i] = "the backend returned no answer"
                break
            for i, comp in zip(ask, got):
                samples[i] = comp
            missing = [i for i in missing if samples[i] is None]
            if not self.cacheable:  # e.g. replay: one look-up, whatever is missing stays missing
                for i in missing:
                    reasons[i] = "no recorded answer"
                break

    def predict(self, ep: Episode, samples: list[Completion | None], reasons: dict[int, str],
                cached: int) -> Prediction:
        parsed = []
        item_errors: list[dict] = []
        n_items = 0
        for i, s in enumerate(samples):
            if s is None:
                parsed.append(None)
                continue
            if len(s.text) > MAX_CHARS:  # cut when received (or cached whole by an older version): not read
                reasons[i] = (f"unparseable answer: {answer_length(s.text)} characters long (at most {MAX_CHARS} "
                              "are read; the first are kept in the responses)")
                parsed.append(None)
                continue
            try:
                answer = read_answer(s.text, self.kind, self.ds.catalog, self.grid)
            except AnswerParseError as e:
                reasons[i] = f"unparseable answer: {e}"
                parsed.append(None)
                continue
            parsed.append(answer.items)
            n_items += answer.n_read
            item_errors += [{"sample": i, "reason": r} for r in answer.item_errors]
        n = self.cfg.decoding.n
        anchor = parsed[n] if len(parsed) > n else None
        placements, agg = combine(parsed[:n], self.kind, self.grid, self.cfg.decoding.aggregation, anchor=anchor)
        kept = [cut_answer(s.text) if s else None for s in samples]  # bounded, whatever a cache holds
        diag = {"backend": self.cfg.backend.name, "model": self.cfg.model.name, "prompt_style": self.cfg.prompt_style,
                "modality": self.modality, "n": n, "cached": cached, "responses": kept[:n],
                **({"greedy_response": kept[n]} if len(samples) > n else {}),
                "failures": [{"sample": i, "reason": r} for i, r in sorted(reasons.items())],
                "n_items": n_items, "n_item_errors": len(item_errors), "item_errors": item_errors,
                "n_item_repeats": sum(is_repeat(e["reason"]) for e in item_errors), **agg}
        decoding = decoding_diagnostics(samples, self.kind, self.ds.catalog, self.grid)  # local models only
        if decoding:
            diag["decoding"] = {"max_new_tokens": self.max_tokens, **decoding}
        return fit_line(Prediction(episode=ep.id, participant=ep.participant, target=ep.target,
                                   method=self.cfg.method, placements=placements, failed=agg["failed"],
                                   diagnostics=redact_json(diag)))

    # ------------------------------------------------------------------------- the run

    def run(self, episodes: list[Episode]) -> list[Prediction]:
        c = self.cfg
        # before the model loads: hf refuses train/test leakage and a render size other than the trained one
        backend_class(c.backend.name).check_run(c.backend, c.model, self.ds, episodes, c.render_size)
        _ = self.modality  # the model's record read once, before the model loads (the ledger names the modality)
        self.backend = make_backend(c.backend, c.model, c.decoding, self.grid, self.ds.catalog)
        if self.max_tokens == "auto":  # hf: what the dataset's answers take with the model's tokenizer
            self.max_tokens = self.backend.token_budget(self.ds, self.answer_method)["max_new_tokens"]
        self.cache = ResponseCache(self.cache_path) if self.cache_path and self.cacheable else None
        self.ledger = Ledger(self.price, c.budget_usd)
        results: dict[str, Prediction] = {}
        unanswered: dict[str, str] = {}  # episode id -> the last server error
        streak = [0]  # episodes in a row the server failed (reset by any answered episode)
        give_up = max(3, c.concurrency + 1)
        stopped: str | None = None
        self.reused = reused = [0, 0]  # tokens of cached answers (paid in an earlier run; `lookup` counts them)
        start = time.time()
        todo = iter(episodes)
        bar = tqdm(total=len(episodes), desc=f"{c.method} {c.model.name}", unit="ep", disable=None)
        pool = _Workers(c.concurrency, "degusta-zeroshot")
        pending: dict = {}
        interrupted = False

        def submit_next() -> bool:
            ep = next(todo, None)
            if ep is None:
                return False
            prompt, keys = self.prompt(ep)
            hits = self.lookup(keys)
            pending[pool.submit(self.episode, ep, prompt, keys, hits)] = ep
            return True

        try:
            while len(pending) < 2 * c.concurrency and submit_next():
                pass
            while pending:
                # polled: a signal is handled at once on every platform, whatever the workers are waiting on
                done, _ = wait(list(pending), timeout=0.5, return_when=FIRST_COMPLETED)
                for fut in done:
                    ep = pending.pop(fut)
                    try:
                        results[ep.id] = fut.result()
                        streak[0] = 0
                        bar.update(1)
                    except _Stopped:
                        pass
                    except _Unanswered as e:
                        unanswered[ep.id] = str(e)
                        streak[0] += 1
                        bar.update(1)
                        if streak[0] >= give_up and not self.stop.is_set():
                            stopped = stopped or (f"server: {streak[0]} episodes in a row got no answer "
                                                  f"(last error: {e})")
                            self.stop.set()
                    except BudgetExceeded as e:
                        stopped = stopped or f"budget: {e}"
                        self.stop.set()
                    except (BackendError, DegustaError) as e:  # fatal (bad key, unknown model), cache write
                        stopped = stopped or f"error: {e}"
                        self.stop.set()
                bar.set_postfix_str(f"${self.ledger.summary()['cost_usd']:.4f}")
                while not self.stop.is_set() and len(pending) < 2 * c.concurrency and submit_next():
                    pass
        except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (errors.Terminated): keep what was paid, wait for nothing
            self.stop.set()
            interrupted = True
            stopped = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
            raise
        finally:
            # interrupted: requests in flight get INTERRUPT_GRACE_S to land, then are left to their daemon threads
            pool.shutdown(INTERRUPT_GRACE_S if interrupted else None)
            bar.close()
            try:
                self.write_ledger(episodes, results, unanswered, stopped, time.time() - start, reused)
            finally:
                if self.cache is not None:
                    self.cache.close()  # every answer received is already committed; this only lets go of the file
        if stopped or unanswered:
            raise DegustaError(redact(self.incomplete_message(episodes, results, unanswered, stopped)))
        return [results[ep.id] for ep in episodes]

    def incomplete_message(self, episodes, results, unanswered, stopped) -> str:
        """One line: why the run is incomplete, what is kept, and that a re-run asks only for what is missing."""
        total, done = len(episodes), len(results)
        if stopped:
            head = f"zero-shot run stopped ({stopped}) after {done} of {total} episodes"
        else:
            last = next(reversed(unanswered.values()))
            head = (f"zero-shot run incomplete: {len(unanswered)} of {total} episodes got no answer from the "
                    f"server after {self.cfg.max_retries} retries (last error: {last})")
        if self.cache is not None:
            keep = (f"answers received are cached in {self.cache_path} and the spend is in {self.ledger_path}; "
                    f"re-run the same command to ask only for the {total - done} unfinished episodes")
        else:
            keep = (f"the spend is in {self.ledger_path}; the cache is off, so a re-run asks for every "
                    "episode again")
        return f"{head}; {keep} (nothing was written to {self.out})"

    @property
    def ledger_path(self) -> Path:
        """ledger.json beside `out` (it names `out`: `degusta compare` claims each method's as its own file)."""
        return self.out.parent / "ledger.json"

    def write_ledger(self, episodes, results, unanswered, stopped, wall_s, reused) -> None:
        c = self.cfg
        summary = self.ledger.summary()
        diags = [p.diagnostics for p in results.values()]
        atomic_write_json(self.ledger_path, redact_json({
            "kind": LEDGER_MARK, "method": c.method, "out": str(self.out), "backend": c.backend.name,
            "model": c.model.name,
            "base_url": getattr(c.backend, "base_url", None),  # null: a backend that calls no server (hf, replay)
            "structured_output": c.backend.structured_output, "prompt_style": c.prompt_style,
            "modality": self.modality,
            "n": c.decoding.n, "aggregation": c.decoding.aggregation, "episodes": len(episodes), "episodes_done": len(results),
            "episodes_failed": sum(p.failed for p in results.values()),
            "episodes_unanswered": len(unanswered), "stopped": stopped,
            "items_read": sum(d.get("n_items", 0) for d in diags),
            "item_errors": sum(d.get("n_item_errors", 0) for d in diags),
            "wall_s": round(wall_s, 3), "cache": str(self.cache_path) if self.cache is not None else None,
            **summary,
            "cost_usd_per_episode": round(summary["cost_usd"] / max(1, len(results)), 6),
            "reused_from_cache": {"input_tokens": reused[0], "output_tokens": reused[1],
                                  "cost_usd": round(cost(self.price, *reused), 6)},
            **self.ledger_extra(results),
        }))

    def ledger_extra(self, results: dict[str, Prediction]) -> dict:
        """Keys a method with a prompt of its own adds to ledger.json (text_llm: its two steps); none here."""
        return {}


def run_zeroshot(cfg: ZeroShotConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction] | None:
    """The MethodSpec entry point; returns None for a dry run (run_predict then writes nothing)."""
    run = ZeroShotRun(cfg, ds)
    if cfg.dry_run:  # a dry run refuses what the real run would refuse (leakage, render size) before estimating
        backend_class(cfg.backend.name).check_run(cfg.backend, cfg.model, ds, episodes, cfg.render_size)
        print_estimate(cfg, estimate_run(run, episodes))
        return None
    from degusta_learn.files.locks import hold

    with hold(run.ledger_path, "zero-shot ledger"):  # a second run writing the same ledger and predictions: refused
        return run.run(episodes)


_DESCRIPTION = "zero-shot VLM prompting (DegustaBot {}: {} objects, {} arrangements)"
LOUMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("LOUMA", "language", "unmarked"))
LOGMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("LOGMA", "language", "grid-marked"))
MOUMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("MOUMA", "marked", "unmarked"))
MOGMA = MethodSpec(ZeroShotConfig, run_zeroshot, _DESCRIPTION.format("MOGMA", "marked", "grid-marked"))
