"""Task-plan metrics over the matched pairs: placement-order agreement and symmetry-aware rotation error.

- `order_tau`: Kendall's tau between the ground truth's and the prediction's placement order (list order)
  of the matched pairs: (concordant - discordant) / (k (k - 1) / 2) over the k matched pairs. Both
  orders are positions in a list, so there are no ties and tau-a = tau-b = scipy's `kendalltau`. 1: the
  matched objects are placed in the same order, -1: in reverse. Fewer than two matched pairs (one
  object, an empty or failed prediction) have no order to compare: nan, left out of the mean (a report
  counts the episodes it was taken over). Not 0: 0 means "as many pairs in order as out of order", a
  claim about a prediction that made none; nor 1: a one-object answer would then earn perfect order.
- `rotation_error`: mean over the matched pairs of the angle (degrees) between the predicted and the
  true rotation, modulo the pair's rotational symmetry. An object of symmetry order s looks the same
  after a turn of 360 / s degrees (s = 1: no symmetry, a knife; s = 0: any turn, a round plate), so
  its error is the circular difference modulo 360 / s, folded into [0, 180 / s]. A pair of two objects
  (a fork matched to a knife, a round plate to a square one) uses the symmetry both share:
  s = lcm(s_gt, s_pred), and 0 when either is fully symmetric (not scored). Pairs that are not scored
  are left out of the mean; an episode with no scored pair has nan (`n_rotation_scored` counts the
  scored pairs). Rotations are compared in the image frame, unregistered: a plan says how each object
  is turned on this table, and the Kabsch turn of the matched positions is not the objects' own.

Symmetry comes from the catalog: each object's type and `shape` (`symmetry_order`), read against
`SHAPE_SYMMETRY`, then `TYPE_SYMMETRY`, then `UNKNOWN_SYMMETRY`. It is the symmetry of the outline the
renderer draws (render/shapes.py), not of the surface pattern: a round plate (any pattern) is fully
symmetric; a square plate has order 4, an octagonal one 8, an oval one 2; a cup has order 1, because
every cup is drawn with a handle that points where the cup points (and the generators give cups a
person-specific turn); forks, knives and spoons have order 1. A type the design does not know (a
dataset's meta.json may add classes) is drawn as a rounded square: order 4.

Usage:
    from degusta_learn.metrics.plan import kendall_tau, rotation_errors, symmetry_order
    kendall_tau([0, 2, 1])                            # (2 concordant - 1 discordant) / 3 = 0.333
    rotation_errors([10.0], [350.0], [1])             # [20.0]
"""

from __future__ import annotations

import math

import numpy as np

from degusta_learn.scene.catalog import CatalogObject

FULL = 0
"""Symmetry order of an object that looks the same after any turn (its rotation is not scored)."""

SHAPE_SYMMETRY: dict[tuple[str, str], int] = {
    ("plate", "round"): FULL,
    ("plate", "square"): 4,
    ("plate", "oval"): 2,
    ("plate", "octagonal"): 8,
}
"""Symmetry order by (type, shape) where a type's shapes differ (render/shapes.py draws each)."""

TYPE_SYMMETRY: dict[str, int] = {
    "plate": FULL,  # any other plate shape is drawn round
    "cup": 1,  # the handle points where the cup points
    "fork": 1,  # tines north at rotation 0
    "knife": 1,  # blade tip north
    "spoon": 1,  # bowl north
}
"""Symmetry order by type, for every type of `scene.TYPES` (tests/test_metrics_plan.py checks)."""

UNKNOWN_SYMMETRY = 4
"""A type outside TYPE_SYMMETRY is drawn as a rounded square (render/shapes.generic)."""


def symmetry_order(obj: CatalogObject) -> int:
    """Rotational symmetry order of a catalog object: 0 = any turn, s = every 360 / s degrees."""
    found = SHAPE_SYMMETRY.get((obj.type, obj.shape))
    if found is not None:
        return found
    return TYPE_SYMMETRY.get(obj.type, UNKNOWN_SYMMETRY)


def pair_symmetry(order_gt, order_pred) -> np.ndarray:
    """The symmetry two matched objects share: lcm of their orders, 0 (not scored) when either is 0."""
    return np.lcm(np.asarray(order_gt, dtype=np.int64), np.asarray(order_pred, dtype=np.int64))


def rotation_errors(rot_gt, rot_pred, order) -> np.ndarray:
    """Per-pair rotation error in degrees modulo symmetry (any shape; broadcasts); nan where order is 0.

    For order s > 0 the error is min(d, 360 / s - d) with d = |rot_pred - rot_gt| mod 360 / s: in [0, 180 / s].
    """
    order = np.asarray(order, dtype=np.int64)
    period = 360.0 / np.where(order > 0, order, 1)
    d = np.mod(np.abs(np.asarray(rot_pred, dtype=float) - np.asarray(rot_gt, dtype=float)), period)
    err = np.minimum(d, period - d)
    return np.where(order > 0, err, np.nan)


def mean_rotation_error(rot_gt, rot_pred, order) -> tuple[np.ndarray, np.ndarray]:
    """(mean error, scored pairs) over the last axis: (..., k) -> (...), (...); nan where nothing is scored."""
    err = rotation_errors(rot_gt, rot_pred, order)
    scored = np.isfinite(err)
    n = scored.sum(-1)
    total = np.where(scored, err, 0.0).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, total / np.maximum(n, 1), np.nan)
    return mean, n


def kendall_tau_batch(pred_idx: np.ndarray) -> np.ndarray:
    """Kendall's tau of E episodes with k matched pairs each: (E, k) prediction positions, listed in ground-truth
    order (ascending ground-truth position, as `linear_sum_assignment` returns them) -> (E,); nan for k < 2."""
    pred_idx = np.asarray(pred_idx)
    k = pred_idx.shape[-1]
    if k < 2:
        return np.full(pred_idx.shape[:-1], np.nan)
    later = pred_idx[..., None, :] - pred_idx[..., :, None]  # [i, j] = pred[j] - pred[i]
    upper = np.triu(np.ones((k, k), dtype=bool), 1)  # i < j: j comes later in the ground truth
    return np.sign(later)[..., upper].sum(-1) / (k * (k - 1) / 2)


def kendall_tau(pred_idx, gt_idx=None) -> float:
    """Kendall's tau between the ground-truth and predicted positions of k matched pairs; nan for k < 2.

    Args:
        pred_idx: each pair's position in the prediction's placement order.
        gt_idx: each pair's position in the ground truth's order (default: 0, 1, 2, ..., i.e. pred_idx is
            already listed in ground-truth order). Positions are distinct (list positions).
    """
    p = np.asarray(pred_idx, dtype=float).ravel()
    if gt_idx is not None:
        g = np.asarray(gt_idx, dtype=float).ravel()
        if g.shape != p.shape:
            raise ValueError(f"kendall_tau: {g.size} ground-truth positions vs {p.size} predicted")
        p = p[np.argsort(g, kind="stable")]
    value = float(kendall_tau_batch(p[None])[0])
    return value if math.isfinite(value) else math.nan
