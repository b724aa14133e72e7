"""The summary table `degusta evaluate` and `degusta compare` print on the terminal.

A short, aligned plain-text version of report.md's main table, methods in rank order (summary.rank_methods):
what a user reads first after a run, before opening the report. Method names come from predictions files
(untrusted) and pass through `textsafe.one_line` (control characters made visible).

Example:
    from degusta_learn.evaluate.console import summary_text
    print(summary_text(json.load(open("runs/eval/metrics.json"))))
"""

from __future__ import annotations

from degusta_learn.evaluate.summary import label, ranked, resampling_of
from degusta_learn.textsafe import one_line

COLUMNS = (("set_rmsd", "set RMSD", 3), ("set_rmsd_unregistered", "set RMSD unreg.", 3),
           ("object_f1", "object F1", 3), ("object_accuracy", "obj. acc. (paper)", 3),
           ("rmsd", "Kabsch (paper)", 3), ("count_bias", "count bias", 2))
"""(summary key, header, digits) of the printed columns; a key a summary lacks prints '-'."""


def _cell(stat, digits: int) -> str:
    if not isinstance(stat, dict) or stat.get("mean") is None:
        return "-"
    if stat.get("ci_low") is None or stat.get("ci_high") is None:
        return f"{stat['mean']:.{digits}f}"
    return f"{stat['mean']:.{digits}f} [{stat['ci_low']:.{digits}f}, {stat['ci_high']:.{digits}f}]"


def summary_text(summary: dict[str, dict]) -> str:
    """The ranked methods as an aligned text table, with one line saying what the intervals resampled."""
    header = ["rank", "method", "episodes", "failed", *(name for _, name, _ in COLUMNS)]
    rows = [header]
    for rank, (method, s) in enumerate(ranked(summary).items(), 1):
        failed = s.get("failure_rate")
        rows.append([str(rank), one_line(label(method, s)), str(s.get("n_episodes", "-")),
                     "-" if failed is None else f"{failed:.3f}",
                     *(_cell(s.get(key), digits) for key, _, digits in COLUMNS)])
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) if i == 1 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
             for r in rows]
    unit = resampling_of(summary).get("unit", "episode")
    lines.append(f"Ranked by set RMSD (lower is better; degenerate methods last). 95% intervals resample {unit}s.")
    return "\n".join(lines)
