"""Plots of a comparison report (matplotlib, Agg backend, PNG): deterministic file content per input.

- `plot_metric_bars`: set RMSD, Kabsch RMSD and object accuracy per method with 95% intervals;
- `plot_acceptability`: the rating-based acceptance curve with each method's RMSD distribution (CDF);
- `plot_context`: set RMSD, accuracy and Kabsch RMSD against context length per method;
- the grid quantization floor (RMSD of the position -> cells -> position round trip) is drawn as a
  dashed line on the RMSD panels where it is known.

Methods appear in rank order (bars left to right, legends top to bottom: summary.rank_methods). A
degenerate method (its answers take a shortcut: too few objects, too many, a constant answer) is drawn
grey and hatched (bars) or dotted (lines), and its label carries its reasons (summary.degenerate_mark; the
acceptability legend, given only names, the plain summary.DEGENERATE_MARK); a method decoded inside the
answer grammar carries summary.GRAMMAR_MARK. Method names pass through textsafe.plot_text (one line, `$` escaped so that no
label is parsed as mathtext, a leading `_` kept visible): any name draws.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from degusta_learn.evaluate.summary import DEGENERATE_MARK, GRAMMAR_MARK, degenerate_mark, ranked  # noqa: E402
from degusta_learn.files.atomic import atomic_open  # noqa: E402
from degusta_learn.scene import CONTEXT_LENGTHS  # noqa: E402
from degusta_learn.textsafe import plot_text  # noqa: E402

_METADATA = {"Software": None}  # no version strings in the PNG: same input, same bytes


def _save(fig, path: Path) -> Path:
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110, bbox_inches="tight", metadata=_METADATA)
    plt.close(fig)
    return path


_BAR, _DEGENERATE = "#4c72b0", "#9a9a9a"


def _line_style(degenerate: bool) -> dict:
    """Dotted for a degenerate method (its own colour, so two of them stay apart), solid otherwise."""
    return {"ls": ":", "lw": 1.8} if degenerate else {"ls": "-"}


def _err(stat: dict) -> tuple[float, float, float]:
    if not stat or stat.get("mean") is None:
        return np.nan, 0.0, 0.0
    if stat.get("ci_low") is None or stat.get("ci_high") is None:  # no interval (one participant): no error bar
        return stat["mean"], 0.0, 0.0
    return stat["mean"], stat["mean"] - stat["ci_low"], stat["ci_high"] - stat["mean"]


def plot_metric_bars(summary: dict[str, dict], path: Path, rmsd_floor: float | None = None) -> Path:
    """Bars with 95% intervals, methods ranked left to right, degenerate ones grey and hatched."""
    summary = ranked(summary)
    methods = list(summary)
    degenerate = [bool(summary[m].get("degenerate")) for m in methods]
    ticks = [plot_text(m) + (GRAMMAR_MARK if summary[m].get("constrained") else "")
             + ("\n" + degenerate_mark(summary[m]).strip() if d else "") for m, d in zip(methods, degenerate)]
    fig, axes = plt.subplots(1, 3, figsize=(max(9, 1.5 * len(methods) + 4), 3.9))
    for ax, metric, title in ((axes[0], "set_rmsd", "set RMSD, ranks the methods (lower is better)"),
                              (axes[1], "rmsd", "Kabsch RMSD, paper (lower is better)"),
                              (axes[2], "object_accuracy", "object accuracy, paper (higher is better)")):
        vals = [_err(summary[m].get(metric)) for m in methods]
        x = np.arange(len(methods))
        ax.bar(x, [v[0] for v in vals], yerr=np.array([[v[1] for v in vals], [v[2] for v in vals]]),
               color=[_DEGENERATE if d else _BAR for d in degenerate],
               hatch=["//" if d else "" for d in degenerate], edgecolor="white", capsize=4)
        ax.set_xticks(x, ticks, rotation=30, ha="right", fontsize=8)
        ax.set_title(title, fontsize=9)
        if metric != "object_accuracy" and rmsd_floor is not None:
            ax.axhline(rmsd_floor, color="#c44e52", ls="--", lw=1, label=f"8x8 grid floor {rmsd_floor:.3f}")
            ax.legend(fontsize=8)
    note = "methods ranked by set RMSD, best on the left"
    if any(degenerate):
        note += "; grey hatched:" + DEGENERATE_MARK + ", ranked last"
    fig.suptitle(note, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def plot_acceptability(curve: dict[float, float], rmsds: dict[str, np.ndarray], path: Path,
                       degenerate: set[str] | frozenset[str] = frozenset(),
                       error: str = "unregistered set RMSD") -> Path:
    """People's acceptance curve and, for each method, the fraction of its episodes whose `error` is <= t (legend
    in the order of `rmsds`; a nan error, a failed prediction, counts as above every t, as in the tables).

    `rmsds` holds each method's per-episode error: by default the like-for-like one (metrics.ACCEPTABILITY_ERROR,
    the unregistered set RMSD, the kind of error the ratings were collected with); the paper's variant passes
    Kabsch RMSDs and error="Kabsch RMSD (paper)". A method in `degenerate` is drawn dotted and labelled with
    DEGENERATE_MARK: its curve says nothing about quality.
    """
    fig, ax = plt.subplots(figsize=(9.4, 3.8))
    ts = sorted(curve)
    ax.plot(ts, [curve[t] for t in ts], "k-o", lw=2, label="people: rating drop < 0.2")
    grid = np.linspace(0, 0.3, 121)
    for method, values in rmsds.items():
        v = np.asarray(values, dtype=float)
        if len(v):
            mark = DEGENERATE_MARK if method in degenerate else ""
            ax.plot(grid, [(v <= g).sum() / len(v) for g in grid], **({"lw": 1.3} | _line_style(bool(mark))),
                    label=f"{plot_text(method)}{mark}: error <= t")
    ax.set_xlabel("error threshold t (normalized image units; people: the jitter's unregistered RMSD)")
    ax.set_ylabel("fraction")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"Acceptability: people's tolerance of a jittered scene vs each method's {error}\n"
                 "legend: methods ranked by set RMSD, best first", fontsize=9)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))  # beside the axes: hides no curve
    fig.tight_layout()
    return _save(fig, path)


def plot_context(summary: dict[str, dict], path: Path, rmsd_floor: float | None = None) -> Path | None:
    if not any("by_context" in s for s in summary.values()):
        return None
    fig, axes = plt.subplots(1, 3, figsize=(11.5, 3.6))
    for method, s in ranked(summary).items():
        by = s.get("by_context", {})
        ks = sorted(by, key=int)
        for ax, metric in ((axes[0], "set_rmsd"), (axes[1], "object_accuracy"), (axes[2], "rmsd")):
            ys = [(by[k].get(metric) or {}).get("mean") for k in ks]
            ax.plot([int(k) for k in ks], [np.nan if y is None else y for y in ys], marker="o",
                    label=plot_text(method) + (GRAMMAR_MARK if s.get("constrained") else "")
                    + degenerate_mark(s),
                    **_line_style(bool(s.get("degenerate"))))
    axes[0].set_title("set RMSD vs context length", fontsize=10)
    axes[1].set_title("object accuracy (paper) vs context length", fontsize=10)
    axes[2].set_title("Kabsch RMSD (paper) vs context length", fontsize=10)
    if rmsd_floor is not None:
        axes[2].axhline(rmsd_floor, color="#c44e52", ls="--", lw=1, label="8x8 grid floor")
    for ax in axes:
        ax.set_xlabel("context arrangements k")
        ax.set_xticks(list(CONTEXT_LENGTHS))
    axes[2].legend(fontsize=7, title="ranked by set RMSD", title_fontsize=7)
    fig.tight_layout()
    return _save(fig, path)
