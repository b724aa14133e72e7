"""`degusta compare`: several methods on the same episodes -> one report folder.

Usage:
    degusta compare --config configs/compare_naturalistic.yaml
    degusta compare --config configs/compare_naturalistic.yaml --set "contexts=[4]" --set out=runs/cmp_k4

A compare config lists methods; each is either an existing predictions file or a predict config that
is run (once per context length, into `<out>/predictions/`). Beside each file it runs, compare records a
fingerprint (`NAME_kK.fingerprint.json`: hashes of the method's resolved config and the files it names,
of the dataset's files, of the episodes, and of the predictions file itself). A file is reused only while
its fingerprint matches, so an interrupted comparison resumes and a changed config or dataset is never
scored from stale predictions: a local method is recomputed (logged); a method that calls a remote API
(openai, anthropic, gemini backends) is refused up front, before anything runs, with a message saying
to delete the file (answers already in the response cache are reused, not paid again). Method names are
safe file names (letters, digits, `.`, `_`, `-`), so nothing is written outside `out`.
A zero-shot method's run leaves its ledger (paid requests) beside its file, as `NAME_kK.ledger.json` (never one
ledger.json shared by every method), and what its ledgers say it cost (USD, requests, tokens) joins its entry in
`metrics.json` (`cost_usd_total`, `requests`, `cost`) and the report's cost table.
Every method must cover exactly the same episodes, and every record must agree with its episode
(scoring.check_records): otherwise the whole comparison is refused, naming the file, line and field. A method whose run fails, or whose every
prediction failed, is reported as failed; the rest of the report is written, and `compare` returns a
`Comparison` naming the failed methods (`degusta compare` then exits 3). When every method failed, compare
exits with an error (exit 2) and writes no report.
The report lists the methods best first by mean set RMSD, degenerate methods last and marked
(evaluate/summary.py, docs/metrics.md); the paired comparisons and the qualitative reference follow
that order.

Writes `<out>/report.md`, `report.html` (opens without a server), `metrics.json`, `per_episode.csv`,
`plots/*.png` and `qualitative/*.png` as one set ((`files.folders`)): a failure leaves the previous
report as it was, and `predictions/` is carried over.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal


from degusta_learn.config import bounded, load_config, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.scoring import METHOD_NAME, EpisodeRow, check_records, score_predictions
from degusta_learn.evaluate.summary import paired_comparisons, rank_methods, summarize
from degusta_learn.files.folders import OutputKind, check_target, write_folder
from degusta_learn.files.guard import refuse_replacing_inputs
from degusta_learn.files.identity import file_sha256, stat_tree
from degusta_learn.files.jsonio import atomic_write_json, read_json
from degusta_learn.files.locks import hold
from degusta_learn.metrics import acceptability_curve
from degusta_learn.metrics.bootstrap import MAX_RESAMPLES
from degusta_learn.metrics.matching import check_matching
from degusta_learn.prompting.backends.base import backend_class
from degusta_learn.render.lifting import MAX_IMAGE_SIZE, MIN_IMAGE_SIZE
from degusta_learn.scene import (
    CONTEXT_LENGTHS,
    Dataset,
    Episode,
    Prediction,
    load_dataset,
    make_episodes,
    read_episodes,
    read_predictions,
    write_predictions,
)
from degusta_learn.scene.dataset import dataset_identity  # also what fine-tuned adapters record
from degusta_learn.shipped import resolve_or_keep
from degusta_learn.textsafe import MESSAGE_LIMIT, one_line


class EpisodeSetMismatch(DegustaError):
    """A method's predictions cover other episodes than the comparison's: the whole comparison is refused."""


class InconsistentRecords(DegustaError):
    """A predictions file contradicts its episodes (scoring.check_records): the whole comparison is refused."""


COMPARISON = OutputKind("comparison report", ("report.md", "report.html", "metrics.json", "per_episode.csv",
                                              "plots", "qualitative", "predictions"))
"""What `degusta compare` writes into `out` (as one set; `predictions/` is carried over)."""

MAX_QUALITATIVE = 100
"""Most random qualitative episodes a comparison draws (each is one image per method)."""


COMPARISON_KEYS = ("dataset", "seed", "split", "episodes", "context", "out")
"""Predict keys `compare` gives every method run itself (a method's `set` may not)."""


@dataclass
class MethodEntry:
    """One row of the comparison: a predictions file, or a predict config to run."""

    name: str
    """Label of the method in the report."""
    predictions: str | None = None
    """An existing predictions.jsonl covering the comparison's episodes."""
    config: str | None = None
    """A `degusta predict` config, run for every context length of the comparison."""
    set: list[str] = field(default_factory=list)
    """Overrides for `config` (like --set key=value)."""

    def __post_init__(self):
        if not isinstance(self.name, str) or not METHOD_NAME.fullmatch(self.name):
            raise DegustaError(f"methods: name {self.name!r}: expected a safe name (letters, digits, '.', '_', '-'; "
                               "starting with a letter or digit; at most 80 characters): it names files under "
                               "<out>/predictions/")
        if (self.predictions is None) == (self.config is None):
            raise DegustaError(f"methods entry {self.name!r}: give exactly one of 'predictions' or 'config'")
        if isinstance(self.config, str):  # a shipped name (or configs/NAME.yaml outside a checkout) works too
            self.config = resolve_or_keep(self.config)
        for item in self.set:  # these the comparison sets for every method (_runs): an override was lost silently
            key = str(item).split("=", 1)[0].strip()
            if key in COMPARISON_KEYS:
                raise DegustaError(f"methods entry {self.name!r}: set: {key!r} is the comparison's own (every method "
                                   "runs on its dataset, seed, split, episodes or context lengths and writes under "
                                   "its out): set it at the top level of the compare config")


@dataclass
class CompareConfig:
    """A comparison of several methods on one episode set."""

    dataset: str
    """Dataset folder."""
    out: str
    """Report folder."""
    methods: list[MethodEntry]
    """The methods; the report ranks them by mean set RMSD (degenerate ones last), this order breaks ties."""
    contexts: list[int] = field(default_factory=lambda: list(CONTEXT_LENGTHS))
    """Context lengths to build episodes for (ignored when `episodes` is set)."""
    split: Literal["train", "val", "test", "all"] = "test"
    """Participant split of the episodes."""
    episodes: str | None = None
    """A fixed episodes.jsonl instead of `contexts` + `split`."""
    seed: int = seed_field(0)
    """Seed of the split, bootstrap and the random qualitative episodes (0 .. 2**32 - 1)."""
    n_bootstrap: int = bounded(1000, 1, MAX_RESAMPLES)
    """Bootstrap resamples of the intervals (more: tighter estimates of the interval, slower; 1 .. 1,000,000)."""
    qualitative: int = bounded(3, 0, MAX_QUALITATIVE)
    """Random episodes drawn side by side (plus the best and worst episode of the top-ranked method; 0 .. 100)."""
    render_size: int = bounded(256, MIN_IMAGE_SIZE, MAX_IMAGE_SIZE)
    """Pixel size the qualitative panels' scenes are rendered at (64 .. 4096)."""
    title: str = "Comparison report"
    matching: Literal["hungarian", "paper"] = "hungarian"
    """How predicted objects are paired with true ones before scoring: "hungarian" (least total Hamming distance)
    or "paper" (the paper's greedy rule); docs/metrics.md, "Matching: ours and the paper's"."""
    resample: Literal["participants", "episodes"] = "participants"
    """What the bootstrap intervals and paired tests resample: "participants" (each with all of its episodes: episodes
    of one person are not independent) or "episodes" (one by one, the older per-episode intervals); every report
    says which."""

    RENAMED: ClassVar[dict[str, str]] = {"image_size": "render_size"}

    def __post_init__(self):
        check_matching(self.matching)  # the loader checks the Literal; a config built in Python is checked here
        if not self.methods:
            raise DegustaError("methods: expected at least one method")
        names = [m.name for m in self.methods]
        if len(set(names)) != len(names):
            raise DegustaError(f"methods: duplicate method name in {names}")
        bad = [k for k in self.contexts if k not in CONTEXT_LENGTHS]
        if bad:
            raise DegustaError(f"contexts: expected values in {list(CONTEXT_LENGTHS)}, got {bad}")
        if not self.episodes:
            if not self.contexts:
                raise DegustaError(f"contexts: expected at least one context length (from {list(CONTEXT_LENGTHS)}), "
                                   "got []; or set episodes")
            twice = sorted({k for k in self.contexts if self.contexts.count(k) > 1})
            if twice:
                raise DegustaError(f"contexts: context length {twice[0]} is given twice in {self.contexts}; "
                                   "give each length once")


@dataclass(frozen=True)
class Comparison:
    """What `compare` wrote: the report folder, and the methods that failed with their reasons (in config order;
    the report lists them too). Empty `failures`: every method was scored."""

    out: Path
    """The report folder (report.md, report.html, metrics.json, ...)."""
    failures: dict[str, str] = field(default_factory=dict)
    """Method name -> why it failed (the DegustaError's message)."""
    methods: int = 0
    """How many methods the comparison had (scored + failed)."""

    @property
    def failed(self) -> list[str]:
        """The names of the methods that failed."""
        return list(self.failures)

    def failure_summary(self) -> str:
        """One line naming the failed methods ("" when none failed)."""
        if not self.failures:
            return ""
        return (f"{len(self.failures)} of {self.methods} methods failed: {', '.join(self.failures)}; the report "
                f"lists why and scores the rest: {self.out / 'report.md'}")


def run_compare(path: str | Path, overrides: list[str] | None = None, log=print) -> Comparison:
    return compare(load_config(CompareConfig, path, overrides), log=log, config_path=path)


def comparison_episodes(cfg: CompareConfig, ds: Dataset) -> list[Episode]:
    if cfg.episodes:
        return read_episodes(cfg.episodes, ds)
    return [e for k in cfg.contexts for e in make_episodes(ds, k, cfg.split, cfg.seed)]


def _runs(entry: MethodEntry, cfg: CompareConfig, pred_dir: Path) -> list[tuple[int | None, list[str], Path]]:
    """(context length, predict overrides, predictions file) of each run of a config method."""
    runs = [(None, [f"episodes={cfg.episodes}", "context=null"])] if cfg.episodes else \
        [(k, ["episodes=null", f"context={k}", f"split={cfg.split}"]) for k in cfg.contexts]
    out = []
    for k, keys in runs:
        path = pred_dir / (f"{entry.name}_k{k}.jsonl" if k is not None else f"{entry.name}_episodes.jsonl")
        out.append((k, [*entry.set, f"dataset={cfg.dataset}", f"seed={cfg.seed}", *keys, f"out={path}"], path))
    return out


def fingerprint_path(predictions: Path) -> Path:
    return predictions.with_name(predictions.stem + ".fingerprint.json")


def ledger_path(predictions: Path) -> Path:
    """The ledger of the run that wrote `predictions` (NAME_kK.ledger.json beside NAME_kK.jsonl)."""
    return predictions.with_name(predictions.stem + ".ledger.json")


def _ledger_for(path: Path, out: Path) -> bool:
    """Whether `path` is a ledger a zero-shot run wrote for the predictions file `out` (its `out` field)."""
    from degusta_learn.prompting.runner import is_degusta_ledger

    try:
        return is_degusta_ledger(path) and Path(str(read_json(path).get("out"))).resolve() == out.resolve()
    except (OSError, DegustaError, ValueError):
        return False


def claim_ledger(out: Path) -> None:
    """Move the ledger.json a zero-shot run just wrote beside `out` to `ledger_path(out)`, the run's own: every
    method of a comparison writes its predictions into one folder, and a ledger.json there would keep only the
    last run's requests. Called however the run ended (done, failed, interrupted); a ledger.json written for
    another file (or not by degusta) is left where it is."""
    shared = out.parent / "ledger.json"
    if _ledger_for(shared, out):
        with contextlib.suppress(OSError):  # else left as ledger.json: the run's outcome matters more than the move
            os.replace(shared, ledger_path(out))


def method_cost(ledgers: list[Path], n_episodes: int) -> dict | None:
    """What the ledgers of one method's runs say it cost (None: it kept none, e.g. a local method): USD spent by
    the runs (`cost_usd`), USD of the cached answers they reused (paid by an earlier run: `cost_usd_reused`),
    their sum (`cost_usd_total`, per episode too), requests, retries, failed requests and tokens."""
    from degusta_learn.prompting.runner import is_degusta_ledger

    found = []
    for path in ledgers:
        try:
            if is_degusta_ledger(path):
                found.append((path, read_json(path)))
        except (OSError, DegustaError):  # gone or garbled since: that run's cost is unknown, the report stays
            continue
    if not found:
        return None

    def total(key, sub=None) -> float:
        values = [(d.get(sub) or {}).get(key) if sub else d.get(key) for _, d in found]
        return sum(v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0)

    spent, reused = total("cost_usd"), total("cost_usd", "reused_from_cache")
    tokens = total("input_tokens") + total("output_tokens")
    tokens += total("input_tokens", "reused_from_cache") + total("output_tokens", "reused_from_cache")
    return {"cost_usd": round(spent, 6), "cost_usd_reused": round(reused, 6), "cost_usd_total": round(spent + reused, 6),
            "cost_usd_per_episode": round((spent + reused) / max(1, n_episodes), 6),
            "tokens_per_episode": round(tokens / max(1, n_episodes), 1), "requests": int(total("requests")),
            "retries": int(total("retries")), "failed_requests": int(total("failed_requests")),
            "ledgers": [str(p) for p, _ in found]}


# Keys that change how a run goes, not what it answers: a change never makes predictions stale.
_RUN_CONTROL = {"out", "dataset", "episodes", "cache", "dry_run", "concurrency", "budget_usd", "max_retries",
                "backoff", "backoff_max", "prices", "est_output_tokens", "timeout", "api_key_env"}


def _sha(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def _resolved(value, files: dict, key: str = ""):
    """The config without run-control keys; every string naming an existing path adds its file identity."""
    if isinstance(value, dict):
        return {k: _resolved(v, files, f"{key}.{k}" if key else str(k)) for k, v in value.items()
                if str(k) not in _RUN_CONTROL}
    if isinstance(value, (list, tuple)):
        return [_resolved(v, files, key) for v in value]
    if isinstance(value, str) and value and len(value) < 4096:
        try:
            path = Path(value)
            if path.exists():
                files[key] = stat_tree(path)
        except (OSError, ValueError):
            pass
    return value


def run_fingerprint(entry: MethodEntry, overrides: list[str], ds_id: str, episodes: list[Episode]) -> tuple[dict, bool]:
    """(fingerprint parts, whether the method may call a paid remote API) of one run of a config method."""
    from degusta_learn.methods import build_config, get_method

    _, mcfg = build_config(entry.config, overrides, "method", get_method)
    files: dict = {}
    config = _resolved(dataclasses.asdict(mcfg), files)
    backend = getattr(mcfg, "backend", None)
    # a backend whose answers may cost money (not local, as it declares): stale predictions are refused,
    # never silently recomputed
    remote = backend is not None and not backend_class(backend.name).is_local(backend)
    return {"config": _sha(config), "files": _sha(files), "dataset": ds_id,
            "episodes": _sha([e.to_json() for e in episodes])}, remote


def stale_reason(predictions: Path, parts: dict) -> str | None:
    """Why an existing predictions file may not be reused (None: reuse it)."""
    record_path = fingerprint_path(predictions)
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return f"there is no {record_path.name} saying what produced it"
    except (OSError, ValueError, RecursionError):
        return f"{record_path.name} is unreadable"
    if not isinstance(record, dict) or not isinstance(record.get("parts"), dict):
        return f"{record_path.name} is malformed"
    changed = [k for k in parts if record["parts"].get(k) != parts[k]]
    if changed:
        what = {"config": "config", "files": "version of a file its config names (e.g. a checkpoint)",
                "dataset": "dataset", "episodes": "episode set"}
        return "it was produced with another " + " and ".join(what.get(k, k) for k in changed)
    if record.get("predictions_sha256") != file_sha256(predictions):
        return "it was changed after it was produced"
    return None


def _episodes_of_run(cfg: CompareConfig, ds: Dataset, episodes: list[Episode], k: int | None) -> list[Episode]:
    return episodes if k is None else make_episodes(ds, k, cfg.split, cfg.seed)


def check_stale_paid(cfg: CompareConfig, ds: Dataset, episodes: list[Episode], pred_dir: Path, ds_id: str) -> None:
    """Before anything runs: refuse stale predictions of a paid method (recomputing would spend money)."""
    for entry in cfg.methods:
        if entry.config is None:
            continue
        for k, overrides, path in _runs(entry, cfg, pred_dir):
            if not path.exists():
                continue
            try:
                parts, remote = run_fingerprint(entry, overrides, ds_id, _episodes_of_run(cfg, ds, episodes, k))
            except DegustaError:
                continue  # reported as that method's failure when it runs
            why = stale_reason(path, parts) if remote else None
            if why:
                raise DegustaError(
                    f"{path}: not reused because {why}; method {entry.name!r} calls a paid API, so compare does not "
                    "recompute it silently: delete that file to recompute (answers already in the response cache "
                    "are reused, not paid again), or restore the config and dataset that produced it")


def _run_config(entry: MethodEntry, cfg: CompareConfig, ds: Dataset, episodes: list[Episode], pred_dir: Path,
                ds_id: str, log) -> list[Path]:
    from degusta_learn.methods import run_predict

    paths = []
    for k, overrides, out in _runs(entry, cfg, pred_dir):
        parts, remote = run_fingerprint(entry, overrides, ds_id, _episodes_of_run(cfg, ds, episodes, k))
        why = stale_reason(out, parts) if out.exists() else "missing"
        if why is None:
            log(f"[compare] {entry.name}: reusing {out}")
        else:
            if why != "missing":
                if remote:  # check_stale_paid refused this up front; the file changed since
                    raise DegustaError(f"{out}: not reused because {why}; delete it to recompute "
                                       "(cached answers are not paid again)")
                log(f"[compare] {entry.name}: {out} is stale ({why}): recomputing")
            log(f"[compare] {entry.name}: predicting" + (f" (context {k})" if k is not None else ""))
            try:
                run_predict(entry.config, overrides)
            finally:  # this run's ledger (paid requests), however it ended, is its own file
                claim_ledger(out)
            atomic_write_json(fingerprint_path(out), {"parts": parts, "predictions_sha256": file_sha256(out),
                                                      "method": entry.name, "context": k})
        paths.append(out)
    return paths


def _collect(entry: MethodEntry, cfg: CompareConfig, ds: Dataset, episodes: list[Episode],
             ep_map: dict[str, Episode], pred_dir: Path, ds_id: str, log) -> list[Prediction]:
    paths = [Path(entry.predictions)] if entry.predictions else \
        _run_config(entry, cfg, ds, episodes, pred_dir, ds_id, log)
    files = [(path, read_predictions(path, ds.catalog)) for path in paths]
    preds = [p for _, found in files for p in found]
    have, want = {p.episode for p in preds}, set(ep_map)
    if have != want:
        missing, extra = sorted(want - have), sorted(have - want)
        raise EpisodeSetMismatch(
            f"method {entry.name!r} was predicted on a different episode set: "
            f"{len(missing)} episodes missing (first: {missing[:1]}), {len(extra)} not in this comparison "
            f"(first: {extra[:1]}); compare methods on the same episodes")
    if len(preds) != len(have):
        raise DegustaError(f"method {entry.name!r}: some episodes are predicted twice across its files")
    for path, found in files:
        try:
            notes = check_records(path, found, ds, ep_map)
        except DegustaError as e:
            raise InconsistentRecords(f"method {entry.name!r}: {e}") from None
        for note in notes:
            log(f"[compare] {entry.name}: {note}")
    if all(p.failed or not p.placements for p in preds):
        raise DegustaError(f"every one of its {len(preds)} predictions failed (see the diagnostics in "
                           f"{', '.join(str(p) for p in paths)})")
    for p in preds:
        p.method = entry.name
    return sorted(preds, key=lambda p: p.episode)


def _ledgers(entry: MethodEntry, cfg: CompareConfig, pred_dir: Path) -> list[Path]:
    """The ledgers of a method: one per run of a config method; for a predictions file, the ledger.json beside it
    when that ledger says it was written for this very file (its `out`)."""
    if entry.config is not None:
        return [ledger_path(path) for _, _, path in _runs(entry, cfg, pred_dir)]
    beside = Path(entry.predictions).parent / "ledger.json"
    return [beside] if _ledger_for(beside, Path(entry.predictions)) else []


def _output_names(cfg: CompareConfig, pred_dir: Path) -> None:
    """Refuse two methods whose files under predictions/ would have the same name."""
    owner: dict[str, str] = {}
    for entry in cfg.methods:
        names = [f"{entry.name}.jsonl"]
        if entry.config is not None:
            for _, _, path in _runs(entry, cfg, pred_dir):
                names += [path.name, fingerprint_path(path).name, ledger_path(path).name]
        for name in names:
            if owner.setdefault(name, entry.name) != entry.name:
                raise DegustaError(f"methods: {owner[name]!r} and {entry.name!r} would both write "
                                   f"predictions/{name}; rename one of them")


RESAMPLE_CLUSTER = {"participants": "participant", "episodes": None}
"""`resample` (a config's or `degusta evaluate --resample`'s word) -> the `cluster` of summary.summarize."""


def paired_table(rows: list[EpisodeRow], methods: list[str], n_bootstrap: int, seed: int,
                 resample: str = "participants") -> list[dict]:
    """Paired differences (b - a) of every pair of methods on their shared episodes, resampled as `resample` says
    (`summary.paired_comparisons`; pass the methods ranked: a is then the better-ranked one)."""
    return paired_comparisons(rows, methods, n_bootstrap, seed, cluster=RESAMPLE_CLUSTER[resample])


def _refuse_replacing_inputs(cfg: CompareConfig, out: Path, pred_dir: Path, config_path) -> None:
    """No file compare writes (the report set, `predictions/*`) may be one of its inputs or a dataset file."""
    inputs = [("the compare config", config_path), ("the episodes file", cfg.episodes),
              *((f"the predictions file of method {e.name!r}", e.predictions) for e in cfg.methods),
              *((f"the predict config of method {e.name!r}", e.config) for e in cfg.methods)]
    refuse_replacing_inputs(out, inputs, kind=COMPARISON, datasets=[cfg.dataset], writes=COMPARISON.patterns,
                            keep=("predictions",))
    for entry in cfg.methods:
        written = [pred_dir / f"{entry.name}.jsonl"]
        if entry.config is not None:
            written += [p for _, _, path in _runs(entry, cfg, pred_dir)
                        for p in (path, fingerprint_path(path), ledger_path(path))]
        for path in written:
            mine = f"the predictions file of method {entry.name!r}"  # predictions/NAME.jsonl may be rewritten
            own = [i for i in inputs if not (path == written[0] and i[0] == mine)]  # from its own content
            refuse_replacing_inputs(path, own, key="out", datasets=[cfg.dataset])


def compare(cfg: CompareConfig, log=print, config_path: str | Path | None = None) -> Comparison:
    """Run/collect every method, score them on the same episodes and write the report folder.

    Returns the report folder and the methods that failed (each is logged and listed in the report); raises
    DegustaError, writing nothing, when every method failed or the comparison itself is refused."""
    from degusta_learn.evaluate.compare_report import write_compare_report

    out = check_target(cfg.out, COMPARISON)  # a bad `out` is refused before anything runs
    with hold(out, COMPARISON.what):  # a second compare into the same folder is refused while this one runs
        ds = load_dataset(cfg.dataset)
        episodes = comparison_episodes(cfg, ds)
        ep_map = {e.id: e for e in episodes}
        pred_dir = out / "predictions"
        _output_names(cfg, pred_dir)
        _refuse_replacing_inputs(cfg, out, pred_dir, config_path)
        ds_id = dataset_identity(ds)
        check_stale_paid(cfg, ds, episodes, pred_dir, ds_id)
        predictions, failures, costs = {}, {}, {}
        for entry in cfg.methods:
            try:
                predictions[entry.name] = _collect(entry, cfg, ds, episodes, ep_map, pred_dir, ds_id, log)
            except (EpisodeSetMismatch, InconsistentRecords):
                raise
            except DegustaError as e:
                log(f"[compare] {entry.name}: FAILED: {one_line(str(e), MESSAGE_LIMIT)}")
                failures[entry.name] = str(e)
                continue
            costs[entry.name] = method_cost(_ledgers(entry, cfg, pred_dir), len(predictions[entry.name]))
        if not predictions:
            reasons = "; ".join(f"{m}: {' '.join(msg.split())}" for m, msg in failures.items())
            raise DegustaError(f"every method failed, so no report was written ({reasons})")
        rows = [r for preds in predictions.values()
                for r in score_predictions(ds, preds, ep_map, matching=cfg.matching)]
        summary = summarize(rows, cfg.n_bootstrap, cfg.seed, cluster=RESAMPLE_CLUSTER[cfg.resample])
        for s in summary.values():
            s["matching"] = cfg.matching  # what every score was taken on
        for name, spent in costs.items():  # what each method's own ledgers say it cost (a paid method keeps one)
            if spent is not None and name in summary:
                summary[name].update({k: spent[k] for k in ("cost_usd_total", "cost_usd_per_episode", "tokens_per_episode",
                                                            "requests")}, cost=spent)
        methods = rank_methods(summary)  # best first; summarize already returns this order
        paired = paired_table(rows, methods, cfg.n_bootstrap, cfg.seed, cfg.resample)
        curve = acceptability_curve(ds.ratings)
        with write_folder(out, COMPARISON, keep=("predictions",)) as tmp:
            for name, preds in predictions.items():
                write_predictions(tmp / "predictions" / f"{name}.jsonl", preds)
            write_compare_report(dataclasses.replace(cfg, out=str(tmp)), ds, episodes, rows, summary, paired, failures,
                                 predictions, curve, log)
        log(f"[compare] report: {out / 'report.md'} (HTML: {out / 'report.html'})")
        return Comparison(out, failures, len(cfg.methods))
