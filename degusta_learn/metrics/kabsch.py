"""2D Kabsch RMSD (proper rotation + translation, never a reflection) and unregistered RMSD.

The Kabsch algorithm finds the rotation R and translation t that minimize the RMSD between matched
ground-truth points p_i and predicted points q_i, i.e. `sum |R q_i + t - p_i|^2`. The optimal t moves
the prediction's centroid onto the ground truth's. In 2D the SVD of the 2x2 covariance, with the usual
det(U V^T) sign correction that rules out reflections, reduces to a closed form: for centred points the
best proper rotation angle is

    theta = atan2(sum(qx * py - qy * px), sum(qx * px + qy * py))

which is what this module computes: no SVD per call; `kabsch_rmsd` works on Python floats (a few
microseconds for a handful of points), `kabsch_rmsd_batch` vectorizes over episodes with numpy.
Residuals are then taken explicitly after rotating, so aligned inputs give ~1e-16, not the ~1e-8 of the
cancellation-prone `sum|p|^2 + sum|q|^2 - 2 |S|` formula. A mirrored arrangement is NOT aligned by a
reflection: the angle parameterization only contains proper rotations.

Caveat (say it wherever RMSD is reported): Kabsch RMSD alone rewards predicting one or two objects:
N = 1 always gives 0, N = 2 only compares the two distances. That is why the unregistered RMSD (no
alignment), the count error and the set-aware `set_rmsd` (scores.py, per-pair distances from
`kabsch_sq_residuals_*`) stand beside it. N = 0 gives nan.

Usage:
    from degusta_learn.metrics import kabsch_rmsd, unregistered_rmsd
    kabsch_rmsd(gt_xy, pred_xy)        # (N, 2), (N, 2) matched rows -> float
"""

from __future__ import annotations

import math

import numpy as np


def _as_pairs(gt_xy, pred_xy) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(gt_xy, dtype=float).reshape(-1, 2)
    q = np.asarray(pred_xy, dtype=float).reshape(-1, 2)
    if p.shape != q.shape:
        raise ValueError(f"matched point sets differ in size: {p.shape} vs {q.shape}")
    return p, q


def kabsch_sq_residuals_batch(gt_xy: np.ndarray, pred_xy: np.ndarray) -> np.ndarray:
    """Squared per-pair distances after the Kabsch registration, for E episodes with the same N.

    Args:
        gt_xy: (E, N, 2) ground-truth points.
        pred_xy: (E, N, 2) matched predicted points.

    Returns:
        (E, N) |R q_i + t - p_i|^2 with the best proper rotation R and translation t of each episode.
    """
    n = gt_xy.shape[1]
    if n == 0:
        return np.zeros((gt_xy.shape[0], 0))
    pc = gt_xy - gt_xy.sum(axis=1, keepdims=True) / n  # (E, N, 2) centred
    qc = pred_xy - pred_xy.sum(axis=1, keepdims=True) / n
    px, py, qx, qy = pc[..., 0], pc[..., 1], qc[..., 0], qc[..., 1]  # (E, N)
    theta = np.arctan2((qx * py - qy * px).sum(1), (qx * px + qy * py).sum(1))  # (E,)
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    rx, ry = c * qx - s * qy - px, s * qx + c * qy - py  # residuals of the rotated prediction
    return rx * rx + ry * ry


def kabsch_rmsd_batch(gt_xy: np.ndarray, pred_xy: np.ndarray) -> np.ndarray:
    """Kabsch RMSD of E episodes with the same N at once.

    Args:
        gt_xy: (E, N, 2) ground-truth points.
        pred_xy: (E, N, 2) matched predicted points.

    Returns:
        (E,) RMSD after the best proper rotation + translation; nan where N = 0.
    """
    n = gt_xy.shape[1]
    if n == 0:
        return np.full(gt_xy.shape[0], np.nan)
    return np.sqrt(kabsch_sq_residuals_batch(gt_xy, pred_xy).sum(1) / n)


def kabsch_transform(gt_xy, pred_xy) -> tuple[np.ndarray, np.ndarray]:
    """The best proper rotation R (2, 2) and translation t (2,) with `pred_xy @ R.T + t ~ gt_xy`.

    det(R) = +1 always. For N = 0 returns the identity and zero translation.
    """
    p, q = _as_pairs(gt_xy, pred_xy)
    if len(p) == 0:
        return np.eye(2), np.zeros(2)
    pm, qm = p.mean(0), q.mean(0)
    pc, qc = p - pm, q - qm
    theta = np.arctan2((qc[:, 0] * pc[:, 1] - qc[:, 1] * pc[:, 0]).sum(), (qc * pc).sum())
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    return rot, pm - rot @ qm


def kabsch_sq_residuals_points(p: list[list[float]], q: list[list[float]]) -> list[float]:
    """Squared per-pair distances after the Kabsch registration (pure Python, the closed form above)."""
    n = len(p)
    if n == 0:
        return []
    pmx, pmy = sum(a[0] for a in p) / n, sum(a[1] for a in p) / n
    qmx, qmy = sum(b[0] for b in q) / n, sum(b[1] for b in q) / n
    pc = [(a[0] - pmx, a[1] - pmy) for a in p]
    qc = [(b[0] - qmx, b[1] - qmy) for b in q]
    dot = cross = 0.0
    for (px, py), (qx, qy) in zip(pc, qc):
        dot += qx * px + qy * py
        cross += qx * py - qy * px
    theta = math.atan2(cross, dot)
    c, s = math.cos(theta), math.sin(theta)
    out = []
    for (px, py), (qx, qy) in zip(pc, qc):
        rx, ry = c * qx - s * qy - px, s * qx + c * qy - py
        out.append(rx * rx + ry * ry)
    return out


def kabsch_rmsd_points(p: list[list[float]], q: list[list[float]]) -> float:
    """Kabsch RMSD of two equally long lists of [x, y] (pure Python, the closed form above)."""
    if not p:
        return float("nan")
    return math.sqrt(sum(kabsch_sq_residuals_points(p, q)) / len(p))


def kabsch_rmsd(gt_xy, pred_xy) -> float:
    """RMSD between matched point sets after the best proper 2D rotation and translation.

    Args:
        gt_xy: (N, 2) ground-truth positions.
        pred_xy: (N, 2) predicted positions, row i matched to row i of gt_xy.

    Returns:
        The minimum RMSD in the points' units; nan for N = 0, 0.0 for N = 1.
    """
    p, q = _as_pairs(gt_xy, pred_xy)
    return kabsch_rmsd_points(p.tolist(), q.tolist())


def unregistered_rmsd(gt_xy, pred_xy) -> float:
    """Plain RMSD between matched positions, no alignment (nan for N = 0)."""
    p, q = _as_pairs(gt_xy, pred_xy)
    if len(p) == 0:
        return float("nan")
    d = p - q
    return float(np.sqrt((d * d).sum() / len(p)))
