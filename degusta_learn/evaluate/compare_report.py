"""Writing the comparison report folder: markdown + HTML, metrics.json, per_episode.csv, plots, images.

Every table, plot and image lists the methods in rank order (summary.rank_methods: mean set RMSD, lower
first, degenerate methods last) and marks degenerate methods (summary.label; grey hatched bars, dotted
lines, "[degenerate]" in qualitative panel titles).

Intervals and paired tests resample participants unless the summary says episodes (`summary.resampling`);
one line under the tables says which. The paired comparisons are `summary.paired_comparisons` of the
rows, resampled like the summary: `paired` entries without a `resampling` record (computed per episode,
with the old shift test) are recomputed here, so the bold "interval excludes 0" and the p-value always
come from the same resamples.

Untrusted text (the config's title, the dataset's name, episode ids, the error messages of failed methods, which
may quote a server's reply) enters report.md through degusta_learn.textsafe, and report.html is rendered by
`textsafe.markdown_to_html` (raw HTML shown as text, only relative and http(s) links): docs/reliability.md,
"Untrusted text".
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.plots import plot_acceptability, plot_context, plot_metric_bars
from degusta_learn.evaluate.report import (
    METRIC_NOTES,
    TEST_REMINDER,
    VAL_REMINDER,
    acceptability_lines,
    answer_table,
    context_table,
    few_object_warnings,
    intervals_line,
    md_label,
    method_table,
    plan_table,
    write_per_episode_csv,
)
from degusta_learn.evaluate.summary import GRAMMAR_MARK, paired_comparisons, ranked, resampling_of
from degusta_learn.files.atomic import atomic_write_text
from degusta_learn.metrics import ACCEPTABILITY_ERROR
from degusta_learn.files.jsonio import atomic_write_json
from degusta_learn.metrics.matching import matching_line
from degusta_learn.scene.predictions import holds_test, recorded_split
from degusta_learn.textsafe import MESSAGE_LIMIT, html_text, markdown_to_html, md_code, md_text

_HTML = """<!doctype html><html><head><meta charset="utf-8"><title>{title}</title><style>
body{{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}}
table{{border-collapse:collapse;margin:1em 0;font-size:14px}} td,th{{border:1px solid #ccc;padding:4px 8px;overflow-wrap:anywhere}}
th{{background:#f3f3f3}} img{{max-width:100%}} blockquote{{background:#fff6e0;margin:0;padding:.5em 1em}}
code{{background:#f3f3f3}}</style></head><body>
{body}
</body></html>
"""


def _finite(*values) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


def p_text(p, n_resamples: int | None = None) -> str:
    """A p-value as the paired table shows it: '<1/B' where every resample fell on one side (p = 0)."""
    if not _finite(p):
        return "-"
    if p == 0:
        return f"<{1 / n_resamples:.2g}" if n_resamples else "<0.001"
    return f"{p:.3f}"


def paired_cells(r: dict | None, n_resamples: int | None = None) -> list[str]:
    """The two cells of one paired difference: 'diff [lo, hi]' (bold where the interval excludes 0) and p."""
    if r is None or not _finite(r.get("diff")):
        return ["-", "-"]
    if not _finite(r.get("lo"), r.get("hi")):
        return [f"{r['diff']:+.3f} [n/a]", "-"]
    text = f"{r['diff']:+.3f} [{r['lo']:+.3f}, {r['hi']:+.3f}]"
    return [f"**{text}**" if r["lo"] > 0 or r["hi"] < 0 else text, p_text(r.get("p_value"), n_resamples)]


def _paired_lines(paired: list[dict], summary: dict[str, dict]) -> list[str]:
    if not paired:
        return []
    lines = ["Differences b - a on the same episodes (paired bootstrap, 95% percentile interval; two-sided p read "
             "off the same resamples: twice the share of resampled differences on the far side of 0, so p < 0.05 "
             "exactly where the interval excludes 0); **bold** where the interval excludes 0. Pairs follow the "
             "ranking: a is the better-ranked method. Set RMSD counts a failed prediction as c; the Kabsch RMSD "
             "(paper) column uses only the episodes where both predicted something.", "",
             "| a | b | Δ set RMSD | p | Δ object accuracy (paper) | p | Δ Kabsch RMSD (paper) | p |",
             "|---|---|---|---:|---|---:|---|---:|"]
    for e in paired:
        n_resamples = (e.get("resampling") or {}).get("n_resamples")
        cells = [c for metric in ("set_rmsd", "object_accuracy", "rmsd") for c in paired_cells(e.get(metric), n_resamples)]
        lines.append(f"| {md_label(e['a'], summary[e['a']])} | {md_label(e['b'], summary[e['b']])} | "
                     + " | ".join(cells) + " |")
    return lines


def consistent_paired(cfg, rows, summary: dict[str, dict], paired: list[dict]) -> list[dict]:
    """`paired` as this report shows it: resampled like the summary's intervals (participants by default). Entries
    computed elsewhere without a `resampling` record (per episode, with another p-value) are recomputed from the
    rows by `summary.paired_comparisons`."""
    if not paired or all(isinstance(e.get("resampling"), dict) for e in paired):
        return paired
    unit = resampling_of(summary).get("unit", "participant")
    return paired_comparisons(rows, list(summary), cfg.n_bootstrap, cfg.seed,
                              cluster=None if unit == "episode" else "participant")


COST_KEYS = ("tokens_per_episode", "cost_usd_per_episode", "cost_usd_total", "requests")
"""What a paid (or token-counting) method adds to its summary (compare.method_cost): the cost table's columns."""


def _cost_lines(summary: dict[str, dict]) -> list[str]:
    """The failures and cost table; [] when no method failed anything and none reports tokens, cost or requests
    (a table of zeros and dashes says nothing)."""
    if not any(s.get("failure_rate") or any(s.get(k) is not None for k in COST_KEYS) for s in summary.values()):
        return []
    lines = ["| method | failure rate | tokens / episode | USD / episode | USD total | requests |",
             "|---|---:|---:|---:|---:|---:|"]  # cost and requests: a paid method's ledgers (compare.method_cost)
    for method, s in summary.items():
        lines.append(f"| {md_label(method, s)} | {s['failure_rate']:.3f} | {s.get('tokens_per_episode', '-')} | "
                     f"{s.get('cost_usd_per_episode', '-')} | {s.get('cost_usd_total', '-')} | "
                     f"{s.get('requests', '-')} |")
    return lines


def _grid_floor(ds) -> float | None:
    try:
        from degusta_learn.render.grid import Grid, quantization_rmsd

        return float(quantization_rmsd(ds, Grid(8, 8)))
    except Exception:  # a floor is a nicety; never lose the report over it
        return None


def _qualitative(cfg, ds, rows, predictions, summary, out: Path) -> list[str]:
    """Side-by-side images: the top-ranked method's best and worst episode (by set RMSD), then random ones, each
    with the placement steps and the scores' own matching (`cfg.matching`) drawn on it."""
    from degusta_learn.evaluate.qualitative import render_side_by_side
    from degusta_learn.render.lifting import Renderer

    if not predictions:
        return []
    ref = next(iter(predictions))  # ranked: the top-ranked method
    ref_rows = [r for r in rows if r.method == ref and not r.failed and math.isfinite(r.set_rmsd)]
    chosen: list[tuple[str, str]] = []
    if ref_rows:
        best = min(ref_rows, key=lambda r: (r.set_rmsd, r.episode))
        worst = max(ref_rows, key=lambda r: (r.set_rmsd, r.episode))
        chosen += [(f"best of {md_text(ref)} (top-ranked)", best.episode),
                   (f"worst of {md_text(ref)} (top-ranked)", worst.episode)]
    episodes = sorted({r.episode for r in rows})
    rng = np.random.default_rng(cfg.seed)
    if isinstance(cfg.qualitative, bool) or not isinstance(cfg.qualitative, int) or cfg.qualitative < 0:
        raise DegustaError(f"qualitative: expected a number of episodes >= 0, got {cfg.qualitative!r}")
    for i in rng.choice(len(episodes), size=min(cfg.qualitative, len(episodes)), replace=False):
        chosen.append(("random", episodes[int(i)]))
    renderer = Renderer.for_dataset(ds, size=cfg.render_size)
    by = {(r.method, r.episode): r for r in rows}
    lines = ["Numbers on the objects: the placement step. On a prediction, j→g is its step j and the step g of the "
             f"true object the scores matched it to (matching: {cfg.matching}), green where it is the same object "
             "(what object accuracy counts), orange where it is another; grey j× was not matched; a red ring marks a "
             "true object left unmatched.", ""] if chosen else []
    for n, (why, eid) in enumerate(chosen):
        panels = {}
        for method, preds in predictions.items():
            pred = next(p for p in preds if p.episode == eid)
            r = by[(method, eid)]
            score = "failed" if r.failed else f"set {r.set_rmsd:.3f}, RMSD {r.rmsd:.3f}, acc {r.object_accuracy:.2f}"
            shown = method + (GRAMMAR_MARK if summary[method].get("constrained") else "")
            panels[shown + (" [degenerate]" if summary[method].get("degenerate") else "")] = (pred, score)
        first = next(p for p in predictions[ref] if p.episode == eid)
        name = f"qualitative/{n:02d}.png"
        render_side_by_side(ds, renderer, first.participant, first.target, panels, out / name, matching=cfg.matching)
        lines += [f"**{why}**: episode {md_code(eid)}", "", f"![episode {n + 1}]({name})", ""]
    return lines


def write_compare_report(cfg, ds, episodes, rows, summary, paired, failures, predictions, curve, log) -> None:
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = ranked(summary)
    predictions = {m: predictions[m] for m in summary if m in predictions}  # rank order
    paired = consistent_paired(cfg, rows, summary, paired)
    write_per_episode_csv(out / "per_episode.csv", rows)
    # split: the comparison's own, or for an episodes file what its predictions record (scene.predictions)
    split = cfg.split if not cfg.episodes else recorded_split(p for preds in predictions.values() for p in preds)
    atomic_write_json(out / "metrics.json", {"dataset": ds.label, "n_episodes": len(episodes), "split": split,
                                             "methods": summary,
                                             "ranking": list(summary), "ranked_by": "set_rmsd (degenerate last)",
                                             "matching": cfg.matching,
                                             "paired": paired, "failed_methods": failures,
                                             "rating_acceptance": {f"{t:.2f}": v for t, v in curve.items()}})
    floor = _grid_floor(ds)
    plots = out / "plots"
    unit = resampling_of(summary).get("unit", "episode")
    lines = [f"# {md_text(cfg.title)}", "",
             f"Dataset: **{md_text(ds.label)}**. Episodes: {len(episodes)} ({md_text(split)} participants). "
             f"Intervals are 95% bootstrap intervals over {unit}s.", ""]
    if ds.synthetic:
        lines += ["> SYNTHETIC data generated by degusta_learn: these are not the paper's human-study numbers.", ""]
    if holds_test(split):
        lines += [TEST_REMINDER, ""]
    elif split == "val":
        lines += [VAL_REMINDER, ""]
    lines += [matching_line(cfg.matching), ""]
    if failures:
        lines += ["## Methods that failed", ""] + [f"- **{md_text(m)}**: {md_text(msg, MESSAGE_LIMIT)}"
                                                   for m, msg in failures.items()] + [""]
    if summary:
        log("[compare] plotting")
        plot_metric_bars(summary, plots / "metrics.png", floor)
        shown = {m: m + GRAMMAR_MARK if s.get("constrained") else m for m, s in summary.items()}  # "+ grammar" rows
        # like for like, as the tables: every episode counts (a failed one scores c, above every threshold reported)
        errors = {shown[m]: np.array([getattr(r, ACCEPTABILITY_ERROR) for r in rows if r.method == m], dtype=float)
                  for m in summary}
        plot_acceptability(curve, errors, plots / "acceptability.png",
                           {shown[m] for m, s in summary.items() if s.get("degenerate")})
        has_ctx = plot_context(summary, plots / "context.png", floor) is not None
        lines += ["## Results", "", *method_table(summary), "", intervals_line(summary), "",
                  *few_object_warnings(summary), "![metrics](plots/metrics.png)", ""]
        lines += [*plan_table(summary), "", intervals_line(summary), ""]
        # (evaluate's table of the people's row alone would repeat that row)
        lines += ["## Acceptability (the paper's Table 1)", "", *acceptability_lines(curve, ds.ratings is not None, summary),
                  "", "![acceptability](plots/acceptability.png)", ""]
        ctx = context_table(summary)
        if ctx:
            lines += ["## Set RMSD, object accuracy and Kabsch RMSD by context length (the paper's Table 2, "
                      "plus set RMSD)", "", *ctx, ""]
            if has_ctx:
                lines += ["![context](plots/context.png)", ""]
        if floor is not None:
            lines += [f"Grid quantization floor (8 x 8 grid, position -> cells -> position): RMSD {floor:.4f}. "
                      "No grid-answering method can be more precise than this.", ""]
        costs = _cost_lines(summary)
        if costs:
            lines += ["## Failures and cost", "", *costs, ""]
        answers = answer_table(summary)
        if answers:
            lines += [*answers, ""]
        lines += ["## Paired comparisons", "", *_paired_lines(paired, summary), ""]
        if paired:
            lines += [intervals_line(summary, paired=True), ""]
        log("[compare] rendering qualitative images")
        lines += ["## Qualitative: ground truth and each method side by side", "",
                  *_qualitative(cfg, ds, rows, predictions, summary, out)]
    lines += ["## How to read this", "", METRIC_NOTES, "",
              "Per-episode scores: `per_episode.csv`; summary: `metrics.json`; predictions: `predictions/`.", ""]
    text = "\n".join(lines)
    atomic_write_text(out / "report.md", text)
    atomic_write_text(out / "report.html", _HTML.format(title=html_text(cfg.title), body=markdown_to_html(text)))
