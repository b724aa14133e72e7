"""Greedy decoding of the arrangement model.

At each step the model sees the objects it has placed so far (their predicted positions, as at training
time with teacher forcing) and picks, in this order: the type or stop (stop is barred before
`min_objects`; a type with no unplaced object left is barred), the most likely unplaced object of that type,
then where it goes (the top mixture component's mean, clipped to the target table's bounds) and its
rotation.

Usage:
    objs, xy, rot = greedy_decode(model, batch, min_objects=3)   # lists per episode (catalog rows)
"""

from __future__ import annotations

import numpy as np
import torch

from degusta_learn.baselines.learned.model import ArrangementModel


@torch.no_grad()
def greedy_decode(model: ArrangementModel, batch: dict, min_objects: int = 1, max_objects: int | None = None
                  ) -> tuple[list[list[int]], list[np.ndarray], list[np.ndarray]]:
    """Predict every episode of `batch` (no targets needed).

    Returns:
        (objects, xy, rotations): per episode a list of catalog rows, an (n, 2) array of positions and an
        (n,) array of rotations in degrees [0, 360).
    """
    was_training = model.training
    model.eval()
    codes = model.codes[:, 0]  # (n_obj,) type of each object
    B, dev, n_obj = batch["tgt_table"].shape[0], batch["tgt_geom"].device, model.vocab.n_objects
    geom = batch["tgt_geom"]
    lo, hi = geom[:, None, 0:2], geom[:, None, 2:4]
    y_obj = torch.zeros(B, 0, dtype=torch.long, device=dev)
    y_xy = torch.zeros(B, 0, 2, device=dev)
    y_rot = torch.zeros(B, 0, device=dev)
    y_mask = torch.zeros(B, 0, dtype=torch.bool, device=dev)
    placed = torch.zeros(B, n_obj, dtype=torch.bool, device=dev)
    done = torch.zeros(B, dtype=torch.bool, device=dev)
    steps = max_objects or model.cfg.max_objects
    for t in range(steps):
        feat = model.position_features(y_xy, y_rot, geom)
        enc = model.encode(batch, y_obj, feat, y_mask)
        type_logits = model.type_logits(enc)[:, -1]  # (B, n_types + 1)
        left = torch.zeros(B, model.n_types, device=dev).index_add_(1, codes, (~placed).float())  # unplaced per type
        allowed = torch.cat([left > 0, torch.full((B, 1), t >= min_objects, device=dev)], dim=1)
        allowed[:, -1] |= ~(left > 0).any(1)  # nothing left to place: stop
        type_idx = type_logits.masked_fill(~allowed, float("-inf")).argmax(-1)  # (B,)
        stop = done | (type_idx == model.n_types)
        ty = type_idx.clamp(max=model.n_types - 1)
        logits = model.object_logits(enc, ty[:, None], slice(-1, None))[:, 0]  # (B, n_obj)
        obj = logits.masked_fill((codes[None] != ty[:, None]) | placed, float("-inf")).argmax(-1)  # (B,)
        place = model.placement(enc, obj[:, None], slice(-1, None))
        xy = torch.minimum(torch.maximum(place["xy"].to(lo.dtype), lo), hi)  # (B, 1, 2); float32 under autocast
        rot = torch.atan2(place["rot"][:, 0, 0], place["rot"][:, 0, 1]).to(y_rot.dtype)  # (B,)
        y_obj = torch.cat([y_obj, obj[:, None]], 1)
        y_xy = torch.cat([y_xy, xy], 1)
        y_rot = torch.cat([y_rot, rot[:, None]], 1)
        y_mask = torch.cat([y_mask, ~stop[:, None]], 1)
        placed[torch.arange(B, device=dev)[~stop], obj[~stop]] = True
        done = stop
        if bool(done.all()):
            break
    model.train(was_training)
    objs, xys, rots = [], [], []
    for b in range(B):
        m = y_mask[b]
        objs.append(y_obj[b][m].tolist())
        xys.append(y_xy[b][m].float().cpu().numpy().astype(float))
        rots.append(np.rad2deg(y_rot[b][m].float().cpu().numpy().astype(float)) % 360.0)
    return objs, xys, rots
