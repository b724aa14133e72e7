"""`degusta compare`: several methods on the same episodes -> one report folder.

Usage:
    degusta compare --config configs/compare_naturalistic.yaml
    degusta compare --config configs/compare_naturalistic.yaml --set "contexts=[4]" --set out=runs/cmp_k4

A compare config lists methods; each is either an existing predictions file or a predict config that
is run (once per context length, into `<out>/predictions/`; files already there are reused, so an
interrupted comparison resumes). Every method must cover exactly the same episodes (refused otherwise,
naming the mismatch). A method whose run fails is reported as failed; the rest of the report is written.
The report lists the methods best first by mean set RMSD, degenerate methods last and marked
(evaluate/summary.py, docs/metrics.md); the paired comparisons and the qualitative reference follow
that order.

Writes `<out>/report.md`, `report.html` (opens without a server), `metrics.json`, `per_episode.csv`,
`plots/*.png` and `qualitative/*.png`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.scoring import EpisodeRow, score_predictions
from degusta_learn.evaluate.summary import rank_methods, summarize
from degusta_learn.metrics import acceptability_curve, paired_bootstrap
from degusta_learn.scene import (
    CONTEXT_LENGTHS, Dataset, Episode, Prediction, load_dataset, make_episodes, read_episodes, read_predictions,
    write_predictions,
)


class EpisodeSetMismatch(DegustaError):
    """A method's predictions cover other episodes than the comparison's: the whole comparison is refused."""


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
        if (self.predictions is None) == (self.config is None):
            raise DegustaError(f"methods entry {self.name!r}: give exactly one of 'predictions' or 'config'")


@dataclass
class CompareConfig:
    """A comparison of several methods on one episode set."""

    dataset: str
    """Dataset folder."""
    out: str
    """Report folder."""
    methods: list[MethodEntry]
    """The methods; the report ranks them by mean set RMSD (degenerate ones last), this order breaks ties."""
    contexts: list[int] = field(default_factory=lambda: [0, 2, 4])
    """Context lengths to build episodes for (ignored when `episodes` is set)."""
    split: str = "test"
    """Participant split of the episodes."""
    episodes: str | None = None
    """A fixed episodes.jsonl instead of `contexts` + `split`."""
    seed: int = 0
    """Seed of the split, bootstrap and the random qualitative episodes."""
    n_bootstrap: int = 1000
    """Bootstrap resamples of the intervals (more: tighter estimates of the interval, slower)."""
    qualitative: int = 3
    """Random episodes drawn side by side (plus the best and worst episode of the top-ranked method)."""
    image_size: int = 256
    """Pixel size of each qualitative panel."""
    title: str = "Comparison report"

    def __post_init__(self):
        if not self.methods:
            raise DegustaError("methods: expected at least one method")
        names = [m.name for m in self.methods]
        if len(set(names)) != len(names):
            raise DegustaError(f"methods: duplicate method name in {names}")
        bad = [k for k in self.contexts if k not in CONTEXT_LENGTHS]
        if bad:
            raise DegustaError(f"contexts: expected values in {list(CONTEXT_LENGTHS)}, got {bad}")


def run_compare(path: str | Path, overrides: list[str] | None = None, log=print) -> Path:
    return compare(load_config(CompareConfig, path, overrides), log=log)


def comparison_episodes(cfg: CompareConfig, ds: Dataset) -> list[Episode]:
    if cfg.episodes:
        return read_episodes(cfg.episodes, ds)
    return [e for k in cfg.contexts for e in make_episodes(ds, k, cfg.split, cfg.seed)]


def _run_config(entry: MethodEntry, cfg: CompareConfig, pred_dir: Path, log) -> list[Path]:
    from degusta_learn.methods import run_predict

    runs = [(None, [f"episodes={cfg.episodes}"])] if cfg.episodes else \
        [(k, ["episodes=null", f"context={k}", f"split={cfg.split}"]) for k in cfg.contexts]
    paths = []
    for k, keys in runs:
        out = pred_dir / (f"{entry.name}_k{k}.jsonl" if k is not None else f"{entry.name}_episodes.jsonl")
        if out.exists():
            log(f"[compare] {entry.name}: reusing {out}")
        else:
            log(f"[compare] {entry.name}: predicting" + (f" (context {k})" if k is not None else ""))
            run_predict(entry.config, [*entry.set, f"dataset={cfg.dataset}", f"seed={cfg.seed}", *keys, f"out={out}"])
        paths.append(out)
    return paths


def _collect(entry: MethodEntry, cfg: CompareConfig, ds: Dataset, ep_map: dict[str, Episode],
             pred_dir: Path, log) -> list[Prediction]:
    paths = [Path(entry.predictions)] if entry.predictions else _run_config(entry, cfg, pred_dir, log)
    preds = [p for path in paths for p in read_predictions(path, ds.catalog)]
    have, want = {p.episode for p in preds}, set(ep_map)
    if have != want:
        missing, extra = sorted(want - have), sorted(have - want)
        raise EpisodeSetMismatch(
            f"method {entry.name!r} was predicted on a different episode set: "
            f"{len(missing)} episodes missing (first: {missing[:1]}), {len(extra)} not in this comparison "
            f"(first: {extra[:1]}); compare methods on the same episodes")
    for p in preds:
        p.method = entry.name
    return sorted(preds, key=lambda p: p.episode)


PAIRED_METRICS = ("set_rmsd", "object_accuracy", "rmsd")


def paired_table(rows: list[EpisodeRow], methods: list[str], n_bootstrap: int, seed: int) -> list[dict]:
    """Paired bootstrap differences (b - a) per metric for every pair of methods on shared episodes.

    Pairs follow the order of `methods` (pass them ranked: a is then the better-ranked method).
    """
    by = {m: {r.episode: r for r in rows if r.method == m} for m in methods}
    out = []
    for a, b in itertools.combinations(methods, 2):
        eps = sorted(set(by[a]) & set(by[b]))
        entry = {"a": a, "b": b}
        for metric in PAIRED_METRICS:
            va = np.array([getattr(by[a][e], metric) for e in eps], dtype=float)
            vb = np.array([getattr(by[b][e], metric) for e in eps], dtype=float)
            ok = np.isfinite(va) & np.isfinite(vb)
            entry[metric] = (paired_bootstrap(vb[ok], va[ok], n_resamples=n_bootstrap, seed=seed)  # mean(b - a)
                             if ok.sum() >= 2 else None)
        out.append(entry)
    return out


def compare(cfg: CompareConfig, log=print) -> Path:
    """Run/collect every method, score them on the same episodes and write the report folder."""
    from degusta_learn.evaluate.compare_report import write_compare_report

    ds = load_dataset(cfg.dataset)
    episodes = comparison_episodes(cfg, ds)
    ep_map = {e.id: e for e in episodes}
    out = Path(cfg.out)
    pred_dir = out / "predictions"
    predictions, failures = {}, {}
    for entry in cfg.methods:
        try:
            predictions[entry.name] = _collect(entry, cfg, ds, ep_map, pred_dir, log)
        except EpisodeSetMismatch:
            raise
        except DegustaError as e:
            log(f"[compare] {entry.name}: FAILED: {e}")
            failures[entry.name] = str(e)
    rows = [r for preds in predictions.values() for r in score_predictions(ds, preds, ep_map)]
    for name, preds in predictions.items():
        write_predictions(pred_dir / f"{name}.jsonl", preds)
    summary = summarize(rows, cfg.n_bootstrap, cfg.seed)
    methods = rank_methods(summary)  # best first; summarize already returns this order
    paired = paired_table(rows, methods, cfg.n_bootstrap, cfg.seed)
    write_compare_report(cfg, ds, episodes, rows, summary, paired, failures, predictions,
                         acceptability_curve(ds.ratings), log)
    log(f"[compare] report: {out / 'report.md'} (HTML: {out / 'report.html'})")
    return out
