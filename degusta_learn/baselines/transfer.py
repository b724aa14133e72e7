"""Carrying arrangements between tables, for the heuristic baselines.

- `relative_positions`: an arrangement's positions relative to its table surface's bounding box (u, v).
- `place_on`: (object, u, v, rotation) rows -> placements on a target table: (u, v) mapped onto the
  target surface's bounding box, then moved onto the surface with `synth.geometry.fit_into`.
- `table_distance`: how different two tables are in shape and size (log width and height ratios plus
  the difference in how much of the bounding box the surface fills: 1 for a rectangle, ~0.785 for an
  ellipse), so `copy_nearest` prefers a context table like the target.
- `circular_mean`: mean of angles in degrees, in [0, 360).
"""

from __future__ import annotations

import hashlib

import numpy as np

from degusta_learn.scene import Arrangement, Catalog, Placement, Table
from degusta_learn.synth.geometry import bounds, fit_into, sizes_of, to_relative, to_table


def relative_positions(arr: Arrangement, table: Table) -> np.ndarray:
    """(N, 2) positions of `arr` relative to `table`'s surface bounds."""
    return to_relative(table, arr.positions)


def place_on(table: Table, catalog: Catalog, objects: list[int], uv: np.ndarray, rot: np.ndarray) -> list[Placement]:
    """Placements of `objects` at relative positions `uv` (N, 2) and rotations `rot` (N,) on `table`."""
    if not objects:
        return []
    rot = np.asarray(rot, dtype=float) % 360.0
    xy = fit_into(table, to_table(table, uv), rot, sizes_of([catalog[o].type for o in objects]))
    xy = np.clip(xy, 0.0, 1.0)
    return [Placement(int(o), float(x), float(y), float(r)) for o, (x, y), r in zip(objects, xy, rot)]


def _fill(table: Table) -> float:
    pts = np.asarray(table.surface, dtype=float)
    area = 0.5 * abs(np.dot(pts[:, 0], np.roll(pts[:, 1], -1)) - np.dot(pts[:, 1], np.roll(pts[:, 0], -1)))
    x0, y0, x1, y1 = bounds(table)
    return float(area / max((x1 - x0) * (y1 - y0), 1e-12))


def table_distance(a: Table, b: Table) -> float:
    """0 for the same shape and size; grows with differences in width, height and fill."""
    ax0, ay0, ax1, ay1 = bounds(a)
    bx0, by0, bx1, by1 = bounds(b)
    return float(abs(np.log((ax1 - ax0) / (bx1 - bx0))) + abs(np.log((ay1 - ay0) / (by1 - by0)))
                 + 2.0 * abs(_fill(a) - _fill(b)))


def circular_mean(degrees) -> float:
    """Mean direction of angles in degrees, in [0, 360); 0 for an empty input."""
    r = np.radians(np.asarray(degrees, dtype=float))
    if r.size == 0:
        return 0.0
    return float(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean())) % 360.0)


def stable_seed(*parts) -> int:
    """A seed from strings/ints that does not depend on Python's hash randomization."""
    return int.from_bytes(hashlib.sha256("/".join(map(str, parts)).encode()).digest()[:8], "little")
