"""Scenes -> tensors for the learned arrangement model: the vocabulary, token features, collation.

`Vocab` fixes what the model can name: the catalog (object row = index into `Vocab.objects`), each
object's discrete features (type, colours, materials, shape, pattern as integer codes) and the known
tables. It is stored in the checkpoint as plain JSON-like data (`to_dict`), so weights-only loading works
and a prediction run can check that its dataset has the same catalog.

A placement on table T becomes a position feature vector (`POS_DIM` numbers)

    [x, y, u, v, sin(rot), cos(rot)]   with  u, v = position relative to T's surface bounds, in [-1, 1]

a context placement also gets `REL_DIM` layout numbers (its offset from its arrangement's centroid, and
that centroid relative to the bounds: how the data carries a layout between tables, see data.swap_table),
and a table becomes `GEOM_DIM` numbers (bounds, size, centre, fill of its bounding box).
`encode_sample` turns (context arrangements, target table, target arrangement or None) into a dict of
numpy arrays; `collate` pads a list of them into a batch of tensors (shapes in its docstring).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from degusta_learn.baselines.learned.align import align_context
from degusta_learn.errors import DegustaError
from degusta_learn.scene import Arrangement, Catalog, Dataset, Table

FEATURES = ("type", "color", "material", "shape", "pattern")  # color/material: both slots share a table
POS_DIM = 6
REL_DIM = 4
MAX_GROUPS = 48  # most context groups told apart (align.py); more share the last number
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


def position_features(table: Table, xy: np.ndarray, rot_deg: np.ndarray) -> np.ndarray:
    """(N, POS_DIM) features of N placements on `table` (xy (N, 2), rotations (N,) in degrees)."""
    x0, y0, x1, y1 = table.bounds
    lo, size = np.array([x0, y0]), np.maximum(np.array([x1 - x0, y1 - y0]), 1e-6)
    uv = (xy - lo) / size * 2 - 1
    rad = np.deg2rad(rot_deg)
    return np.concatenate([xy, uv, np.sin(rad)[:, None], np.cos(rad)[:, None]], axis=1).astype(np.float32)


def layout_features(table: Table, xy: np.ndarray) -> np.ndarray:
    """(N, REL_DIM) per placement: [dx, dy] offset from its arrangement's centroid (physical units) and
    [cu, cv] that centroid relative to the surface bounds in [-1, 1] (the same for every placement)."""
    x0, y0, x1, y1 = table.bounds
    centre = xy.mean(0)
    cuv = (centre - [x0, y0]) / np.maximum([x1 - x0, y1 - y0], 1e-6) * 2 - 1
    return np.concatenate([xy - centre, np.repeat(cuv[None], len(xy), axis=0)], axis=1).astype(np.float32)


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


def _cat(xs: list[np.ndarray], shape: tuple, dtype) -> np.ndarray:
    return np.concatenate(xs).astype(dtype) if xs else np.zeros(shape, dtype=dtype)


def encode_sample(vocab: Vocab, tables: dict[int, Table], context: list[Arrangement], target_table: int,
                  target: Arrangement | None = None, max_objects: int = 20, rng=None) -> dict[str, np.ndarray]:
    """Arrays for one episode; `target` None at prediction time. Arrangements may carry remapped tables.

    `rng` (training): shuffle the context group numbers (see align.py) so that only their identity counts.
    """
    obj, feat, rel, step, slot, tab, geom = [], [], [], [], [], [], []
    for s, arr in enumerate(context):
        n = len(arr.placements)
        obj.append(vocab.rows(arr.objects))
        feat.append(position_features(tables[arr.table], arr.positions, arr.rotations))
        rel.append(layout_features(tables[arr.table], arr.positions))
        step.append(np.minimum(np.arange(n), max_objects - 1))
        slot.append(np.full(n, s))
        tab.append(np.full(n, vocab.table_index.get(arr.table, len(vocab.tables))))
        geom.append(np.repeat(table_geometry(tables[arr.table])[None], n, axis=0))
    group, support = align_context(context, tables, vocab.type_of_id)
    order = rng.permutation(MAX_GROUPS) if rng is not None else np.arange(MAX_GROUPS)
    out = {
        "ctx_group": order[np.minimum(group, MAX_GROUPS - 1)], "ctx_support": support[:, None],
        "ctx_obj": _cat(obj, (0,), np.int64), "ctx_feat": _cat(feat, (0, POS_DIM), np.float32),
        "ctx_rel": _cat(rel, (0, REL_DIM), np.float32),
        "ctx_step": _cat(step, (0,), np.int64), "ctx_slot": _cat(slot, (0,), np.int64),
        "ctx_table": _cat(tab, (0,), np.int64), "ctx_geom": _cat(geom, (0, GEOM_DIM), np.float32),
        "tgt_table": np.int64(vocab.table_index.get(target_table, len(vocab.tables))),
        "tgt_geom": table_geometry(tables[target_table]),
    }
    if target is not None:
        if len(target.placements) > max_objects:
            raise DegustaError(f"participant {target.participant!r} trial {target.trial}: {len(target.placements)} "
                               f"objects, more than model.max_objects={max_objects}")
        rot = target.rotations
        out.update(y_obj=vocab.rows(target.objects), y_xy=target.positions.astype(np.float32),
                   y_feat=position_features(tables[target_table], target.positions, rot),
                   y_rot=np.deg2rad(rot).astype(np.float32))
    return out


def _pad(arrays: list[np.ndarray], value=0) -> tuple[torch.Tensor, torch.Tensor]:
    n = max((len(a) for a in arrays), default=0)
    first = arrays[0]
    out = np.full((len(arrays), n, *first.shape[1:]), value, dtype=first.dtype)
    mask = np.zeros((len(arrays), n), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
        mask[i, : len(a)] = True
    return torch.from_numpy(out), torch.from_numpy(mask)


def collate(samples: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    """Pad samples into a batch.

    Returns (B = batch, C = longest context token list, T = longest target):
        ctx_obj, ctx_group, ctx_step, ctx_slot, ctx_table (B, C) long; ctx_support (B, C, 1); ctx_feat (B, C, POS_DIM); ctx_rel (B, C, REL_DIM);
        ctx_geom (B, C, GEOM_DIM);
        ctx_mask (B, C) bool (True = real token); tgt_table (B,) long; tgt_geom (B, GEOM_DIM);
        index (B,) long when the samples carry one (which validation episode);
        with targets also y_obj (B, T) long, y_xy (B, T, 2), y_feat (B, T, POS_DIM), y_rot (B, T), y_mask (B, T).
    """
    batch: dict[str, torch.Tensor] = {}
    for key in ("ctx_obj", "ctx_group", "ctx_support", "ctx_feat", "ctx_rel", "ctx_step", "ctx_slot", "ctx_table", "ctx_geom"):
        batch[key], batch["ctx_mask"] = _pad([s[key] for s in samples])
    batch["tgt_table"] = torch.tensor(np.array([s["tgt_table"] for s in samples]))
    batch["tgt_geom"] = torch.from_numpy(np.stack([s["tgt_geom"] for s in samples]))
    if "index" in samples[0]:
        batch["index"] = torch.tensor([int(s["index"]) for s in samples])
    if "y_obj" in samples[0]:
        for key in ("y_obj", "y_xy", "y_feat", "y_rot"):
            batch[key], batch["y_mask"] = _pad([s[key] for s in samples])
    return batch


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
