"""The readable report of `degusta evaluate`: report.md, plus metrics.json and per_episode.csv.

The report names the dataset (and says SYNTHETIC where it is), states how each metric is computed in
one line, and warns that Kabsch RMSD alone rewards predicting one or two objects (N = 1 gives RMSD 0):
read it beside the set RMSD, the count error and the unregistered RMSD. Methods are listed best first
by mean set RMSD (summary.rank_methods); a degenerate method is marked with its reasons and listed after all
others. The main table shows the count bias (predicted minus true objects) beside the count error, and a line
under it names the paper's columns a shortcut flatters (SHORTCUT_NOTE).
A second table (`plan_table`) shows the rest of the task plan: placement order, rotation, and physical
plausibility (off the table, overlapping footprints) with the ground truth's own rates as the reference.
Under the tables one line says what the intervals resampled (participants by default, or episodes).

Every untrusted string (the title, the dataset's name, method names, notes naming files) enters the Markdown
through degusta_learn.textsafe (`md_text`, `md_label`), and per_episode.csv is written by `textsafe.write_csv`
(no cell a spreadsheet would run as a formula): docs/reliability.md, "Untrusted text".
"""

from __future__ import annotations

import math
from pathlib import Path

from degusta_learn.evaluate.scoring import CSV_COLUMNS, NEEDS, EpisodeRow
from degusta_learn.evaluate.summary import (
    GRAMMAR_MARK,
    RANKING_NOTE,
    REASON_LABELS,
    label,
    ranked,
    resampling_line,
    resampling_of,
)
from degusta_learn.files.atomic import atomic_open, atomic_write_text
from degusta_learn.files.jsonio import atomic_write_json
from degusta_learn.metrics import OVERLAP_FRACTION, PAD_MARGIN, PAD_RATIO, SET_PENALTY, SHORT_RATIO
from degusta_learn.metrics.matching import matching_line
from degusta_learn.scene.predictions import EPISODES_FILE, NOT_RECORDED, holds_test
from degusta_learn.textsafe import md_prose, md_text, write_csv

PAPER_NOTE = ("The paper's metrics are marked (paper): object accuracy and Kabsch RMSD here, its acceptability (Kabsch "
              "RMSD <= t) in the Acceptability section; acc@t here is acceptability like for like (unregistered set "
              "RMSD <= t, the kind of error the ratings were collected with).")
SHORTCUT_NOTE = ("Shortcuts move the paper's columns: keeping only a few objects flatters Kabsch RMSD and the paper's "
                 "acc@t, "
                 "padding an answer or naming the whole catalog flatters object accuracy. Set RMSD, which ranks, "
                 f"charges c = {SET_PENALTY} for each missing or extra object, so a shortcut lowers it only where "
                 "the answers were too long to begin with (cutting wrong objects) or near chance; answers that take "
                 "a shortcut wholesale are marked degenerate and ranked last (docs/metrics.md, \"Degenerate answers "
                 "and shortcuts\").")
"""The line under the main table: which of the paper's columns a shortcut flatters."""
DEGENERATE_NOTES = {
    "too few": f"most of its scored predictions have at most {SHORT_RATIO:g} x the ground truth's objects or match at "
               "most 2 of 3 or more, where Kabsch RMSD and acc@t are ~0 by construction",
    "padding": f"most of its scored predictions have at least {PAD_RATIO:g} x the ground truth's objects or "
               f"{PAD_MARGIN} more, which can only raise object accuracy",
    "constant": "it gives one answer (the same objects at the same places) on more than half of its scored episodes, "
                "to several participants",
}
"""The footnote of each degeneracy reason (metrics/degenerate.py) under the main table."""

METRIC_NOTES = f"""\
- **set RMSD** (ranks the methods): OSPA-style set distance on the same matching and Kabsch registration as RMSD: sqrt((sum of min(d, c)^2 over matched pairs + c^2 per unmatched object) / max(n_gt, n_pred)), c = {SET_PENALTY} (lower is better; a failed prediction scores c, one object of five at least 0.179).
- **object accuracy** (paper): fraction of ground-truth objects whose matched prediction is exactly the same object id (higher is better).
- **Kabsch RMSD** (paper): RMSD between matched positions after the best proper 2D rotation + translation, normalized image units (lower is better).
- **acc@t** (like for like): fraction of episodes whose prediction has unregistered set RMSD <= t. The ratings behind the people's curve were collected on complete scenes moved rigidly, measured by the unregistered RMSD of that move; the unregistered set RMSD equals it for a prediction with the ground truth's number of objects (no pair beyond c) and charges c for each missing or extra object. Failed predictions never count.
- **acc@t (paper)**: the paper's variant, the fraction with Kabsch RMSD <= t: the registration removes exactly the rigid move the ratings judged, and one or two matched objects give ~0 (see the Acceptability section).
- **unreg. RMSD**: RMSD of matched positions without registration (where, not only what shape).
- **count error**: |predicted objects - ground-truth objects|.
- **object precision**: same-id matches / predicted objects; **object F1**: 2 * same-id matches / (ground-truth + predicted objects), the harmonic mean of precision and object accuracy (which is the recall). A failed prediction scores 0 on all three.
- **set RMSD (unreg.)**: the set RMSD on unregistered distances: it also charges for where the arrangement is, not only its shape.
- **order τ**: Kendall's tau between the true and the predicted placement order of the matched objects (1 same order, -1 reversed); undefined with fewer than two matched objects, so averaged over the episodes counted beside it.
- **rotation error**: degrees between predicted and true rotation of matched objects, modulo the symmetry both objects share (a round plate is not scored, a square one modulo 90, a cup, fork, knife or spoon in [0, 180]); mean over the scored pairs of an episode, then over episodes.
- **off table**: share of predicted objects whose centroid is outside the table surface; **overlapping pairs**: share of pairs of predicted objects whose footprint ellipses (the scene's width x length) overlap by more than {OVERLAP_FRACTION:g} of the smaller one. The ground truth's own rates are shown as the reference.
- **count bias**: mean of (predicted objects - ground-truth objects), a failed prediction counting as 0 objects: below 0 the method leaves objects out, above 0 it adds some.
- **degenerate** (marked "(degenerate: reason)"): more than half of the method's scored predictions take one shortcut: **too few objects** (at most {SHORT_RATIO:g} x the ground truth's objects, or at most 2 matched of 3 or more: Kabsch RMSD and acc@t are ~0 there by construction), **too many objects** (at least {PAD_RATIO:g} x the ground truth's, or {PAD_MARGIN} more: object accuracy only rises with more guesses) or a **constant answer** (the same objects at the same places, for at least two participants); such a method is ranked after all others.
- Matching: on Hamming distance over type, colours, materials, shape, pattern (the two colours and the two materials compare as unordered pairs: red/blue = blue/red), by the rule stated at the top of the report: Hungarian assignment (the default; ties go to nearer positions) or the paper's greedy rule.
- **{GRAMMAR_MARK.strip()}**: a local model decoded inside the answer grammar, so every answer parses by construction; its "parsed without the grammar" rate (the same model and seeds decoding freely) is the one to set beside free-text failure rates such as the paper's.
- Caution: Kabsch RMSD alone rewards predicting one or two objects (N = 1 gives RMSD 0, N = 2 is nearly free); read it beside set RMSD, count error and unregistered RMSD. Failed predictions are left out of the Kabsch and unregistered RMSD means and counted in the failure rate (and as c in set RMSD).
"""


def fmt(stat: dict | None, digits: int = 3) -> str:
    """'mean [lo, hi]' or '-' for a {"mean", "ci_low", "ci_high"} entry; 'mean [n/a]' without bounds (a clustered
    interval over fewer than two participants)."""
    if not stat or stat.get("mean") is None:
        return "-"
    if stat.get("ci_low") is None or stat.get("ci_high") is None:
        return f"{stat['mean']:.{digits}f} [n/a]"
    return f"{stat['mean']:.{digits}f} [{stat['ci_low']:.{digits}f}, {stat['ci_high']:.{digits}f}]"


def intervals_line(summary: dict[str, dict], paired: bool = False) -> str:
    """The line under the tables saying what the intervals resampled (summary.resampling_line)."""
    r = resampling_of(summary)
    return resampling_line(r.get("unit", "episode"), r.get("n_units"), r.get("n_resamples"), paired)


def md_label(method: str, summary: dict) -> str:
    """summary.label as Markdown: the (untrusted) method name escaped, its marks as they are."""
    return md_text(method) + label(method, summary)[len(method):]


def method_table(summary: dict[str, dict]) -> list[str]:
    """The main table, best first (see RANKING_NOTE), degenerate rows marked, with its notes above it."""
    lines = [RANKING_NOTE + " " + PAPER_NOTE, "",
             "| rank | method | episodes | failure rate | set RMSD | object accuracy (paper) | Kabsch RMSD (paper) | "
             "acc@0.01 | acc@0.05 | acc@0.10 | unreg. RMSD | count error | count bias | "
             "object precision | object F1 | set RMSD (unreg.) |",
             "|---:|---|---:|---:|---|---|---|---:|---:|---:|---|---|---|---|---|---|"]
    for rank, (method, s) in enumerate(ranked(summary).items(), 1):
        acc = s["acceptable_at"]
        lines.append(f"| {rank} | {md_label(method, s)} | {s['n_episodes']} | {s['failure_rate']:.3f} | "
                     f"{fmt(s.get('set_rmsd'))} | {fmt(s['object_accuracy'])} | {fmt(s['rmsd'])} | "
                     f"{acc['0.01']:.3f} | {acc['0.05']:.3f} | {acc['0.10']:.3f} | "
                     f"{fmt(s['rmsd_unregistered'])} | {fmt(s['count_error'], 2)} | {fmt(s.get('count_bias'), 2)} | "
                     f"{fmt(s.get('object_precision'))} | {fmt(s.get('object_f1'))} | "
                     f"{fmt(s.get('set_rmsd_unregistered'))} |")
    lines += ["", SHORTCUT_NOTE, *degenerate_notes(summary)]
    return lines


def degenerate_notes(summary: dict[str, dict]) -> list[str]:
    """One footnote per degeneracy reason some method shows (DEGENERATE_NOTES); [] when none is degenerate."""
    found = [r for r in REASON_LABELS if any(r in (s.get("degenerate_reasons") or ()) for s in summary.values()
                                             if s.get("degenerate"))]
    if any(s.get("degenerate") and not s.get("degenerate_reasons") for s in summary.values()):
        found.append(None)  # an older summary: degenerate, reason not recorded
    lines = [f"(degenerate: {REASON_LABELS[r]}): {DEGENERATE_NOTES[r]}; ranked after every other method." if r
             else "(degenerate): its answers take a shortcut (reason not recorded); ranked after every other method."
             for r in found]
    return [part for line in lines for part in ("", line)]


_SHOWN = {"rotation_error": "rotation error", "overlap_rate": "overlapping pairs"}


def plan_table(summary: dict[str, dict]) -> list[str]:
    """The rest of the task plan, methods ranked: placement order, rotation, off the table, overlapping footprints,
    each with the number of episodes its mean is taken over; then the ground truth's own rates and any fields the
    predictions lacked."""
    lines = ["**Task plan**: placement order, rotation and physical plausibility (how each is defined: \"How to read "
             "this\"). A mean is taken over the episodes where the metric is defined, counted in the `n` column after "
             "it.", "",
             "| rank | method | order τ | n | rotation error (°) | n | off table | n | overlapping pairs | n |",
             "|---:|---|---|---:|---|---:|---|---:|---|---:|"]
    for rank, (method, s) in enumerate(ranked(summary).items(), 1):
        n = s.get("n_scored") or {}
        cells = [f"{fmt(s.get(m), 1 if m == 'rotation_error' else 3)} | {n.get(m, '-')}"
                 for m in ("order_tau", "rotation_error", "off_table_rate", "overlap_rate")]
        lines.append(f"| {rank} | {md_label(method, s)} | " + " | ".join(cells) + " |")
    gt = next((s["ground_truth"] for s in summary.values() if s.get("ground_truth")), None)
    if gt:
        def share(v) -> str:
            return "-" if v is None else f"{v:.3f}"

        lines += ["", f"Ground truth, same episodes (the reference): off table {share(gt.get('off_table_rate'))}, "
                      f"overlapping pairs {share(gt.get('overlap_rate'))}."]
    for method, s in ranked(summary).items():
        for name, count in (s.get("missing_fields") or {}).items():
            what = " and ".join(_SHOWN.get(m, m) for m in NEEDS.get(name, ())) or "metrics needing it"
            lines += ["", f"> {md_text(method)}: {count} of {s['n_episodes']} predictions have placements without "
                          f"`{md_text(name)}`; their {md_text(what)} are not scored (left out of those means and "
                          "their n), every other metric is."]
    return lines


def answer_table(summary: dict[str, dict]) -> list[str]:
    """How the answers of methods that parse model text fared: parsed, how they were decoded, parsed without
    the grammar (constrained rows), closed early by the token budget; [] when no method parses text."""
    rows = [(m, s) for m, s in summary.items() if s.get("parse_rate") is not None]
    if not rows:
        return []

    def rate(v) -> str:
        return "-" if v is None else f"{v:.3f}"

    lines = ["| method | decoding | answers per episode, combined by | answers parsed | parsed without the grammar | "
             "closed early by the token budget |", "|---|---|---|---:|---:|---:|"]
    for method, s in rows:
        constrained = s.get("constrained")
        decoding = {True: "answer grammar", False: "free"}.get(constrained, "not recorded")  # e.g. a remote API
        free = {True: s.get("parse_rate_free"), False: s["parse_rate"]}.get(constrained)
        lo, hi = s.get("samples_per_episode") or (None, None)
        combined = "-" if hi is None else (f"{lo}" if lo == hi else f"{lo}-{hi}") + (
            f", {s['aggregation']}" if s.get("aggregation") else "")
        lines.append(f"| {md_label(method, s)} | {decoding} | {combined} | {rate(s['parse_rate'])} | {rate(free)} | "
                     f"{rate(s.get('forced_close_rate'))} |")
    return ["Answers: how many per episode and, for more than one, how they were combined (steps: the paper's "
            "per-step modes; greedy_votes_pooled: one more, greedy answer lengthened by the samples' votes, its "
            "objects placed from every answer naming them, docs/prompting.md); "
            "the fraction that parsed; for a model decoded inside the answer grammar (every answer parses) "
            "the fraction its free decoding writes parseably (same model, same seeds: the grammar's free answers "
            "are generated wherever it changed one), comparable with free-text parse rates; and the fraction of "
            "answers the token budget closed early (grammar) or cut off (free).", "", *lines]


def few_object_warnings(summary: dict[str, dict], threshold: float = 0.2) -> list[str]:
    """Warnings for methods whose Kabsch RMSD is flattered by matching only one or two objects."""
    lines = []
    for method, s in summary.items():
        rate = s.get("few_objects_rate")
        if rate is not None and rate >= threshold:
            lines.append(f"> Warning: {md_text(method)} matches at most 2 objects in {rate:.0%} of its predictions, where "
                         "Kabsch RMSD is ~0 by construction: judge it by set RMSD, count error and unregistered RMSD.")
    return [*lines, ""] if lines else []


def context_table(summary: dict[str, dict]) -> list[str]:
    """The paper's Table 2 layout (accuracy and RMSD against context length) plus set RMSD, methods ranked."""
    contexts = sorted({k for s in summary.values() for k in s.get("by_context", {})}, key=int)
    if not contexts:
        return []
    lines = ["| method | metric | " + " | ".join(f"k = {k}" for k in contexts) + " |",
             "|---|---|" + "---:|" * len(contexts)]
    for method, s in ranked(summary).items():
        by = s.get("by_context", {})
        for metric, name in (("set_rmsd", "set RMSD"), ("object_accuracy", "object accuracy (paper)"),
                             ("rmsd", "Kabsch RMSD (paper)")):
            cells = [f"{by[k][metric]['mean']:.3f}" if k in by and (by[k].get(metric) or {}).get("mean") is not None
                     else "-" for k in contexts]
            lines.append(f"| {md_label(method, s)} | {name} | " + " | ".join(cells) + " |")
    return lines


def acceptability_lines(curve: dict[float, float], from_ratings: bool, summary: dict[str, dict] | None = None
                        ) -> list[str]:
    """The Acceptability section (the paper's Table 1): the people's tolerance curve, then for every method (ranked)
    the fraction of its episodes acceptable at t like for like (unregistered set RMSD <= t) and the paper's variant
    (Kabsch RMSD <= t). Without `summary`, the people's row alone."""
    source = "this dataset's ratings" if from_ratings else "the paper's user study (no ratings in this dataset)"
    ts = [f"{t:.2f}" for t in sorted(curve)]
    lines = [f"Rating-based acceptance, from {source}: the fraction of jitter trials with RMSD <= t whose "
             "normalized rating drop is below 0.2. A jitter moves the whole scene rigidly and its RMSD is unregistered, "
             "so a method is compared like for like by its unregistered set RMSD (every object present and where it "
             "belongs; a missing or extra object costs c); the paper's variant, Kabsch RMSD <= t, is kept below it, "
             "labelled (paper).", "",
             "| error threshold t | " + " | ".join(ts) + " |", "|---|" + "---:|" * len(ts),
             "| people: % of ratings with drop < 0.2 | " + " | ".join(f"{curve[float(t)]:.3f}" for t in ts) + " |"]

    def cells(fractions) -> str:
        return " | ".join("-" if (fractions or {}).get(t) is None else f"{fractions[t]:.3f}" for t in ts)

    for method, s in ranked(summary or {}).items():
        lines.append(f"| {md_label(method, s)}: unregistered set RMSD <= t | {cells(s.get('acceptable_at'))} |")
        lines.append(f"| {md_label(method, s)}: Kabsch RMSD <= t (paper) | {cells(s.get('acceptable_at_paper'))} |")
    return lines


def write_per_episode_csv(path: Path, rows: list[EpisodeRow]) -> None:
    """One row per (method, episode); text cells neutralised for spreadsheets (textsafe.csv_cell), NaN empty."""
    with atomic_open(path, "w") as f:
        write_csv(f, CSV_COLUMNS, ({k: (None if isinstance(v, float) and math.isnan(v) else v)
                                    for k, v in r.to_row().items()} for r in rows))


TEST_REMINDER = ("> Test participants: these are final numbers, one look per result. Every choice (checkpoints, "
                 "decodings, aggregation, hyperparameters, which build to ship) is made on the validation "
                 "participants first (docs/metrics.md, \"Protocol: validation for choices, test once\").")
"""The header line of a report where some prediction is on test participants."""
VAL_REMINDER = ("> Validation participants: numbers to choose by (checkpoints, decodings, hyperparameters), not the "
                "final number, which is measured once on the test participants after every choice is frozen.")
"""The header line of a report whose predictions are all on the validation participants."""


def _split_text(label: str) -> str:
    """A `recorded_split` label as the header says it."""
    if label == NOT_RECORDED:
        return "not recorded (predictions written before degusta recorded it)"
    if label == EPISODES_FILE:
        return "an episodes file (the dataset has too few participants to split)"
    return "all participants (train, val and test)" if label == "all" else f"**{md_text(label)}** participants"


def split_lines(summary: dict[str, dict]) -> list[str]:
    """The header's split line, from each method's `split` (evaluate.add_protocol; one clause per split when the
    methods differ), then a reminder: test numbers are final, validation numbers are for choosing."""
    by: dict[str, list[str]] = {}
    for method, s in summary.items():
        by.setdefault(str(s.get("split", NOT_RECORDED)), []).append(method)
    if not by:
        return []
    clauses = [_split_text(label) if len(by) == 1 else
               f"{_split_text(label)} ({', '.join(md_text(m) for m in methods)})" for label, methods in by.items()]
    line = "Split (from the predictions' records): " + "; ".join(clauses) + "."
    if any(holds_test(label) for label in by):
        return [line, "", TEST_REMINDER, ""]
    return [line, "", VAL_REMINDER, ""] if set(by) == {"val"} else [line, ""]


def write_report(out: Path, title: str, dataset_label: str, summary: dict[str, dict], rows: list[EpisodeRow],
                 curve: dict[float, float], from_ratings: bool, notes: list[str] | None = None) -> None:
    """Write metrics.json, per_episode.csv and report.md into `out` (a staging folder: see (`files.folders`))."""
    out.mkdir(parents=True, exist_ok=True)
    summary = ranked(summary)
    atomic_write_json(out / "metrics.json", summary)
    write_per_episode_csv(out / "per_episode.csv", rows)
    n_eps = len({r.episode for r in rows})
    unit = resampling_of(summary).get("unit", "episode")
    lines = [f"# {md_text(title)}", "", f"Dataset: **{md_text(dataset_label)}**. Episodes: {n_eps}. "
             f"Methods: {', '.join(md_text(m) for m in summary)}. Intervals are 95% bootstrap intervals over "
             f"{unit}s.", ""]
    if "SYNTHETIC" in dataset_label:
        lines += ["> These numbers are on SYNTHETIC data generated by degusta_learn, not on the paper's human data.", ""]
    lines += split_lines(summary)
    lines += [matching_line(next((s["matching"] for s in summary.values() if "matching" in s), "hungarian")), ""]
    lines += ["## Results", "", *method_table(summary), "", intervals_line(summary), "", *few_object_warnings(summary),
              *plan_table(summary), "", intervals_line(summary), ""]
    answers = answer_table(summary)
    if answers:
        lines += ["## Answers", "", *answers, ""]
    ctx = context_table(summary)
    if ctx:
        lines += ["## By context length", "", *ctx, ""]
    lines += ["## Acceptability (the paper's Table 1)", "", *acceptability_lines(curve, from_ratings, summary), ""]
    for note in notes or []:
        lines += [f"> {md_prose(note)}", ""]  # notes name files and methods: escaped, `code` kept
    lines += ["## How to read this", "", METRIC_NOTES, "",
              "Per-episode scores: `per_episode.csv`; machine-readable summary: `metrics.json`.", ""]
    atomic_write_text(out / "report.md", "\n".join(lines))
