"""Per-method summaries with bootstrap intervals: the content of metrics.json.

For each method: `n_episodes`, `failure_rate`, and for each of `METRICS` (object_accuracy, rmsd,
rmsd_unregistered, count_error, set_rmsd, and the task-plan metrics object_precision, object_f1,
set_rmsd_unregistered, order_tau, rotation_error, off_table_rate, overlap_rate) a {"mean", "ci_low",
"ci_high"}: a percentile bootstrap that by default resamples participants (all episodes of a participant
stay together, the statistic is the mean over the resampled participants' episodes; `cluster=None`
resamples episodes one by one), recorded under `resampling` ({"unit", "n_units", "n_resamples", "seed"}).
Bounds are null with fewer than two participants. `n_scored` says over how many episodes each metric
that can be undefined was averaged (order_tau needs two matched objects, rotation_error a scored pair,
off_table_rate a placement, overlap_rate two; rmsd a non-failed prediction); `ground_truth` holds the
ground truth's own off-table and overlap rates over the same episodes (the reference for the
plausibility columns); `missing_fields` counts records that lacked a field (e.g. rotation) a metric
needs. `acceptable_at` maps "0.01", "0.05", "0.10" to the fraction of episodes whose prediction is
acceptable at t like for like (its unregistered set RMSD <= t: the kind of error the ratings were collected
with, metrics.ACCEPTABILITY_ERROR); `acceptable_at_paper` is the paper's variant (Kabsch RMSD <= t).
A failed or empty prediction has object accuracy 0, is not acceptable at any t
and is left out of the Kabsch and unregistered RMSD means (which is why failure_rate always stands
beside them); in the set_rmsd mean it counts as c = SET_PENALTY, the worst score.
`count_bias` is the mean of n_pred - n_gt with its interval (a failed prediction counts as 0 objects):
below 0 the method leaves objects out, above 0 it adds some. `degenerate` says whether the answers take a
shortcut and `degenerate_reasons` which ("too few", "padding", "constant": metrics.degenerate_answers,
from n_gt, n_pred, failed and each row's `answer_key`), with the share behind each reason in
`degenerate_fractions`; `frac_le2_matched` is the older few-matched share (metrics.few_matched_fraction),
one of the "too few" tests. `by_context` repeats the summary per context length when the episodes
span several. Methods that parse model text add `parse_rate` (answers parsed / sampled); a local model's
add `constrained` (decoded inside the answer grammar: labelled GRAMMAR_MARK), `forced_close_rate`
(answers the token budget closed early or cut off) and, constrained, `parse_rate_free`: the fraction of
its answers that free decoding (the same model and seeds, no grammar) writes parseably, the number to
set beside free-text parse rates such as the paper's.

Ranking (the one order every table and plot uses): non-degenerate methods by mean set_rmsd, lower
first, then the degenerate ones by the same key; ties keep the given order. `summarize` returns its
dict in that order; `rank_methods` / `ranked` apply it to any summary.

`paired_comparisons` gives the paired bootstrap differences between methods, resampled the same way
(participants by default) and with a p-value read off the same resamples as the interval, so a bold
"interval excludes 0" and p < 0.05 always agree (metrics/bootstrap.py).
"""

from __future__ import annotations

import itertools
import math
from collections import defaultdict

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.scoring import EpisodeRow
from degusta_learn.metrics import (
    ACCEPTABILITY_ERROR,
    PAPER_ACCEPTABILITY_ERROR,
    THRESHOLDS,
    bootstrap_ci,
    degenerate_answers,
    fraction_acceptable,
    paired_bootstrap,
)

PAPER_METRICS = ("object_accuracy", "rmsd", "rmsd_unregistered", "count_error", "set_rmsd")
PLAN_METRICS = ("object_precision", "object_f1", "set_rmsd_unregistered", "order_tau", "rotation_error",
                "off_table_rate", "overlap_rate")
"""The rest of the task plan (metrics/scores.py, docs/metrics.md "Task plan")."""
METRICS = PAPER_METRICS + PLAN_METRICS
MAY_BE_UNDEFINED = ("rmsd", "order_tau", "rotation_error", "off_table_rate", "overlap_rate")
"""Metrics that are nan on some episodes: `n_scored` counts the episodes each mean is taken over."""
PAIRED_METRICS = ("set_rmsd", "object_accuracy", "rmsd")
"""The metrics of the paired comparisons (the same as evaluate/compare.py's)."""
CLUSTERS = ("participant", None)
"""What the bootstrap resamples: participants (the default) or, with None, episodes."""
DEGENERATE_MARK = " (degenerate)"
"""The mark of a degenerate method whose reasons are not known (e.g. an older metrics.json); `degenerate_mark`
names the reasons."""
REASON_LABELS = {"too few": "too few objects", "padding": "too many objects", "constant": "constant answer"}
"""How a mark names each reason of metrics.degenerate_answers."""
GRAMMAR_MARK = " + grammar"
"""Appended to a method decoded inside the answer grammar: its parse rate is 1 by construction, so compare
its `parse_rate_free` (not its failure rate) with free-text methods and the paper."""
RANKING_NOTE = ("Methods are ranked by mean set RMSD (lower is better); degenerate methods come after all others, "
                "whatever their scores.")


def check_cluster(cluster) -> None:
    if cluster not in CLUSTERS:
        raise DegustaError(f"cluster: expected 'participant' (resample participants) or None (resample episodes), "
                           f"got {cluster!r}")


def clusters_of(rows: list[EpisodeRow], cluster: str | None) -> list[str] | None:
    """The bootstrap's cluster label of each row (its participant), or None for per-episode resampling."""
    check_cluster(cluster)
    return None if cluster is None else [r.participant for r in rows]


def _interval(values: np.ndarray, n_bootstrap: int, seed: int, clusters=None) -> dict:
    if not np.isfinite(values).any():
        return {"mean": None, "ci_low": None, "ci_high": None}
    mean, lo, hi = bootstrap_ci(values, n_resamples=n_bootstrap, seed=seed, clusters=clusters)
    return {"mean": _num(mean), "ci_low": _num(lo), "ci_high": _num(hi)}


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 6)


def _mean(values: list) -> float | None:
    x = np.array(values, dtype=float)
    x = x[np.isfinite(x)]
    return _num(float(x.mean())) if x.size else None


def resampling(rows: list[EpisodeRow], n_bootstrap: int, seed: int, cluster: str | None) -> dict:
    """What the intervals resampled: {"unit": "participant" | "episode", "n_units", "n_resamples", "seed"}."""
    check_cluster(cluster)
    n_units = len({r.participant for r in rows}) if cluster else len(rows)
    return {"unit": cluster or "episode", "n_units": n_units, "n_resamples": n_bootstrap, "seed": seed}


def summarize_rows(rows: list[EpisodeRow], n_bootstrap: int = 1000, seed: int = 0,
                   cluster: str | None = "participant") -> dict:
    """Summary of one method's rows (see module docstring)."""
    clusters = clusters_of(rows, cluster)
    out: dict = {"n_episodes": len(rows),
                 "failure_rate": round(sum(r.failed for r in rows) / len(rows), 6) if rows else None,
                 "resampling": resampling(rows, n_bootstrap, seed, cluster)}
    for name in METRICS:
        values = np.array([getattr(r, name) for r in rows], dtype=float)
        out[name] = _interval(values, n_bootstrap, seed, clusters)
    out["n_scored"] = {name: int(np.isfinite(np.array([getattr(r, name) for r in rows], dtype=float)).sum())
                       for name in MAY_BE_UNDEFINED}
    out["ground_truth"] = {"off_table_rate": _mean([r.gt_off_table_rate for r in rows]),
                           "overlap_rate": _mean([r.gt_overlap_rate for r in rows])}
    missing: dict[str, int] = {}
    for r in rows:
        for name in (r.missing or "").split():
            missing[name] = missing.get(name, 0) + 1
    if missing:
        out["missing_fields"] = missing
    out["count_bias"] = _interval(count_bias(rows), n_bootstrap, seed, clusters)
    scored = [r for r in rows if not r.failed]
    # Kabsch RMSD is ~0 by construction with 1-2 matched objects: say how often that happens.
    out["few_objects_rate"] = round(sum(r.n_matched <= 2 for r in scored) / len(scored), 6) if scored else None
    verdict = degenerate_answers([r.n_gt for r in rows], [r.n_pred for r in rows], [r.failed for r in rows],
                                 answer_keys=[r.answer_key for r in rows], participants=[r.participant for r in rows],
                                 n_matched=[r.n_matched for r in rows])
    out["frac_le2_matched"] = _num(verdict.few_matched_fraction)
    out["degenerate"] = verdict.degenerate
    out["degenerate_reasons"] = list(verdict.reasons)
    out["degenerate_fractions"] = verdict.fractions()
    for key, error in (("acceptable_at", ACCEPTABILITY_ERROR), ("acceptable_at_paper", PAPER_ACCEPTABILITY_ERROR)):
        errors = np.array([getattr(r, error) for r in rows], dtype=float)
        out[key] = {f"{t:.2f}": round(v, 6) for t, v in fraction_acceptable(errors, THRESHOLDS).items()}
    tokens = [r.tokens for r in rows if r.tokens is not None]
    costs = [r.cost_usd for r in rows if r.cost_usd is not None]
    if tokens:
        out["tokens_per_episode"] = round(float(np.mean(tokens)), 1)
    if costs:
        out["cost_usd_per_episode"] = round(float(np.mean(costs)), 6)
        out["cost_usd_total"] = round(float(np.sum(costs)), 6)
    out.update(_answer_rates(rows))
    return out


def count_bias(rows: list[EpisodeRow]) -> np.ndarray:
    """n_pred - n_gt per row, a failed prediction counting as 0 objects (E,)."""
    return np.array([(0 if r.failed else r.n_pred) - r.n_gt for r in rows], dtype=float)


def _answer_rates(rows: list[EpisodeRow]) -> dict:
    """parse_rate, constrained, forced_close_rate, parse_rate_free (module docstring); {} for methods that
    parse no model text."""
    def ratio(num: list, den: list) -> float | None:
        return round(sum(num) / sum(den), 6) if sum(den) else None

    out: dict = {}
    sampled = [r for r in rows if r.n_samples is not None and r.n_parsed is not None]
    if sampled:
        out["parse_rate"] = ratio([r.n_parsed for r in sampled], [r.n_samples for r in sampled])
        out["samples_per_episode"] = [min(r.n_samples for r in sampled), max(r.n_samples for r in sampled)]
    combined = {r.aggregation or "not recorded" for r in sampled if r.n_samples > 1}  # one answer: nothing combined
    if combined:  # a run's one choice; more than one: predictions files put together
        out["aggregation"] = " + ".join(sorted(combined))
    decoded = [r for r in rows if r.constrained is not None and r.n_decoded]
    if decoded:
        out["constrained"] = any(r.constrained for r in decoded)
        out["forced_close_rate"] = ratio([r.forced_closes or 0 for r in decoded], [r.n_decoded for r in decoded])
        if out["constrained"]:
            free = [r for r in decoded if r.n_free_known is not None and r.n_free_parsed is not None]
            out["parse_rate_free"] = ratio([r.n_free_parsed for r in free], [r.n_free_known for r in free])
    return out


def summarize(rows: list[EpisodeRow], n_bootstrap: int = 1000, seed: int = 0,
              cluster: str | None = "participant") -> dict[str, dict]:
    """{method: summary}, with `by_context` per method when several context lengths are present.

    `cluster`: "participant" (default) resamples participants for every interval, None resamples episodes.
    """
    check_cluster(cluster)
    by_method: dict[str, list[EpisodeRow]] = defaultdict(list)
    for r in rows:
        by_method[r.method].append(r)
    result = {}
    for method, mrows in by_method.items():
        summary = summarize_rows(mrows, n_bootstrap, seed, cluster)
        contexts = sorted({r.context for r in mrows if r.context is not None})
        if len(contexts) > 1:
            summary["by_context"] = {str(k): summarize_rows([r for r in mrows if r.context == k], n_bootstrap, seed,
                                                            cluster) for k in contexts}
        result[method] = summary
    return ranked(result)


def paired_comparisons(rows: list[EpisodeRow], methods: list[str], n_bootstrap: int = 1000, seed: int = 0,
                       cluster: str | None = "participant", metrics: tuple[str, ...] = PAIRED_METRICS) -> list[dict]:
    """Paired bootstrap differences (b - a) per metric for every pair of methods on their shared episodes.

    Pairs follow the order of `methods` (pass them ranked: a is then the better-ranked method). Each entry is
    {"a", "b", "resampling": {...}, metric: {"diff", "lo", "hi", "p_value"} or None (fewer than 2 complete
    pairs)}. With `cluster="participant"` participants are resampled with all their episodes; the p-value and
    the interval come from the same resamples (bold "excludes 0" <=> p < 0.05).
    """
    check_cluster(cluster)
    by = {m: {r.episode: r for r in rows if r.method == m} for m in methods}
    out = []
    for a, b in itertools.combinations(methods, 2):
        eps = sorted(set(by[a]) & set(by[b]))
        shared = [by[a][e] for e in eps]
        entry: dict = {"a": a, "b": b, "resampling": resampling(shared, n_bootstrap, seed, cluster)}
        for metric in metrics:
            va = np.array([getattr(by[a][e], metric) for e in eps], dtype=float)
            vb = np.array([getattr(by[b][e], metric) for e in eps], dtype=float)
            ok = np.isfinite(va) & np.isfinite(vb)
            labels = None if cluster is None else [r.participant for r, keep in zip(shared, ok) if keep]
            entry[metric] = (paired_bootstrap(vb[ok], va[ok], n_resamples=n_bootstrap, seed=seed,  # mean(b - a)
                                              clusters=labels) if ok.sum() >= 2 else None)
        out.append(entry)
    return out


def resampling_line(unit: str, n_units: int | None = None, n_resamples: int | None = None,
                    paired: bool = False) -> str:
    """The one line under a report's tables that says what the intervals (and paired tests) resampled."""
    tests = " and the paired tests" if paired else ""
    count = f"{n_resamples} resamples" if n_resamples else "resamples"
    if unit == "participant":
        who = f"the {n_units} participants" if n_units else "the participants"
        return (f"Intervals{tests}: 95% percentile bootstrap over participants ({count} of {who}, drawn with "
                "replacement, each with all of its episodes; the statistic is the mean over their episodes).")
    return (f"Intervals{tests}: 95% percentile bootstrap over episodes ({count}, episodes drawn one by one: "
            "per-episode resampling, which treats episodes of one participant as independent).")


def resampling_of(summary: dict[str, dict]) -> dict:
    """The `resampling` record shared by a summary's methods (the first method's; {} for an old summary)."""
    for s in summary.values():
        if isinstance(s.get("resampling"), dict):
            return s["resampling"]
    return {}


def rank_methods(summary: dict[str, dict]) -> list[str]:
    """Method names best first: non-degenerate by mean set_rmsd (lower first), then degenerate ones."""
    def key(item: tuple[int, str]) -> tuple:
        i, method = item
        mean = (summary[method].get("set_rmsd") or {}).get("mean")
        return bool(summary[method].get("degenerate")), mean is None, mean if mean is not None else 0.0, i

    return [m for _, m in sorted(enumerate(summary), key=key)]


def ranked(summary: dict[str, dict]) -> dict[str, dict]:
    """The same summary with its methods in rank order."""
    return {m: summary[m] for m in rank_methods(summary)}


def degenerate_mark(summary: dict) -> str:
    """The mark of a degenerate method naming its reasons, e.g. " (degenerate: too few objects)" (REASON_LABELS;
    a reason it does not know is left out), "" for a method that is not degenerate, DEGENERATE_MARK when the
    summary does not say why."""
    if not summary.get("degenerate"):
        return ""
    reasons = [REASON_LABELS[r] for r in summary.get("degenerate_reasons") or () if r in REASON_LABELS]
    return f" (degenerate: {', '.join(reasons)})" if reasons else DEGENERATE_MARK


def label(method: str, summary: dict) -> str:
    """The method's name as tables and plots show it: with GRAMMAR_MARK when it decoded inside the answer
    grammar, and its `degenerate_mark` when it is degenerate. Plain text: Markdown tables use report.md_label (the
    name escaped by textsafe.md_text), plots textsafe.plot_text."""
    name = method + GRAMMAR_MARK if summary.get("constrained") else method
    return name + degenerate_mark(summary)
