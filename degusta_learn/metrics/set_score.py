"""The set-aware score `set_rmsd` and the few-matched rule: what Kabsch RMSD cannot see.

Kabsch RMSD is taken over the N = min(n_gt, n_pred) matched pairs only, so predicting one object gives
0 and two nearly 0. `set_rmsd` is an OSPA distance (Optimal Sub-Pattern Assignment, Schuhmacher,
Vo & Vo 2008, order p = 2, cut-off c) on top of the same matching and the same Kabsch registration:

    set_rmsd = sqrt( (sum_i min(d_i, c)^2 + c^2 * |n_gt - n_pred|) / max(n_gt, n_pred) )

where d_i is the distance of matched pair i after the best proper rotation + translation of the
matched pairs (exactly the registration behind `rmsd`). Every object, matched or not, contributes
one term of at most c^2, so the score lies in [0, c]: 0 for a perfect prediction (up to a rigid
motion), c for a failed or empty one, and at least c * sqrt(|n_gt - n_pred| / max(n_gt, n_pred))
whatever the positions (one object of five: sqrt(4/5) * c ~ 0.179, never ~0).

c = SET_PENALTY = 0.2 normalized image units: an object further than 0.2 of the image from where it
belongs counts as badly as a missing one. Random placement's Kabsch RMSD is ~0.22 on the default
data, so c sits at "no better than chance" and an unmatched object costs what a random guess costs.

`few_matched_fraction` counts how often a method's scored predictions match at most 2 objects of a
ground truth of 3 or more, where Kabsch RMSD is ~0 by construction: one of the "too few" tests of
metrics/degenerate.py, which decides whether a method is degenerate.

Usage:
    from degusta_learn.metrics import SET_PENALTY, few_matched_fraction
    s = score_prediction(catalog, gt, placements)          # s.set_rmsd in [0, SET_PENALTY]
    frac, degenerate = few_matched_fraction(n_gt, n_matched, failed)
"""

from __future__ import annotations

import math

import numpy as np

SET_PENALTY = 0.2
"""c, the cost of one unmatched object (and the cap on a matched pair's distance), image units."""
DEGENERATE_FRACTION = 0.5
"""A degeneracy reason applies when more than this fraction of a method's scored predictions show it
(metrics/degenerate.py; here: match <= 2 objects of >= 3)."""


def set_rmsd_points(sq_residuals: list[float], n_gt: int, n_pred: int, c: float = SET_PENALTY) -> float:
    """OSPA-style set RMSD of one episode (pure Python).

    Args:
        sq_residuals: squared registered distances of the matched pairs (min(n_gt, n_pred) values).
        n_gt: ground-truth objects.
        n_pred: predicted objects (0 for a failed prediction).
        c: the penalty per unmatched object and cap per matched pair.

    Returns:
        The score in [0, c]; nan for an empty ground truth.
    """
    if n_gt == 0:
        return math.nan
    c2 = c * c
    total = sum(min(r, c2) for r in sq_residuals) + c2 * abs(n_gt - n_pred)
    return math.sqrt(total / max(n_gt, n_pred))


def set_rmsd_batch(sq_residuals: np.ndarray, n_gt: int, n_pred: int, c: float = SET_PENALTY) -> np.ndarray:
    """`set_rmsd_points` for E episodes sharing n_gt > 0 and n_pred: sq_residuals (E, min(n_gt, n_pred)) -> (E,)."""
    c2 = c * c
    total = np.minimum(sq_residuals, c2).sum(1) + c2 * abs(n_gt - n_pred)
    return np.sqrt(total / max(n_gt, n_pred))


def few_matched_fraction(n_gt, n_matched, failed, min_gt: int = 3, max_matched: int = 2,
                         threshold: float = DEGENERATE_FRACTION) -> tuple[float | None, bool]:
    """How often a method matches at most `max_matched` objects of a ground truth of `min_gt` or more.

    Counted over the episodes whose ground truth has >= `min_gt` objects and whose prediction did not
    fail: a failure is not a few-object answer (it scores c in `set_rmsd` and shows in the failure rate).

    Args:
        n_gt, n_matched, failed: one value per episode (sequences or arrays of equal length).
        min_gt: ground truths smaller than this are left out (2 matched of 2 is a full answer).
        max_matched: "few" means at most this many matched objects.
        threshold: degenerate when the fraction is strictly above this.

    Returns:
        (fraction, degenerate); (None, False) when no episode counts.
    """
    n_gt, n_matched = np.asarray(n_gt, dtype=int), np.asarray(n_matched, dtype=int)
    counted = (n_gt >= min_gt) & ~np.asarray(failed, dtype=bool)
    if not counted.any():
        return None, False
    frac = float((n_matched[counted] <= max_matched).mean())
    return frac, frac > threshold
