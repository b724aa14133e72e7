"""The readable report of `degusta evaluate`: report.md, plus metrics.json and per_episode.csv.

The report names the dataset (and says SYNTHETIC where it is), states how each metric is computed in
one line, and warns that Kabsch RMSD alone rewards predicting one or two objects (N = 1 gives RMSD 0):
read it beside the count error and the unregistered RMSD.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from degusta_learn.evaluate.scoring import CSV_COLUMNS, EpisodeRow
from degusta_learn.fileio import atomic_open, atomic_write_json, atomic_write_text

METRIC_NOTES = """\
- **object accuracy**: fraction of ground-truth objects whose matched prediction is exactly the same object id (higher is better).
- **RMSD**: Kabsch RMSD between matched positions after the best proper 2D rotation + translation, normalized image units (lower is better).
- **unreg. RMSD**: RMSD of matched positions without registration (where, not only what shape).
- **count error**: |predicted objects - ground-truth objects|.
- **acc@t**: fraction of episodes whose prediction has Kabsch RMSD <= t (failed predictions never count).
- Matching: Hungarian assignment on Hamming distance over type, colours, materials, shape, pattern; ties go to nearer positions.
- Caution: Kabsch RMSD alone rewards predicting one or two objects (N = 1 gives RMSD 0, N = 2 is nearly free); read it beside count error and unregistered RMSD. Failed predictions are left out of RMSD means and counted in the failure rate.
"""


def fmt(stat: dict | None, digits: int = 3) -> str:
    """'mean [lo, hi]' or '-' for a {"mean", "ci_low", "ci_high"} entry."""
    if not stat or stat.get("mean") is None:
        return "-"
    return f"{stat['mean']:.{digits}f} [{stat['ci_low']:.{digits}f}, {stat['ci_high']:.{digits}f}]"


def method_table(summary: dict[str, dict]) -> list[str]:
    lines = ["| method | episodes | failure rate | object accuracy | RMSD | unreg. RMSD | count error | acc@0.01 | acc@0.05 | acc@0.10 |",
             "|---|---:|---:|---|---|---|---|---:|---:|---:|"]
    for method, s in summary.items():
        acc = s["acceptable_at"]
        lines.append(f"| {method} | {s['n_episodes']} | {s['failure_rate']:.3f} | {fmt(s['object_accuracy'])} | "
                     f"{fmt(s['rmsd'])} | {fmt(s['rmsd_unregistered'])} | {fmt(s['count_error'], 2)} | "
                     f"{acc['0.01']:.3f} | {acc['0.05']:.3f} | {acc['0.10']:.3f} |")
    return lines


def few_object_warnings(summary: dict[str, dict], threshold: float = 0.2) -> list[str]:
    """Warnings for methods whose Kabsch RMSD is flattered by matching only one or two objects."""
    lines = []
    for method, s in summary.items():
        rate = s.get("few_objects_rate")
        if rate is not None and rate >= threshold:
            lines.append(f"> Warning: {method} matches at most 2 objects in {rate:.0%} of its predictions, where "
                         "Kabsch RMSD is ~0 by construction: judge it by count error and unregistered RMSD.")
    return [*lines, ""] if lines else []


def context_table(summary: dict[str, dict]) -> list[str]:
    """The paper's Table 2 layout: accuracy and RMSD against context length, one row pair per method."""
    contexts = sorted({k for s in summary.values() for k in s.get("by_context", {})}, key=int)
    if not contexts:
        return []
    lines = ["| method | metric | " + " | ".join(f"k = {k}" for k in contexts) + " |",
             "|---|---|" + "---:|" * len(contexts)]
    for method, s in summary.items():
        by = s.get("by_context", {})
        for metric, label in (("object_accuracy", "object accuracy"), ("rmsd", "RMSD")):
            cells = [f"{by[k][metric]['mean']:.3f}" if k in by and by[k][metric]["mean"] is not None else "-"
                     for k in contexts]
            lines.append(f"| {method} | {label} | " + " | ".join(cells) + " |")
    return lines


def acceptability_lines(curve: dict[float, float], from_ratings: bool) -> list[str]:
    source = "this dataset's ratings" if from_ratings else "the paper's user study (no ratings in this dataset)"
    return [f"Rating-based acceptance, from {source}: the fraction of jitter trials with RMSD <= t whose "
            "normalized rating drop is below 0.2.", "",
            "| RMSD threshold | " + " | ".join(f"{t:.2f}" for t in curve) + " |",
            "|---|" + "---:|" * len(curve),
            "| % of ratings with drop < 0.2 | " + " | ".join(f"{v:.3f}" for v in curve.values()) + " |"]


def write_per_episode_csv(path: Path, rows: list[EpisodeRow]) -> None:
    with atomic_open(path, "w") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: ("" if v is None or (isinstance(v, float) and math.isnan(v)) else v)
                             for k, v in r.to_row().items()})


def write_report(out: Path, title: str, dataset_label: str, summary: dict[str, dict], rows: list[EpisodeRow],
                 curve: dict[float, float], from_ratings: bool, notes: list[str] | None = None) -> None:
    """Write metrics.json, per_episode.csv and report.md into `out` (each atomically)."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "metrics.json", summary)
    write_per_episode_csv(out / "per_episode.csv", rows)
    n_eps = len({r.episode for r in rows})
    lines = [f"# {title}", "", f"Dataset: **{dataset_label}**. Episodes: {n_eps}. "
             f"Methods: {', '.join(summary)}. Intervals are 95% bootstrap intervals over episodes.", ""]
    if "SYNTHETIC" in dataset_label:
        lines += ["> These numbers are on SYNTHETIC data generated by degusta_learn, not on the paper's human data.", ""]
    lines += ["## Results", "", *method_table(summary), "", *few_object_warnings(summary)]
    ctx = context_table(summary)
    if ctx:
        lines += ["## By context length", "", *ctx, ""]
    lines += ["## Acceptability", "", *acceptability_lines(curve, from_ratings), ""]
    for note in notes or []:
        lines += [f"> {note}", ""]
    lines += ["## How to read this", "", METRIC_NOTES, "",
              "Per-episode scores: `per_episode.csv`; machine-readable summary: `metrics.json`.", ""]
    atomic_write_text(out / "report.md", "\n".join(lines))
