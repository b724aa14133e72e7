"""Tables: the empty surfaces that arrangements are set on.

A table has an id, an image size in pixels, and a surface polygon in normalized image coordinates
(x right, y down, both in [0, 1]) on which object centroids may lie. `name` picks the procedural look
(wood, marble, ...) when there is no `image`. The default set has five visually distinct tables
(different shapes and surfaces), all square images so that normalized units are isotropic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Table:
    """An empty table: id, image size, surface polygon (normalized) and an optional picture."""

    id: int
    width: int
    height: int
    surface: tuple[tuple[float, float], ...]
    name: str = ""
    image: str | None = None  # path relative to the dataset folder, if the table has a picture

    def to_json(self) -> dict:
        d = {"id": self.id, "name": self.name, "width": self.width, "height": self.height,
             "surface": [list(p) for p in self.surface]}
        if self.image is not None:
            d["image"] = self.image
        return d

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the surface polygon."""
        pts = np.asarray(self.surface)
        return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max())

    @property
    def center(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.bounds
        return (x0 + x1) / 2, (y0 + y1) / 2

    def contains(self, x, y) -> np.ndarray:
        """Whether points lie inside the surface polygon (even-odd rule); vectorized over x, y."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        poly = np.asarray(self.surface, dtype=float)
        inside = np.zeros(np.broadcast(x, y).shape, dtype=bool)
        x2, y2 = np.roll(poly[:, 0], -1), np.roll(poly[:, 1], -1)
        for xa, ya, xb, yb in zip(poly[:, 0], poly[:, 1], x2, y2):
            crosses = (ya > y) != (yb > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                x_at = xa + (y - ya) * (xb - xa) / (yb - ya)
            inside ^= crosses & (x < x_at)
        return inside


def _ellipse(cx: float, cy: float, rx: float, ry: float, n: int = 48) -> tuple[tuple[float, float], ...]:
    return tuple((round(cx + rx * math.cos(2 * math.pi * i / n), 4), round(cy + ry * math.sin(2 * math.pi * i / n), 4))
                 for i in range(n))


def _rect(x0: float, y0: float, x1: float, y1: float) -> tuple[tuple[float, float], ...]:
    return ((x0, y0), (x1, y0), (x1, y1), (x0, y1))


def default_tables() -> tuple[Table, ...]:
    """Five visually distinct tables: oak rectangle, marble round, walnut square, white oval, slate bench."""
    return (
        Table(0, 1024, 1024, _rect(0.04, 0.12, 0.96, 0.88), name="oak"),
        Table(1, 1024, 1024, _ellipse(0.5, 0.5, 0.46, 0.46), name="marble"),
        Table(2, 1024, 1024, _rect(0.06, 0.06, 0.94, 0.94), name="walnut"),
        Table(3, 1024, 1024, _ellipse(0.5, 0.5, 0.47, 0.36), name="white"),
        Table(4, 1024, 1024, _rect(0.03, 0.2, 0.97, 0.8), name="slate"),
    )
