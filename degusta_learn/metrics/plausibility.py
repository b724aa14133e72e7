"""Physical plausibility of a set of placements: centroids off the table surface, overlapping footprints.

- `off_table_rate`: the share of the placements whose centroid lies outside the table's surface polygon
  (`Table.contains`, the even-odd rule of the dataset and the generators). The surface is where "object
  centroids may lie" (scene/tables.py), so a centroid outside it is an object set beside the table; a
  footprint that only overhangs the edge is not counted.
- `overlap_rate`: the share of the pairs of placed objects whose footprints overlap, i.e. pairs with

      area(F_i & F_j) / min(area(F_i), area(F_j)) > OVERLAP_FRACTION = 0.3

  where F is the object's footprint ellipse: width x length from `scene.object_size` (the box the
  renderer draws the sprite into), long axis along the placement's rotation (0 = north, clockwise),
  centred on the centroid. That is the footprint the generators keep apart (synth/geometry.py), and 0.3
  is their limit on ground truth (`synth.realize.MAX_OVERLAP`): on synthetic data the ground truth scores
  about 0, so a prediction's overlaps are its own; on human data (people may lay a knife on a plate) the
  ground truth's own rate, computed the same way, is the reference the reports show. A small overlap
  (objects touching, a fork tucked at a plate's rim) is not counted.

The area ratio is estimated on OVERLAP_SAMPLES points spread evenly over the smaller ellipse (a
sunflower lattice, deterministic): the fraction of them inside the other footprint. The error is about
one boundary ring of points, ~1-2% of the footprint's area (tests/test_metrics_plausibility.py checks the
exact lens area of two discs); pairs whose bounding circles do not meet are skipped without sampling.

Both are nan where they are undefined: `off_table_rate` for no placement (an empty or failed
prediction), `overlap_rate` for fewer than two (no pair). A report averages them over the episodes where
they are defined and says over how many.

Usage:
    from degusta_learn.metrics.plausibility import off_table_rates, overlap_rates, footprint_overlap
    off = off_table_rates([ds.tables[gt.table]], [xy])           # xy (N, 2) -> array([share])
    ovl = overlap_rates([xy], [rotations], [sizes])               # sizes (N, 2): object_size per object
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from degusta_learn.scene.tables import Table

OVERLAP_FRACTION = 0.3
"""A pair overlaps when more than this fraction of the smaller footprint is covered by the other."""
OVERLAP_SAMPLES = 512
"""Sample points per footprint ellipse for the overlap estimate."""

_GOLDEN = math.pi * (3.0 - math.sqrt(5.0))
_I = np.arange(OVERLAP_SAMPLES) + 0.5
_DISC = np.stack([np.sqrt(_I / OVERLAP_SAMPLES) * np.cos(_I * _GOLDEN),
                  np.sqrt(_I / OVERLAP_SAMPLES) * np.sin(_I * _GOLDEN)], axis=1)  # (S, 2), uniform in the unit disc
_PAIR_CHUNK = 2048  # pairs sampled at once (2048 * 512 points)


def _axes(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Width-axis and long-axis unit vectors (..., 2) for rotations in degrees (0 = long axis north, y down)."""
    r = np.radians(rot)
    return np.stack([np.cos(r), np.sin(r)], -1), np.stack([np.sin(r), -np.cos(r)], -1)


def _inside_fraction(xy_a, rot_a, size_a, xy_b, rot_b, size_b) -> np.ndarray:
    """(P,) fraction of ellipse a's sample points inside ellipse b, for P pairs."""
    wa, la = _axes(rot_a)  # (P, 2)
    wb, lb = _axes(rot_b)
    # Sample point k of a, relative to b's centre, in b's axes scaled to b's semi-axes: u = (c + s_k) . w_b / h_b.
    # s_k = du_k * ha_w * wa + dv_k * ha_l * la, so each coordinate is affine in the disc coordinates (du_k, dv_k).
    c = xy_a - xy_b
    ha, hb = size_a / 2, size_b / 2
    u0, v0 = (c * wb).sum(-1) / hb[:, 0], (c * lb).sum(-1) / hb[:, 1]  # (P,)
    uu, uv = ha[:, 0] * (wa * wb).sum(-1) / hb[:, 0], ha[:, 1] * (la * wb).sum(-1) / hb[:, 0]
    vu, vv = ha[:, 0] * (wa * lb).sum(-1) / hb[:, 1], ha[:, 1] * (la * lb).sum(-1) / hb[:, 1]
    du, dv = _DISC[:, 0], _DISC[:, 1]  # (S,)
    u = u0[:, None] + uu[:, None] * du + uv[:, None] * dv  # (P, S)
    v = v0[:, None] + vu[:, None] * du + vv[:, None] * dv
    return (u * u + v * v <= 1.0).mean(-1)


def footprint_overlap(xy_a, rot_a, size_a, xy_b, rot_b, size_b) -> np.ndarray:
    """Estimated area(F_a & F_b) / min(area F_a, area F_b) for P pairs of footprints: xy (P, 2), rot (P,),
    size (P, 2) width x length -> (P,) in [0, 1]: the fraction of the smaller footprint's sample points that lie
    inside the other (either one's for equal areas)."""
    args = [np.asarray(a, dtype=float) for a in (xy_a, rot_a, size_a, xy_b, rot_b, size_b)]
    xy_a, rot_a, size_a, xy_b, rot_b, size_b = (a.reshape(-1, 2) if i % 3 != 1 else a.reshape(-1)
                                                for i, a in enumerate(args))
    swap = size_a.prod(1) > size_b.prod(1)  # sample the smaller footprint
    sw = swap[:, None]
    xy_s, xy_l = np.where(sw, xy_b, xy_a), np.where(sw, xy_a, xy_b)
    rot_s, rot_l = np.where(swap, rot_b, rot_a), np.where(swap, rot_a, rot_b)
    size_s, size_l = np.where(sw, size_b, size_a), np.where(sw, size_a, size_b)
    out = np.empty(len(xy_a))
    for s in range(0, len(xy_a), _PAIR_CHUNK):
        sl = slice(s, s + _PAIR_CHUNK)
        out[sl] = _inside_fraction(xy_s[sl], rot_s[sl], size_s[sl], xy_l[sl], rot_l[sl], size_l[sl])
    return out


def overlap_rates(xys: Sequence, rots: Sequence, sizes: Sequence,
                  threshold: float = OVERLAP_FRACTION) -> np.ndarray:
    """Per episode, the share of pairs of placed objects whose footprints overlap (module docstring).

    Args:
        xys: per episode, (N, 2) centroids.
        rots: per episode, (N,) rotations in degrees.
        sizes: per episode, (N, 2) footprints (width, length), `scene.object_size` of each object.
        threshold: a pair overlaps when its footprint_overlap exceeds this.

    Returns:
        (E,) shares in [0, 1]; nan where an episode has fewer than two objects.
    """
    n_ep = len(xys)
    out = np.full(n_ep, np.nan)
    by_n: dict[int, list[int]] = {}
    for e in range(n_ep):
        by_n.setdefault(len(xys[e]), []).append(e)
    for n, eps in by_n.items():  # episodes with n objects at once
        if n < 2:
            continue
        xy = np.array([xys[e] for e in eps], dtype=float).reshape(len(eps), n, 2)
        rot = np.array([rots[e] for e in eps], dtype=float).reshape(len(eps), n)
        size = np.array([sizes[e] for e in eps], dtype=float).reshape(len(eps), n, 2)
        i, j = np.triu_indices(n, 1)
        radius = size.max(-1) / 2  # bounding circles: footprints whose circles do not meet cannot overlap
        d = xy[:, i] - xy[:, j]  # (E, P, 2)
        near = (d * d).sum(-1) < (radius[:, i] + radius[:, j]) ** 2  # (E, P)
        hits = np.zeros(near.shape)
        if near.any():
            e_idx, p_idx = np.nonzero(near)
            a, b = i[p_idx], j[p_idx]
            hits[e_idx, p_idx] = footprint_overlap(xy[e_idx, a], rot[e_idx, a], size[e_idx, a],
                                                   xy[e_idx, b], rot[e_idx, b], size[e_idx, b]) > threshold
        out[eps] = hits.sum(1) / len(i)
    return out


def off_table_rates(tables: Sequence[Table | None], xys: Sequence) -> np.ndarray:
    """Per episode, the share of placements whose centroid is outside the table's surface polygon.

    Args:
        tables: per episode, the table the placements are on (None: unknown, gives nan).
        xys: per episode, (N, 2) centroids.

    Returns:
        (E,) shares in [0, 1]; nan where an episode has no placement or no table.
    """
    out = np.full(len(xys), np.nan)
    by_table: dict[int, tuple[Table, list[int]]] = {}
    for e, (table, xy) in enumerate(zip(tables, xys)):
        if table is not None and len(xy):
            by_table.setdefault(id(table), (table, []))[1].append(e)
    for table, eps in by_table.values():  # one point-in-polygon call per table
        pts = [np.asarray(xys[e], dtype=float).reshape(-1, 2) for e in eps]
        flat = np.concatenate(pts)
        outside = ~table.contains(flat[:, 0], flat[:, 1])
        counts = np.array([len(p) for p in pts])
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        out[eps] = np.add.reduceat(outside.astype(float), starts) / counts
    return out
