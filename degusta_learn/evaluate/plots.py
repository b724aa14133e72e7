"""Plots of a comparison report (matplotlib, Agg backend, PNG): deterministic file content per input.

- `plot_metric_bars`: Kabsch RMSD and object accuracy per method with 95% intervals;
- `plot_acceptability`: the rating-based acceptance curve with each method's RMSD distribution (CDF);
- `plot_context`: accuracy and RMSD against context length per method;
- the grid quantization floor (RMSD of the position -> cells -> position round trip) is drawn as a
  dashed line on the RMSD panels where it is known.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from degusta_learn.fileio import atomic_open  # noqa: E402

_METADATA = {"Software": None}  # no version strings in the PNG: same input, same bytes


def _save(fig, path: Path) -> Path:
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110, bbox_inches="tight", metadata=_METADATA)
    plt.close(fig)
    return path


def _err(stat: dict) -> tuple[float, float, float]:
    if not stat or stat.get("mean") is None:
        return np.nan, 0.0, 0.0
    return stat["mean"], stat["mean"] - stat["ci_low"], stat["ci_high"] - stat["mean"]


def plot_metric_bars(summary: dict[str, dict], path: Path, rmsd_floor: float | None = None) -> Path:
    methods = list(summary)
    fig, axes = plt.subplots(1, 2, figsize=(max(6, 1.3 * len(methods) + 3), 3.6))
    for ax, metric, label in ((axes[0], "rmsd", "Kabsch RMSD (lower is better)"),
                              (axes[1], "object_accuracy", "object accuracy (higher is better)")):
        vals = [_err(summary[m][metric]) for m in methods]
        x = np.arange(len(methods))
        ax.bar(x, [v[0] for v in vals], yerr=np.array([[v[1] for v in vals], [v[2] for v in vals]]),
               color="#4c72b0", capsize=4)
        ax.set_xticks(x, methods, rotation=30, ha="right")
        ax.set_title(label, fontsize=10)
        if metric == "rmsd" and rmsd_floor is not None:
            ax.axhline(rmsd_floor, color="#c44e52", ls="--", lw=1, label=f"8x8 grid floor {rmsd_floor:.3f}")
            ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_acceptability(curve: dict[float, float], rmsds: dict[str, np.ndarray], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6.2, 3.8))
    ts = sorted(curve)
    ax.plot(ts, [curve[t] for t in ts], "k-o", lw=2, label="people: rating drop < 0.2")
    grid = np.linspace(0, 0.3, 121)
    for method, values in rmsds.items():
        v = np.asarray(values, dtype=float)
        if len(v):
            ax.plot(grid, [(v <= g).sum() / len(v) for g in grid], lw=1.3, label=f"{method}: RMSD <= t")
    ax.set_xlabel("RMSD threshold t (normalized image units)")
    ax.set_ylabel("fraction")
    ax.set_ylim(0, 1.02)
    ax.set_title("Acceptability: people's tolerance vs each method's RMSD distribution", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return _save(fig, path)


def plot_context(summary: dict[str, dict], path: Path, rmsd_floor: float | None = None) -> Path | None:
    if not any("by_context" in s for s in summary.values()):
        return None
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.4))
    for method, s in summary.items():
        by = s.get("by_context", {})
        ks = sorted(by, key=int)
        for ax, metric in ((axes[0], "object_accuracy"), (axes[1], "rmsd")):
            ys = [by[k][metric]["mean"] if by[k][metric]["mean"] is not None else np.nan for k in ks]
            ax.plot([int(k) for k in ks], ys, "-o", label=method)
    axes[0].set_title("object accuracy vs context length", fontsize=10)
    axes[1].set_title("Kabsch RMSD vs context length", fontsize=10)
    if rmsd_floor is not None:
        axes[1].axhline(rmsd_floor, color="#c44e52", ls="--", lw=1, label="8x8 grid floor")
    for ax in axes:
        ax.set_xlabel("context arrangements k")
        ax.set_xticks([0, 2, 4])
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path)
