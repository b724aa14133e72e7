"""The Hungarian matching loss (DETR, Carion et al. 2020): pair queries with target objects, then score the pairs.

The target is a set: its placements have no slot a query could own. Per episode, every query i is paired with at
most one target object j by one optimal assignment (scipy `linear_sum_assignment`) on the cost

    C[i, j] = w_object * (-log sigmoid(present_i) - log p_i(object_j))          # class: present, and this object
              + w_position * POSITION_SCALE * |xy_i(object_j) - xy_j|^2          # where

(DETR's class cost -log p(class) with its "no object" class factored out as the present logit; its box cost as
squared distance, the quantity RMSD is made of; xy_i(o) is where query i puts object o, model.py's `placing`,
or its one position `xy_i` for a model without one). With Q >= M every target object gets one query; the other
Q - M queries are unmatched and trained toward "absent". The assignment is a constant of the step (no gradient
flows through it); on the matched pairs:

    present  = weighted binary cross-entropy over all queries: 1 for matched (weight 1), 0 for unmatched
               (weight `absent_weight`), divided by the total weight
    object   = mean over matched pairs of -log p_i(object_j)
    position = mean over matched pairs of POSITION_SCALE * |xy_i(object_j) - xy_j|^2   (teacher-forced object)
    rotation = mean over matched pairs of 1 - cos(rotation error)   (query i's (sin, cos) for object_j)
    step     = mean over matched pairs of (step_i(object_j) - step_j)^2   (placement step / n_queries: the order)
    loss     = w_present * present + w_object * object + w_position * position + w_rotation * rotation
               + w_step * step

Means are over all matched pairs of the batch (DETR normalises by the number of target boxes). Because the
cost only looks at each (query, object) pair, the loss does not depend on the order of the target's
placements (tests/test_set_transformer.py checks both the 2x2 arithmetic and that invariance).

Usage:
    pairs = assign(out, batch, cfg)            # per episode: (query rows, target rows)
    losses = set_loss(out, batch, cfg)         # dict with "loss" and its parts
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

POSITION_SCALE = 100.0  # squared distance in units of 0.1 image: comparable with a cross-entropy
LOSS_TERMS = ("present", "object", "position", "rotation", "step")


class LossWeights(Protocol):
    """The weights the loss reads (a `ModelConfig`)."""

    w_present: float
    w_object: float
    w_position: float
    w_rotation: float
    w_step: float
    absent_weight: float


def placing(out: dict, b: torch.Tensor, q: torch.Tensor, objects: torch.Tensor) -> dict[str, torch.Tensor]:
    """"xy" (..., 2), "rot" (..., 2) and "step" (...) of queries `q` of episodes `b` placing catalog rows `objects`
    (index tensors of one shape): the model's own for that object (`out["placing"]`, model.py) when it has them,
    else the query's one position, rotation and step."""
    if "placing" in out:
        return out["placing"](b, q, objects)
    return {key: out[key][b, q] for key in ("xy", "rot", "step")}


def match_cost(present: torch.Tensor, obj_logp: torch.Tensor, xy: torch.Tensor, y_obj: torch.Tensor,
               y_xy: torch.Tensor, w_object: float, w_position: float) -> torch.Tensor:
    """(Q, M) matching cost of one episode: present (Q,) logits, obj_logp (Q, O) and xy (Q, M, 2) (query i's
    position if it places target object j) against the target's y_obj (M,) catalog rows and y_xy (M, 2)."""
    cls = -F.logsigmoid(present)[:, None] - obj_logp[:, y_obj]  # (Q, M)
    dist = ((xy - y_xy[None, :, :]) ** 2).sum(-1)  # (Q, M)
    return w_object * cls + w_position * POSITION_SCALE * dist


def assign(out: dict, batch: dict, cfg: LossWeights) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per episode, the optimal (query rows, target rows) of the Hungarian matching on `match_cost`."""
    pairs = []
    n_queries = out["present"].shape[1]
    with torch.no_grad():
        for b in range(len(batch["y_mask"])):
            m = int(batch["y_mask"][b].sum())
            y_obj = batch["y_obj"][b, :m]
            q = torch.arange(n_queries, device=y_obj.device)[:, None].expand(-1, m)
            xy = placing(out, torch.full_like(q, b), q, y_obj[None].expand(n_queries, -1))["xy"]  # (Q, M, 2)
            cost = match_cost(out["present"][b].float(), out["obj"][b].float(), xy.float(), y_obj,
                              batch["y_xy"][b, :m].float(), cfg.w_object, cfg.w_position)
            pairs.append(linear_sum_assignment(cost.cpu().numpy()))
    return pairs


def set_loss(out: dict, batch: dict, cfg: LossWeights,
             pairs: list[tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, torch.Tensor]:
    """The matching loss of a batch (module docstring): "loss" and its five parts.

    Args:
        out: the model's outputs, "present" (B, Q), "obj" (B, Q, O) log-probabilities, "xy" (B, Q, 2),
            "rot" (B, Q, 2) unit (sin, cos), "step" (B, Q).
        batch: the labels, "y_obj" (B, M), "y_xy" (B, M, 2), "y_rot" (B, M) radians, "y_step" (B, M), "y_mask".
        cfg: the weights (`ModelConfig`).
        pairs: the assignment, if already made (else `assign`).
    """
    pairs = assign(out, batch, cfg) if pairs is None else pairs
    b_idx = torch.as_tensor(np.concatenate([np.full(len(q), b) for b, (q, _) in enumerate(pairs)]), dtype=torch.long)
    q_idx = torch.as_tensor(np.concatenate([q for q, _ in pairs]), dtype=torch.long)
    t_idx = torch.as_tensor(np.concatenate([t for _, t in pairs]), dtype=torch.long)
    device = out["present"].device
    b_idx, q_idx, t_idx = b_idx.to(device), q_idx.to(device), t_idx.to(device)
    n = max(len(q_idx), 1)

    matched = torch.zeros_like(out["present"])
    matched[b_idx, q_idx] = 1.0
    weight = matched + cfg.absent_weight * (1.0 - matched)
    l_present = (F.binary_cross_entropy_with_logits(out["present"], matched, reduction="none") * weight).sum() \
        / weight.sum()
    l_object = -out["obj"][b_idx, q_idx, batch["y_obj"][b_idx, t_idx]].sum() / n
    placed = placing(out, b_idx, q_idx, batch["y_obj"][b_idx, t_idx])  # each query placing its matched object
    l_position = POSITION_SCALE * ((placed["xy"] - batch["y_xy"][b_idx, t_idx]) ** 2).sum() / n
    y_rot = batch["y_rot"][b_idx, t_idx]
    rot = placed["rot"]  # (P, 2) = (sin, cos): cos(error) = sin_p sin_t + cos_p cos_t
    l_rotation = (1.0 - (rot[:, 0] * torch.sin(y_rot) + rot[:, 1] * torch.cos(y_rot))).sum() / n
    l_step = ((placed["step"] - batch["y_step"][b_idx, t_idx]) ** 2).sum() / n
    total = (cfg.w_present * l_present + cfg.w_object * l_object + cfg.w_position * l_position
             + cfg.w_rotation * l_rotation + cfg.w_step * l_step)
    return {"loss": total, "present": l_present, "object": l_object, "position": l_position, "rotation": l_rotation,
            "step": l_step}
