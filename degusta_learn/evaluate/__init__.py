"""Evaluation: predictions -> per-episode scores -> metrics.json, per_episode.csv, report.md.

Usage:
    degusta evaluate --dataset data/naturalistic --predictions runs/copy_nearest/predictions.jsonl --out runs/eval
"""

from __future__ import annotations

from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.report import write_report
from degusta_learn.evaluate.scoring import EpisodeRow, score_predictions
from degusta_learn.evaluate.summary import summarize
from degusta_learn.metrics import acceptability_curve
from degusta_learn.scene import load_dataset, read_episodes, read_predictions

__all__ = ["EpisodeRow", "evaluate_files", "score_predictions", "summarize"]


def evaluate_files(dataset: str | Path, prediction_files: list[str | Path], out: str | Path,
                   episodes: str | Path | None = None, n_bootstrap: int = 1000, seed: int = 0) -> Path:
    """Score prediction files against a dataset and write the report folder `out`.

    With `episodes`, every prediction must belong to that set and every episode must be predicted.
    Several files may hold different methods; a method name found in two files (say, `mogma` from two
    backends) is labelled with each file's folder name, e.g. `mogma (hf_tiny_zeroshot)`.
    """
    ds = load_dataset(dataset)
    ep_map = {e.id: e for e in read_episodes(episodes, ds)} if episodes else None
    loaded = [(Path(path), read_predictions(path, ds.catalog, ep_map)) for path in prediction_files]
    names = [m for _, preds in loaded for m in {p.method for p in preds}]
    rows, seen_methods, notes = [], {}, []
    for path, preds in loaded:
        for p in preds:
            if names.count(p.method) > 1:
                p.method = f"{p.method} ({path.parent.name or path.stem})"
        for method in {p.method for p in preds}:
            if method in seen_methods:
                raise DegustaError(f"{path}: method {method!r} is also in {seen_methods[method]}")
            seen_methods[method] = path
        if ep_map is not None:
            missing = sorted(set(ep_map) - {p.episode for p in preds})
            if missing:
                raise DegustaError(f"{path}: {len(missing)} of {len(ep_map)} episodes have no prediction "
                                   f"(first: {missing[0]!r})")
        rows += score_predictions(ds, preds, ep_map)
    sets = {m: {r.episode for r in rows if r.method == m} for m in seen_methods}
    if len({frozenset(s) for s in sets.values()}) > 1:
        notes.append("The methods were predicted on different episode sets: compare them with care "
                     "(`degusta compare` refuses this).")
    summary = summarize(rows, n_bootstrap=n_bootstrap, seed=seed)
    out = Path(out)
    write_report(out, "Evaluation report", ds.label, summary, rows, acceptability_curve(ds.ratings),
                 ds.ratings is not None, notes)
    return out
