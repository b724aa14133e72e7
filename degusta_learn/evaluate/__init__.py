"""Evaluation: predictions -> per-episode scores -> metrics.json, per_episode.csv, report.md.

Usage:
    degusta evaluate --dataset data/naturalistic --predictions runs/copy_nearest/predictions.jsonl --out runs/eval

Every record is checked against its episode first (scoring.check_records): a file holds one method, and
a prediction whose participant or target disagrees with its episode (or whose target is a context trial)
is refused with file, line and field; a record lacking a field a metric needs (placements without
`rotation`) is scored on what it has, with a note. Intervals resample participants by default
(`cluster=None`: episodes); the report says which. Each method's entry in metrics.json says which participants its
predictions are on (`split`, from their records: `scene.predictions.recorded_split`; "not recorded" for older files)
and what they were made with (`choices`: the distinct records `degusta predict` wrote), and the report's header
names the split, with a reminder that test numbers are final numbers wherever a prediction is on test participants.
The three files are written as one set ((`files.folders`)): an error at any point leaves the previous report folder
as it was.
"""

from __future__ import annotations

import json
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.report import write_report
from degusta_learn.evaluate.scoring import EpisodeRow, check_records, score_predictions
from degusta_learn.evaluate.summary import check_cluster, paired_comparisons, summarize
from degusta_learn.files.folders import OutputKind, check_target, write_folder
from degusta_learn.files.guard import refuse_replacing_inputs
from degusta_learn.metrics import acceptability_curve
from degusta_learn.metrics.matching import check_matching
from degusta_learn.scene import Prediction, load_dataset, read_episodes, read_predictions
from degusta_learn.scene.predictions import CHOICES_KEY, recorded_split

__all__ = ["EVALUATION", "EpisodeRow", "evaluate_files", "paired_comparisons", "score_predictions", "summarize"]

EVALUATION = OutputKind("evaluation report", ("metrics.json", "per_episode.csv", "report.md"))
"""What `degusta evaluate` writes into its --out folder (as one set)."""


def evaluate_files(dataset: str | Path, prediction_files: list[str | Path], out: str | Path,
                   episodes: str | Path | None = None, n_bootstrap: int = 1000, seed: int = 0,
                   cluster: str | None = "participant", matching: str = "hungarian") -> Path:
    """Score prediction files against a dataset and write the report folder `out`.

    With `episodes`, every prediction must belong to that set and every episode must be predicted.
    Several files may hold different methods; a method name found in two files (say, `mogma` from two
    backends) is labelled with each file's folder name, e.g. `mogma (hf_tiny_zeroshot)`.
    `cluster`: the bootstrap resamples participants ("participant", the default) or episodes (None).
    `matching`: how predicted objects are paired with true ones before scoring, "hungarian" (the default) or
    "paper" (the paper's greedy rule; metrics.matching); recorded as each method's `matching` in metrics.json.
    """
    check_cluster(cluster)
    check_matching(matching)
    out = check_target(out, EVALUATION)  # refuse a bad --out before any work
    refuse_replacing_inputs(out, [*(("a predictions file", p) for p in prediction_files),
                                  ("the episodes file", episodes)],
                            kind=EVALUATION, datasets=[dataset], writes=EVALUATION.patterns, key="--out")
    ds = load_dataset(dataset)
    ep_map = {e.id: e for e in read_episodes(episodes, ds)} if episodes else None
    loaded = [(Path(path), read_predictions(path, ds.catalog, ep_map)) for path in prediction_files]
    notes = [note for path, preds in loaded for note in check_records(path, preds, ds, ep_map)]
    names = [m for _, preds in loaded for m in {p.method for p in preds}]
    rows, seen_methods = [], {}
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
        rows += score_predictions(ds, preds, ep_map, matching=matching)
    for method in seen_methods:
        mine = [r for r in rows if r.method == method]
        if mine and all(r.failed for r in mine):
            notes.append(f"Every prediction of {method} failed ({len(mine)} of {len(mine)}): its row is no result; "
                         "see the `diagnostics` of its predictions for why.")
    sets = {m: {r.episode for r in rows if r.method == m} for m in seen_methods}
    if len({frozenset(s) for s in sets.values()}) > 1:
        notes.append("The methods were predicted on different episode sets: compare them with care "
                     "(`degusta compare` refuses this).")
    summary = summarize(rows, n_bootstrap=n_bootstrap, seed=seed, cluster=cluster)
    add_protocol(summary, [p for _, preds in loaded for p in preds])
    for s in summary.values():
        s["matching"] = matching  # what every score was taken on (write_report states it)
    curve = acceptability_curve(ds.ratings)
    with write_folder(out, EVALUATION) as tmp:
        write_report(tmp, "Evaluation report", ds.label, summary, rows, curve, ds.ratings is not None, notes)
    return out


def add_protocol(summary: dict[str, dict], predictions: list[Prediction]) -> None:
    """Add to each method's summary the split its predictions record (`split`) and the distinct choices they were
    made with (`choices`: a list, empty for files written before degusta recorded them)."""
    by_method: dict[str, list[Prediction]] = {}
    for p in predictions:
        by_method.setdefault(p.method, []).append(p)
    for method, s in summary.items():
        mine = by_method.get(method, [])
        s["split"] = recorded_split(mine)
        distinct: dict[str, dict] = {}
        for p in mine:
            choices = (p.diagnostics or {}).get(CHOICES_KEY)
            if isinstance(choices, dict):
                distinct.setdefault(json.dumps(choices, sort_keys=True, default=str), choices)
        s["choices"] = list(distinct.values())
