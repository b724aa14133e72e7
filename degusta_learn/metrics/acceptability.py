"""Acceptability: how small an RMSD people accept, and how many of a method's predictions are that close.

From the paper's jitter study: a participant rated their own arrangement (b_initial, 0..100) and a
jittered copy of it (b_jitter) that lies `rmsd_jitter` away. At threshold t, the acceptability is the
fraction of jitter trials with rmsd_jitter <= t whose normalized rating drop (b_initial - b_jitter) / 100
is below `drop_threshold` (0.2). The paper reports 0.727, 0.333 and 0.199 at t = 0.01, 0.05, 0.10
(`PAPER_ACCEPTABILITY`); without ratings those three points are the default curve.

For a method, `fraction_acceptable` gives the fraction of its predictions whose error is <= t; a nan error
(failed or empty prediction) counts as not acceptable. Which error (docs/metrics.md, "Acceptability"):

- like for like (`ACCEPTABILITY_ERROR`, the default every report leads with): the ratings were collected
  against the *unregistered* displacement of a complete scene (every object present, moved rigidly), so a
  prediction is judged by its unregistered set RMSD (`set_rmsd_unregistered`): it equals the unregistered
  RMSD when the prediction places as many objects as the ground truth and no matched pair is more than
  SET_PENALTY away, and charges SET_PENALTY for every object missing or extra (a scene the raters never saw).
- the paper's (`PAPER_ACCEPTABILITY_ERROR`): Kabsch RMSD over the matched pairs, which removes exactly the
  rigid motion the jitter applied and is ~0 for one or two matched objects; kept, labelled "(paper)".

The paper's GPT-4o MOGMA reaches 0.145, 0.332 and 0.532 on its variant (`PAPER_MOGMA_FRACTION`).

Usage:
    from degusta_learn.metrics import acceptability_curve, fraction_acceptable
    acceptability_curve(ds.ratings)            # {0.01: ..., 0.05: ..., 0.1: ...}
    fraction_acceptable([s.set_rmsd_unregistered for s in scores])     # like for like (the default)
    fraction_acceptable([s.rmsd for s in scores])                      # the paper's variant
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.scene.types import Rating

THRESHOLDS = (0.01, 0.05, 0.10)
ACCEPTABILITY_ERROR = "set_rmsd_unregistered"
"""The per-episode score "acceptable at t" reads by default: the same kind of error as the ratings' (see above)."""
PAPER_ACCEPTABILITY_ERROR = "rmsd"
"""The paper's variant: Kabsch RMSD over the matched pairs."""
PAPER_ACCEPTABILITY = {0.01: 0.727, 0.05: 0.333, 0.10: 0.199}
PAPER_MOGMA_FRACTION = {0.01: 0.145, 0.05: 0.332, 0.10: 0.532}


def _paper_point(t: float) -> float:
    for key, value in PAPER_ACCEPTABILITY.items():
        if math.isclose(t, key, rel_tol=1e-9, abs_tol=1e-12):
            return value
    raise DegustaError(f"acceptability threshold {t}: the paper only reports "
                       f"{', '.join(str(k) for k in PAPER_ACCEPTABILITY)} (give ratings for other thresholds)")


def acceptability_curve(ratings: Sequence[Rating] | None, thresholds: Iterable[float] = THRESHOLDS,
                        drop_threshold: float = 0.2) -> dict[float, float]:
    """Fraction of jitter trials within each RMSD threshold whose rating drop stays below `drop_threshold`.

    Args:
        ratings: jitter-study ratings; None or empty -> the paper's points (`PAPER_ACCEPTABILITY`).
        thresholds: RMSD thresholds t.
        drop_threshold: a normalized drop (b_initial - b_jitter) / 100 below this is "acceptable".

    Returns:
        {t: fraction}; nan where no trial has rmsd_jitter <= t.
    """
    thresholds = tuple(thresholds)
    if not ratings:
        return {t: _paper_point(t) for t in thresholds}
    rmsd = np.array([r.rmsd_jitter for r in ratings], dtype=float)
    ok = np.array([r.drop for r in ratings], dtype=float) < drop_threshold
    out = {}
    for t in thresholds:
        within = rmsd <= t
        out[t] = float(ok[within].mean()) if within.any() else float("nan")
    return out


def fraction_acceptable(rmsds: Iterable[float], thresholds: Iterable[float] = THRESHOLDS) -> dict[float, float]:
    """Fraction of a method's predictions whose error is <= t, per threshold (nan = not acceptable): pass each
    episode's `ACCEPTABILITY_ERROR` (or, for the paper's variant, its Kabsch RMSD).

    Returns:
        {t: fraction}; nan for an empty input.
    """
    r = np.asarray(list(rmsds), dtype=float)
    return {t: float((r <= t).mean()) if r.size else float("nan") for t in thresholds}
