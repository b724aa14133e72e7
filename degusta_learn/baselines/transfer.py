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
import math

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
    rot = np.nan_to_num(np.asarray(rot, dtype=float), nan=0.0, posinf=0.0, neginf=0.0) % 360.0
    uv = np.nan_to_num(np.asarray(uv, dtype=float), nan=0.5, posinf=1.0, neginf=0.0)
    xy = fit_into(table, to_table(table, uv), rot, sizes_of([catalog[o].type for o in objects]))
    xy = np.clip(np.nan_to_num(xy, nan=0.5), 0.0, 1.0)
    return [Placement(int(o), float(x), float(y), float(r)) for o, (x, y), r in zip(objects, xy, rot)]


def _fill(table: Table) -> float:
    pts = np.asarray(table.surface, dtype=float)
    area = 0.5 * abs(np.dot(pts[:, 0], np.roll(pts[:, 1], -1)) - np.dot(pts[:, 1], np.roll(pts[:, 0], -1)))
    w, h = _extent(table)
    return float(area / (w * h)) if w * h > 1e-12 else 0.0


def _extent(table: Table) -> tuple[float, float]:
    """Width and height of the surface's bounding box, floored at 1e-9 (degenerate surfaces: no 0 / 0)."""
    x0, y0, x1, y1 = bounds(table)
    return max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)


def table_distance(a: Table, b: Table) -> float:
    """0 for the same shape and size; grows with differences in width, height and fill.

    Finite for every pair of tables, degenerate ones included (load_dataset rejects those; a Table built
    in code may still be one).
    """
    (aw, ah), (bw, bh) = _extent(a), _extent(b)
    return float(abs(math.log(aw / bw)) + abs(math.log(ah / bh)) + 2.0 * abs(_fill(a) - _fill(b)))


def circular_mean(degrees) -> float:
    """Mean direction of angles in degrees, in [0, 360); 0 for an empty input."""
    r = np.radians(np.asarray(degrees, dtype=float))
    if r.size == 0:
        return 0.0
    return float(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean())) % 360.0)


def stable_seed(*parts) -> int:
    """A seed from strings/ints that does not depend on Python's hash randomization."""
    return int.from_bytes(hashlib.sha256("/".join(map(str, parts)).encode()).digest()[:8], "little")
