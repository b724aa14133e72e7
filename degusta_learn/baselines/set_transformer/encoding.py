"""An episode as the set transformer reads it: one token per context placement, the target table, the labels.

No alignment: each object of each context arrangement is its own token, as it was placed. A token carries

- which catalog object it is (`obj`: a row of `Vocab.objects`; the model embeds its id and features);
- where it is: relative to its table's bounds (u, v), in image coordinates (x, y), as an offset from its
  arrangement's centroid (dx, dy), and *carried* onto the target table (`carried`: the arrangement's centroid keeps
  its place relative to the surface bounds, the object keeps its physical offset from it, as `data.swap_table`
  moves a layout); its rotation (sin, cos); its placement step (step / n_queries);
- its arrangement: which context trial (`trial`: 0..k-1, in the episode's random order), that arrangement's
  object count, the context length k, whether its table is the target table, its table (`table`: a row of
  `Vocab.tables`, unknown tables the last row) and that table's geometry (`features.table_geometry`).

The target table is one more input (`tgt_table`, `tgt_geom`, and k). `share` is, per catalog object, the fraction
of the context arrangements that hold it: a per-episode prior the object head adds (see model.py).

Labels (training and validation) are the target's placements in placement order, unaligned: objects, positions,
rotations (radians) and steps (index / n_queries). The Hungarian matching (matching.py) pairs them with the
queries, so their order never matters to the loss.

Usage:
    encode = SetEncoder(vocab, ds.tables, n_queries=20)
    sample = encode(context_arrangements, target_table_id, target)   # dict of numpy arrays
    batch = collate_sets([sample, ...])                              # dict of padded tensors
"""

from __future__ import annotations

import math

import numpy as np
import torch

from degusta_learn.baselines.learned.features import Vocab, table_geometry
from degusta_learn.scene import Arrangement, Table

TOKEN_FEATURES = ("u", "v", "x", "y", "dx", "dy", "carried x", "carried y", "sin", "cos", "step / n_queries",
                  "objects / n_queries", "k / 4", "same table as the target")
POSITIONS = slice(0, 8)  # u, v, x, y, dx, dy, carried x, y: Fourier-encoded by the model
CARRIED = slice(6, 8)  # where the model's pointer reads a token's position
ROTATION = slice(8, 10)  # ... and its rotation (sin, cos)
STEP = TOKEN_FEATURES.index("step / n_queries")  # ... and its placement step
TOKEN_DIM = len(TOKEN_FEATURES)


class SetEncoder:
    """`encode(context, target_table_id, target=None)` -> the sample of one episode (a plain object, so
    DataLoader workers can pickle it)."""

    def __init__(self, vocab: Vocab, tables: dict[int, Table], n_queries: int):
        self.vocab, self.tables, self.n_queries = vocab, tables, n_queries

    def table_row(self, table_id: int) -> int:
        return self.vocab.table_index.get(table_id, len(self.vocab.tables))

    def __call__(self, context: list[Arrangement], target_table: int, target: Arrangement | None = None) -> dict:
        k, nq = len(context), self.n_queries
        feats, objs, trials, tables = [], [], [], []
        share = np.zeros(self.vocab.n_objects, dtype=np.float32)
        b0, b1 = np.array(self.tables[target_table].bounds).reshape(2, 2)  # target (x0, y0), (x1, y1)
        for c, arr in enumerate(context):
            a0, a1 = np.array(self.tables[arr.table].bounds).reshape(2, 2)
            xy = arr.positions  # (n, 2)
            centre = xy.mean(0)
            carried = xy - centre + b0 + (centre - a0) / np.maximum(a1 - a0, 1e-6) * (b1 - b0)  # (n, 2)
            uv = (xy - a0) / np.maximum(a1 - a0, 1e-6)
            n = len(arr.placements)
            for j, p in enumerate(arr.placements):
                r = math.radians(p.rotation)
                feats.append([*uv[j], p.x, p.y, *(xy[j] - centre), *carried[j], math.sin(r), math.cos(r), j / nq,
                              n / nq, k / 4, float(arr.table == target_table), *table_geometry(self.tables[arr.table])])
            rows = self.vocab.rows([p.object for p in arr.placements])
            objs.extend(rows.tolist())
            share[np.unique(rows)] += 1.0 / k
            trials.extend([c] * n)
            tables.extend([self.table_row(arr.table)] * n)
        width = TOKEN_DIM + len(table_geometry(self.tables[target_table]))
        sample = {"tok_feat": np.asarray(feats, dtype=np.float32).reshape(-1, width),
                  "tok_obj": np.asarray(objs, dtype=np.int64), "tok_trial": np.asarray(trials, dtype=np.int64),
                  "tok_table": np.asarray(tables, dtype=np.int64), "share": share,
                  "tgt_table": self.table_row(target_table), "tgt_geom": table_geometry(self.tables[target_table]),
                  "k": k}
        if target is not None:
            sample.update(labels(self.vocab, target, nq))
        return sample


def labels(vocab: Vocab, target: Arrangement, n_queries: int) -> dict[str, np.ndarray]:
    """The target's placements as arrays: y_obj (M,) catalog rows, y_xy (M, 2), y_rot (M,) radians, y_step (M,)."""
    return {"y_obj": vocab.rows([p.object for p in target.placements]),
            "y_xy": target.positions.astype(np.float32),
            "y_rot": np.radians([p.rotation for p in target.placements]).astype(np.float32),
            "y_step": (np.arange(len(target.placements)) / n_queries).astype(np.float32)}


def _pad(arrays: list[np.ndarray], value=0) -> tuple[torch.Tensor, torch.Tensor]:
    """Stack arrays of different lengths into (B, L, ...) padded with `value`, and the (B, L) mask (True = real)."""
    n = max((len(a) for a in arrays), default=0)
    first = arrays[0]
    out = np.full((len(arrays), n, *first.shape[1:]), value, dtype=first.dtype)
    mask = np.zeros((len(arrays), n), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, :len(a)] = a
        mask[i, :len(a)] = True
    return torch.from_numpy(out), torch.from_numpy(mask)


def collate_sets(samples: list[dict]) -> dict[str, torch.Tensor]:
    """Pad samples into a batch: tokens (B, T, ...) with tok_mask (B, T), labels (B, M, ...) with y_mask (B, M);
    share (B, O), tgt_geom (B, GEOM_DIM), tgt_table / k (B,) and index (B,) when present. T may be 0 (context 0)."""
    batch: dict[str, torch.Tensor] = {}
    for key in ("tok_feat", "tok_obj", "tok_trial", "tok_table"):
        batch[key], batch["tok_mask"] = _pad([s[key] for s in samples])
    if "y_obj" in samples[0]:
        for key in ("y_obj", "y_xy", "y_rot", "y_step"):
            batch[key], batch["y_mask"] = _pad([s[key] for s in samples], -1 if key == "y_obj" else 0)
    for key in ("share", "tgt_geom"):
        batch[key] = torch.from_numpy(np.stack([s[key] for s in samples]))
    for key in ("tgt_table", "k", "index"):
        if key in samples[0]:
            batch[key] = torch.tensor([int(s[key]) for s in samples])
    return batch
