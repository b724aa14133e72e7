"""Grid geometry of grid-marked arrangements (GMA): cell ids, footprints, decoding, directions.

A `Grid(rows, cols)` divides the table image (normalized x, y in [0, 1], origin top-left) into equal
cells. Columns are letters from the left (A, B, ...), rows numbers from the top (1, 2, ...): cell
"C7" is the third column, seventh row; "A1" is the top-left cell.

Encoding a placement lists the cells the object's rotated footprint intersects. The footprint is the
object's procedural sprite outline (render/shapes.py: the same masks the sprite is drawn from, sampled
every 0.0025 normalized units), rotated clockwise by the placement's rotation about its centroid; so a
fork covers the cells its tines and handle cover, a cup includes its handle. An object drawn from a
picture (`image` entries) uses its full footprint rectangle. Points outside the image are ignored; the
centroid's cell is always included. Normalized units are treated as isotropic (square table images).

Decoding is the mean of the listed cell centres. Over several responses (`decode_weighted`) it is the
mean of the responses' own decoded centres, so each response weighs the same however many cells it lists
(the paper: "we average the centroids of the responses"); a cell named by more responses still pulls
harder. `quantization_rmsd` measures the round trip position -> cells -> position over a dataset: the
floor under every grid method's RMSD. `max_cells` bounds how many cells an object of a given footprint
can cover anywhere on the grid (the answer grammar's per-type limit).

Example:
    from degusta_learn.render.grid import Grid, rotation_to_direction
    g = Grid(8, 8)
    cells = g.encode(ds.catalog[75], 0.5, 0.5, 0.0)   # e.g. ['D4', 'E4', 'D5', 'E5']
    g.decode(cells), rotation_to_direction(350.0)     # (0.5, 0.5), 'N'
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass

import numpy as np

from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError
from degusta_learn.render.shapes import footprint_points
from degusta_learn.scene import CatalogObject, Dataset, object_size

DIRECTIONS = ("N", "NE", "E", "SE", "S", "SW", "W", "NW")
_CELL = re.compile(r"^([A-Z])\s*(\d+)$")


@dataclass(frozen=True)
class Grid:
    """A rows x cols grid over the table image; cell ids like "C7" (column letter, row number). Also the
    `grid:` section of every config that has one (predict configs, `data.grid` of fine-tune and pretrain)."""

    rows: int = bounded(8, 1, 99)
    """Number of rows (numbered 1.. from the top)."""
    cols: int = bounded(8, 1, 26)
    """Number of columns (lettered A.. from the left; at most 26)."""

    def __post_init__(self):
        for key, value, hi in (("rows", self.rows, 99), ("cols", self.cols, 26)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= hi:
                raise DegustaError(f"grid {key}: expected an integer from 1 to {hi}, got {value!r}")

    def __str__(self) -> str:
        return f"{self.rows}x{self.cols}"

    @property
    def cells(self) -> list[str]:
        """All cell ids, row-major: A1, B1, ..., then A2, ..."""
        return [self.cell_id(c, r) for r in range(self.rows) for c in range(self.cols)]

    def cell_id(self, col: int, row: int) -> str:
        """0-based (col, row) -> id, e.g. (2, 6) -> "C7"."""
        if not (0 <= col < self.cols and 0 <= row < self.rows):
            raise DegustaError(f"grid cell (col {col}, row {row}) is outside the {self} grid")
        return f"{chr(ord('A') + col)}{row + 1}"

    def parse_cell(self, s: str) -> tuple[int, int]:
        """Cell id (case-insensitive, spaces ignored) -> 0-based (col, row)."""
        m = _CELL.match(str(s).strip().upper()) if isinstance(s, str) else None
        if m is None:
            raise DegustaError(f"grid cell {s!r} is not a cell id (a column letter then a row number, e.g. C7)")
        col, row = ord(m.group(1)) - ord("A"), int(m.group(2)) - 1
        if not (0 <= col < self.cols and 0 <= row < self.rows):
            last = chr(ord("A") + self.cols - 1)
            raise DegustaError(f"grid cell {s!r} is outside the {self} grid (columns A-{last}, rows 1-{self.rows})")
        return col, row

    def cell_center(self, s: str) -> tuple[float, float]:
        """Normalized (x, y) of a cell's centre."""
        col, row = self.parse_cell(s)
        return (col + 0.5) / self.cols, (row + 0.5) / self.rows

    def encode(self, obj: CatalogObject, x: float, y: float, rotation: float) -> list[str]:
        """Sorted (row-major) ids of the cells that `obj` placed at (x, y, rotation) intersects."""
        width, length = object_size(obj)
        pts = footprint_points(obj.type, obj.shape, width, length, obj.image is not None)  # (N, 2)
        pts = rotate(pts, rotation) + np.array([x, y])
        pts = np.vstack([pts, [[x, y]]])
        ok = (pts[:, 0] >= 0) & (pts[:, 0] < 1) & (pts[:, 1] >= 0) & (pts[:, 1] < 1)
        cols = np.clip((pts[ok, 0] * self.cols).astype(int), 0, self.cols - 1)
        rows = np.clip((pts[ok, 1] * self.rows).astype(int), 0, self.rows - 1)
        flat = np.unique(rows * self.cols + cols)
        if flat.size == 0:  # the centroid is off the image: its nearest cell
            c = min(max(int(x * self.cols), 0), self.cols - 1)
            r = min(max(int(y * self.rows), 0), self.rows - 1)
            flat = np.array([r * self.cols + c])
        return [self.cell_id(int(i % self.cols), int(i // self.cols)) for i in flat]

    def decode(self, cells: list[str]) -> tuple[float, float]:
        """Mean of the cells' centres; DegustaError on an empty list or a bad id."""
        if not cells:
            raise DegustaError("cannot decode an empty list of grid cells")
        centres = np.array([self.cell_center(c) for c in cells])
        return float(centres[:, 0].mean()), float(centres[:, 1].mean())

    def decode_weighted(self, cell_lists: list[list[str]]) -> tuple[float, float]:
        """Mean over responses of each response's decoded centre: every response weighs the same, whatever
        the number of cells it lists. DegustaError on no responses, an empty response or a bad id."""
        if not cell_lists:
            raise DegustaError("cannot decode an empty list of responses")
        centres = np.array([self.decode(cells) for cells in cell_lists])
        return float(centres[:, 0].mean()), float(centres[:, 1].mean())


def as_grid(grid: Grid | int | None) -> Grid | None:
    """A Grid from a Grid, an int n (n x n) or None."""
    if grid is None or isinstance(grid, Grid):
        return grid
    if isinstance(grid, int) and not isinstance(grid, bool):
        return Grid(grid, grid)
    raise DegustaError(f"grid: expected a Grid or an integer, got {grid!r}")


def rotate(points: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate (N, 2) image-frame points (y down) clockwise by `degrees` about the origin."""
    t = math.radians(degrees)
    c, s = math.cos(t), math.sin(t)
    return points @ np.array([[c, s], [-s, c]])  # x' = c x - s y, y' = s x + c y


@functools.lru_cache(maxsize=256)
def max_cells(width: float, length: float, rows: int = 8, cols: int = 8, offsets: int = 16,
              step_deg: float = 0.5) -> int:
    """The most cells `Grid(rows, cols).encode` can list for an object of footprint `width` x `length`,
    at any position and rotation: a guaranteed upper bound, usually exact.

    `encode` lists cells that points of the footprint fall in, and every such point lies in the footprint
    rectangle; so the count is at most the number of cells the rotated rectangle intersects. That number is
    counted exactly (separating axis test, rectangle against each cell) at every `step_deg` of rotation in
    [0, 90] (a rectangle's symmetries and the grid's mirror symmetry cover the rest) and at an
    `offsets` x `offsets` lattice of centre positions within one cell, with the rectangle grown on every
    side by the farthest any point of it can move between lattice placements (half a lattice diagonal plus
    half a rotation step along the half diagonal). Every placement lies within that reach of a lattice
    placement, so its cells are among the grown rectangle's there.
    """
    cw, ch = 1.0 / cols, 1.0 / rows
    reach = 0.5 * math.hypot(cw, ch) / offsets + 0.5 * math.hypot(width, length) * math.radians(step_deg) / 2
    a, b = width / 2 + reach, length / 2 + reach  # half sizes across / along the object's long axis
    kc, kr = math.ceil(math.hypot(a, b) / cw) + 1, math.ceil(math.hypot(a, b) / ch) + 1
    frac = (np.arange(offsets) + 0.5) / offsets
    dx = (np.arange(-kc, kc + 1)[None, :] + 0.5) * cw - frac[:, None] * cw  # (O, C) cell centre - object centre
    dy = (np.arange(-kr, kr + 1)[None, :] + 0.5) * ch - frac[:, None] * ch  # (O, R)
    dx, dy = dx[:, None, :, None], dy[None, :, None, :]  # (O, 1, C, 1), (1, O, 1, R)
    best = 0
    for t in np.radians(np.arange(0.0, 90.0 + step_deg / 2, step_deg)):
        c, s = abs(math.cos(t)), abs(math.sin(t))  # width axis (c, s), length axis (-s, c); t in [0, 90]
        hit = (np.abs(dx) <= cw / 2 + a * c + b * s) & (np.abs(dy) <= ch / 2 + a * s + b * c)
        hit &= np.abs(dx * c + dy * s) <= a + cw / 2 * c + ch / 2 * s
        hit &= np.abs(dy * c - dx * s) <= b + cw / 2 * s + ch / 2 * c
        best = max(best, int(hit.sum(axis=(2, 3)).max()))
    return min(best, rows * cols)


def rotation_to_direction(deg: float) -> str:
    """Nearest of the 8 directions (N = 0 = image north, clockwise); ties go clockwise (22.5 -> NE)."""
    return DIRECTIONS[int(math.floor((float(deg) % 360.0 + 22.5) / 45.0)) % 8]


def direction_to_rotation(d: str) -> float:
    """"N" -> 0, "NE" -> 45, ... (case-insensitive, spaces ignored)."""
    key = str(d).strip().upper() if isinstance(d, str) else None
    if key not in DIRECTIONS:
        raise DegustaError(f"unknown direction {d!r} (expected one of {', '.join(DIRECTIONS)})")
    return 45.0 * DIRECTIONS.index(key)


def circular_mean(degs, weights=None) -> float:
    """Weighted circular mean of angles in degrees, in [0, 360). Opposite angles cancel to atan2's answer."""
    a = np.radians(np.asarray(degs, dtype=float).ravel())
    if a.size == 0:
        raise DegustaError("circular mean of no angles")
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=float).ravel()
    if w.shape != a.shape:
        raise DegustaError(f"circular mean: {a.size} angles but {w.size} weights")
    m = math.degrees(math.atan2(float((w * np.sin(a)).sum()), float((w * np.cos(a)).sum()))) % 360.0
    return 0.0 if m >= 360.0 - 1e-9 else m


def _kabsch_rmsd(p: np.ndarray, q: np.ndarray) -> float:
    """RMSD between (N, 2) point sets after the best proper rotation + translation of q onto p."""
    if len(p) < 2:
        return 0.0
    p0, q0 = p - p.mean(0), q - q.mean(0)
    u, _, vt = np.linalg.svd(q0.T @ p0)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    r = u @ np.diag([1.0, d]) @ vt
    return float(np.sqrt(((q0 @ r - p0) ** 2).sum(1).mean()))


def quantization_rmsd(ds: Dataset, grid: Grid, registered: bool = True) -> float:
    """Mean over arrangements of the RMSD between true positions and their decoded cells.

    Each placement is encoded (`grid.encode`) and decoded (`grid.decode`); per arrangement the RMSD over
    its objects is taken, after Kabsch registration by default (as the evaluation's headline RMSD is;
    `registered=False` gives the plain RMSD), and the mean over arrangements returned. It is the error a
    grid method makes even when it names exactly the right cells.
    """
    grid = as_grid(grid)
    out = []
    for arr in ds.arrangements:
        gt = arr.positions
        dec = np.array([grid.decode(grid.encode(ds.catalog[p.object], p.x, p.y, p.rotation))
                        for p in arr.placements]).reshape(-1, 2)
        out.append(_kabsch_rmsd(gt, dec) if registered else float(np.sqrt(((gt - dec) ** 2).sum(1).mean())))
    return float(np.mean(out)) if out else float("nan")
