"""The vocabulary of the learned model and small helpers: table geometry, Fourier features, surfaces.

`Vocab` fixes what the model can name: the catalog (object row = index into `Vocab.objects`), each
object's discrete features (type, colours, materials, shape, pattern as integer codes) and the known
tables. It is stored in the checkpoint as plain JSON-like data (`to_dict`), so weights-only loading works
and a prediction run can check that its dataset has the same catalog. A table becomes `GEOM_DIM` numbers
(`table_geometry`: bounds, size, centre, fill of its bounding box). The episode encoding is in slots.py.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from degusta_learn.errors import DegustaError
from degusta_learn.scene import Catalog, Dataset, Table

FEATURES = ("type", "color", "material", "shape", "pattern")  # color/material: both slots share a table
GEOM_DIM = 9


def _polygon_area(pts: np.ndarray) -> float:
    x, y = pts[:, 0], pts[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@functools.lru_cache(maxsize=256)
def table_geometry(table: Table) -> np.ndarray:
    """(GEOM_DIM,) [x0, y0, x1, y1, width, height, cx, cy, polygon area / bbox area] (cached: do not modify)."""
    x0, y0, x1, y1 = table.bounds
    fill = _polygon_area(np.asarray(table.surface, dtype=float)) / max((x1 - x0) * (y1 - y0), 1e-9)
    return np.array([x0, y0, x1, y1, x1 - x0, y1 - y0, (x0 + x1) / 2, (y0 + y1) / 2, fill], dtype=np.float32)


@dataclass
class Vocab:
    """The catalog and tables a model was trained on, as integer codes (see module docstring)."""

    catalog: list[dict]
    """Catalog entries (the catalog.json form, without images), in row order."""
    tables: list[dict]
    """Known tables (the tables.json form); a table not listed gets the 'unknown table' embedding."""
    codes: np.ndarray = field(init=False, repr=False)  # (n_objects, len(FEATURES)) int
    sizes: list[int] = field(init=False)  # vocabulary size per feature
    types: list[str] = field(init=False)
    row_of: dict[int, int] = field(init=False, repr=False)

    def __post_init__(self):
        values: dict[str, list[str]] = {f: [] for f in FEATURES}
        for o in self.catalog:
            for f, keys in (("type", ("class",)), ("color", ("color1", "color2")), ("material", ("material1", "material2")),
                            ("shape", ("shape",)), ("pattern", ("pattern",))):
                for k in keys:
                    if o[k] not in values[f]:
                        values[f].append(o[k])
        self.types = values["type"]
        self.sizes = [len(values[f]) for f in FEATURES]
        self.codes = np.array([[values["type"].index(o["class"]), values["color"].index(o["color1"]),
                                values["material"].index(o["material1"]), values["shape"].index(o["shape"]),
                                values["pattern"].index(o["pattern"])] for o in self.catalog], dtype=np.int64)
        self.second = np.array([[values["color"].index(o["color2"]), values["material"].index(o["material2"])]
                                for o in self.catalog], dtype=np.int64)
        self.row_of = {o["id"]: i for i, o in enumerate(self.catalog)}
        self.type_of_id = {o["id"]: int(self.codes[i, 0]) for i, o in enumerate(self.catalog)}
        self.table_index = {t["id"]: i for i, t in enumerate(self.tables)}

    @classmethod
    def from_dataset(cls, ds: Dataset) -> Vocab:
        return cls([o.to_json(with_image=False) for o in ds.catalog],
                   [{k: v for k, v in t.to_json().items() if k != "image"} for t in ds.tables.values()])

    def to_dict(self) -> dict:
        return {"catalog": self.catalog, "tables": self.tables}

    @property
    def n_objects(self) -> int:
        return len(self.catalog)

    @property
    def type_of_row(self) -> np.ndarray:
        return self.codes[:, 0]

    def check_catalog(self, catalog: Catalog, where: str) -> None:
        """Raise DegustaError if `catalog` differs from the one the model was trained on."""
        mine = {o["id"]: o for o in self.catalog}
        theirs = {o.id: o.to_json(with_image=False) for o in catalog}
        if mine != theirs:
            diff = sorted(set(mine) ^ set(theirs)) or sorted(i for i in mine if mine[i] != theirs[i])
            raise DegustaError(f"{where}: the model was trained on another catalog (object {diff[0]} differs); "
                               "predict on a dataset with the training catalog")

    def rows(self, ids) -> np.ndarray:
        return np.array([self.row_of[i] for i in ids], dtype=np.int64)


def fourier(x: torch.Tensor, n_freq: int) -> torch.Tensor:
    """(..., D) -> (..., D * 2 * n_freq) sin/cos features at frequencies pi * 2^k."""
    freqs = math.pi * (2.0 ** torch.arange(n_freq, device=x.device, dtype=x.dtype))
    ang = x[..., None] * freqs  # (..., D, F)
    return torch.cat([ang.sin(), ang.cos()], dim=-1).flatten(-2)


def onto_surface(table: Table, xy: np.ndarray, margin: float = 0.98) -> np.ndarray:
    """Move points outside `table`'s surface polygon toward its centre until inside (bisection)."""
    xy = np.clip(np.asarray(xy, dtype=float).reshape(-1, 2), 0.0, 1.0)
    out = ~table.contains(xy[:, 0], xy[:, 1])
    if not out.any():
        return xy
    c = np.array(table.center)
    d = xy[out] - c  # (M, 2)
    lo, hi = np.zeros(len(d)), np.ones(len(d))  # scales of d known inside / outside
    for _ in range(20):
        mid = (lo + hi) / 2
        p = c + d * mid[:, None]
        inside = table.contains(p[:, 0], p[:, 1])
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    xy[out] = c + d * (lo * margin)[:, None]
    return xy
