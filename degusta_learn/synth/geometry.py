"""Geometry for the generators and baselines: surface-relative coordinates, footprints, fitting, overlap.

- `to_table` / `to_relative`: positions relative to a table surface's bounding box (u, v in [0, 1]) and
  back; this is how a layout transfers between tables of different shape and size.
- `footprint_points`: points on each object's footprint ellipse (width x length from
  `scene.object_size`, rotation 0 = long axis to image north), used to keep footprints on the surface.
- `fit_into`: moves a layout toward the table centre (then shrinks its spacing) until every footprint
  lies on the surface; if no such move exists, until every centroid does.
- `max_overlap`: the largest fraction of one object's footprint covered by another's.

All functions are vectorized numpy; the point-in-polygon rule is the even-odd rule of `Table.contains`.
"""

from __future__ import annotations

import functools

import numpy as np

from degusta_learn.scene import TYPE_SIZE, Table

_EPS = 1e-9  # smallest surface extent divided by (degenerate surfaces only)
_PHI = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)  # footprint boundary samples
# Interior + boundary samples of a unit disc, for overlap estimates: (17, 2)
_DISC = np.concatenate([[[0.0, 0.0]], 0.55 * np.c_[np.cos(_PHI), np.sin(_PHI)],
                        0.9 * np.c_[np.cos(_PHI + np.pi / 8), np.sin(_PHI + np.pi / 8)]])


# fit_into's candidate moves, in the order tried: (scale, shift) batches of shape (C, 1, 1)
_CANDIDATES = [(np.ones((k, 1, 1)), np.linspace(lo, hi, k).reshape(-1, 1, 1)) for lo, hi, k in ((0.1, 0.3, 3), (0.4, 1.0, 7))]
_CANDIDATES.append(tuple(a.reshape(-1, 1, 1) for a in np.meshgrid([0.9, 0.8, 0.7, 0.6, 0.5], np.linspace(0.1, 1, 10),
                                                                   indexing="ij")))


def sizes_of(types: list[str]) -> np.ndarray:
    """(N, 2) footprint (width, length) per object type."""
    return np.array([TYPE_SIZE.get(t, TYPE_SIZE["cup"]) for t in types], dtype=float).reshape(-1, 2)


def bounds(table: Table) -> tuple[float, float, float, float]:
    """`table.bounds`, cached per surface."""
    return _bounds(table.surface)


@functools.lru_cache(maxsize=64)
def _bounds(surface: tuple) -> tuple[float, float, float, float]:
    pts = np.asarray(surface, dtype=float)
    return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max())


def to_table(table: Table, uv: np.ndarray) -> np.ndarray:
    """Surface-relative (u, v) -> table image coordinates; (..., 2) -> (..., 2)."""
    x0, y0, x1, y1 = bounds(table)
    return np.asarray(uv, dtype=float) * [x1 - x0, y1 - y0] + [x0, y0]


def to_relative(table: Table, xy: np.ndarray) -> np.ndarray:
    """Table image coordinates -> surface-relative (u, v); (..., 2) -> (..., 2)."""
    x0, y0, x1, y1 = bounds(table)
    # A degenerate surface (zero width or height; load_dataset rejects those) maps to u or v = 0, not inf/NaN.
    return (np.asarray(xy, dtype=float) - [x0, y0]) / [max(x1 - x0, _EPS), max(y1 - y0, _EPS)]


@functools.lru_cache(maxsize=64)
def _edges(surface: tuple) -> tuple[np.ndarray, ...]:
    poly = np.asarray(surface, dtype=float)
    xa, ya = poly[:, 0], poly[:, 1]
    xb, yb = np.roll(xa, -1), np.roll(ya, -1)
    return xa, ya, yb, xb - xa, yb - ya


def inside(table: Table, pts: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test of (..., 2) points on the table surface -> (...) bool."""
    pts = np.asarray(pts, dtype=float)
    flat = pts.reshape(-1, 2)
    xa, ya, yb, dx, dy = _edges(table.surface)
    x, y = flat[:, :1], flat[:, 1:]  # (M, 1)
    crosses = (ya > y) != (yb > y)  # (M, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = xa + (y - ya) * dx / dy  # the same float operations as Table.contains
    hits = np.count_nonzero(crosses & (x < x_at), axis=1)
    return (hits % 2 == 1).reshape(pts.shape[:-1])


def _axes(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Width axis and long axis unit vectors (N, 2) for rotations in degrees (0 = long axis north)."""
    r = np.radians(rot)
    return np.stack([np.cos(r), np.sin(r)], -1), np.stack([np.sin(r), -np.cos(r)], -1)


def footprint_points(xy: np.ndarray, rot: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(N, 8, 2) points on each object's footprint ellipse."""
    w_ax, l_ax = _axes(rot)
    a = (sizes[:, 0] / 2)[:, None, None] * np.cos(_PHI)[None, :, None] * w_ax[:, None, :]
    b = (sizes[:, 1] / 2)[:, None, None] * np.sin(_PHI)[None, :, None] * l_ax[:, None, :]
    return xy[:, None, :] + a + b


def fit_into(table: Table, xy: np.ndarray, rot: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Shift (then shrink) a layout toward the table centre until it lies on the surface.

    Tries, in order, shifts of 10%, 20%, ... 100% of the way from the layout's box centre to the surface
    centre at full spacing, then the same shifts with spacing shrunk to 90%, 80%, ... 50%, and takes the
    first candidate whose footprints all lie on the surface; failing that, the first whose centroids do;
    failing that, each centroid is pulled to the surface centre until it is on the surface.
    Deterministic. Returns the new (N, 2) positions.
    """
    xy = np.asarray(xy, dtype=float)
    offsets = footprint_points(np.zeros_like(xy), rot, sizes)  # (N, 8, 2) footprint around each centre
    if inside(table, xy[:, None, :] + offsets).all():
        return xy
    c_lay = (xy.min(0) + xy.max(0)) / 2
    x0, y0, x1, y1 = bounds(table)
    c_tab = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    for use_footprints in (True, False):
        for scales, shifts in _CANDIDATES:
            cand = c_lay + shifts * (c_tab - c_lay) + scales * (xy - c_lay)  # (C, N, 2)
            pts = cand[:, :, None, :] + offsets if use_footprints else cand
            ok = inside(table, pts.reshape(len(cand), -1, 2)).all(1)
            if ok.any():
                return cand[int(np.argmax(ok))]
    out = xy.copy()
    for i in range(len(out)):  # last resort: each centroid on its own
        for t in np.linspace(0.05, 1.0, 20):
            p = out[i] + t * (c_tab - out[i])
            if inside(table, p[None])[0]:
                out[i] = p
                break
    return out


def max_overlap(xy: np.ndarray, rot: np.ndarray, sizes: np.ndarray) -> float:
    """Largest fraction of one footprint's sample points inside another footprint (0 = no overlap)."""
    n = len(xy)
    if n < 2:
        return 0.0
    radius = sizes.max(1) / 2  # bounding circles: objects whose circles do not meet cannot overlap
    dist = np.sqrt(((xy[:, None] - xy[None]) ** 2).sum(-1))
    if (dist + np.eye(n) * 1e9 >= radius[:, None] + radius[None]).all():
        return 0.0
    w_ax, l_ax = _axes(rot)
    half = sizes / 2  # (N, 2) semi-axes (width, length)
    # sample points of every object: (N, 17, 2)
    pts = xy[:, None, :] + _DISC[None, :, :1] * half[:, None, :1] * w_ax[:, None, :] \
        + _DISC[None, :, 1:] * half[:, None, 1:] * l_ax[:, None, :]
    d = pts[:, :, None, :] - xy[None, None, :, :]  # (N, 17, N, 2): point of i relative to centre of j
    u = (d * w_ax[None, None]).sum(-1) / half[None, None, :, 0]
    v = (d * l_ax[None, None]).sum(-1) / half[None, None, :, 1]
    frac = ((u ** 2 + v ** 2) <= 1.0).mean(1)  # (N, N): fraction of i inside j
    np.fill_diagonal(frac, 0.0)
    return float(frac.max())
