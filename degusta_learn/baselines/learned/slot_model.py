"""The slot model: a transformer over a participant's slots that decides, per slot, what the target gets.

Architecture (B batch, S slots, d = `d_model`, O = catalog objects):

    slot token (B, S, d) = MLP(slot features, Fourier of its carried position; slots.py)
                           + type embedding
                           + vote-weighted mean embedding of the objects that filled it
                           (object embedding = id + type + colours + materials + shape + pattern)
    target-table token (B, 1, d) = table id + MLP(table geometry)
    a transformer over [target table | slots], full attention (a set: no order)
    per slot, from its output h:
      1. set or not: a logit (binary cross-entropy);
      2. which object: (W h) . E_o / sqrt(d) + a learned function of copy features (the object's vote share
         in this slot, the share of context arrangements holding it anywhere, its votes in other slots of
         the type, how common its colours and materials are among the person's objects), over the objects
         of the slot's type (cross-entropy on the slots the target sets);
      3. where: the slot's carried position + a learned residual (squared error after removing the
         residuals' mean over the set slots: the metric registers layouts, a common shift is free);
      4. rotation: the members' mean (sin, cos) + a learned (sin, cos), normalized (loss 1 - cos of the error);
      5. the placement step, for order: the members' mean context step + a learned residual (squared error).
    Position, rotation and step start from what the context shows (the slot heuristic's answer); the heads
    learn the corrections.

Decoding: the slots with P(set) >= 0.5 (at least `min_objects`, most likely first); objects by one
Hungarian assignment over those slots (scipy `linear_sum_assignment` on -log P(object | slot), so no object
is placed twice); positions and rotations from the heads; placed in order of the predicted step.

Why slots and not object-by-object generation: the metric matches objects by their features and then
registers the layouts, so an arrangement is right when it holds the person's objects in the person's
relative layout. A person's habits show up in the context as recurring slots; deciding per slot
(set it? with which of the objects that filled it? where exactly?) is the decision the task asks for, and
a set model makes it with full view of every other slot. The autoregressive token decoder this replaced
had to discover the correspondences itself and lost to the `consensus` heuristic (docs/learned.md).

Usage:
    model = SlotModel(ModelConfig(d_model=32, n_layers=1), vocab)
    out = model(batch)                       # per-slot outputs
    losses = model.loss(batch, out)          # dict with "loss" and its parts
    objs, xy, rot = model.decode(batch, min_objects=3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import nn

from degusta_learn.baselines.learned.features import GEOM_DIM, Vocab, fourier
from degusta_learn.baselines.learned.slots import SLOT_DIM, SLOT_FEATURES
from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError

N_FREQ = 4
RESIDUAL_SCALE = 0.05  # the position head's output x this = residual in normalized table units
POSITION = slice(SLOT_FEATURES.index("u"), SLOT_FEATURES.index("dy") + 1)  # u, v, dx, dy: Fourier-encoded
CONTEXT = SLOT_FEATURES.index("k / 4")
MEAN_STEP = SLOT_FEATURES.index("mean step / max_objects")


@dataclass
class ModelConfig:
    """The `model:` section of a learned train config."""

    d_model: int = bounded(128, 1, 8192)
    """Token width; larger fits more styles but trains slower."""
    n_layers: int = bounded(3, 1, 128)
    """Transformer layers."""
    n_heads: int = bounded(4, 1, 256)
    """Attention heads (must divide d_model)."""
    d_ff: int = bounded(256, 1, 65_536)
    """Feed-forward width inside each layer."""
    dropout: float = 0.0
    """Dropout in the transformer."""
    max_objects: int = bounded(20, 1, 1000)
    """Most objects one arrangement may have (and the most a prediction places)."""
    w_set: float = 1.0
    """Loss weight of the set / not-set classification per slot."""
    w_object: float = 1.0
    """Loss weight of the object classification (on the slots the target sets)."""
    w_position: float = 1.0
    """Loss weight of the position residual (squared error x 100, after removing the mean residual)."""
    w_rotation: float = 0.2
    """Loss weight of the circular rotation loss."""
    w_step: float = 1.0
    """Loss weight of the placement-step regression (it orders the prediction)."""

    def __post_init__(self):
        for key in ("d_model", "n_layers", "n_heads", "d_ff", "max_objects"):
            if getattr(self, key) < 1:
                raise DegustaError(f"model.{key}: expected >= 1, got {getattr(self, key)}")
        if self.d_model % self.n_heads:
            raise DegustaError(f"model.n_heads: {self.n_heads} does not divide model.d_model={self.d_model}")
        if not 0.0 <= self.dropout < 1.0:
            raise DegustaError(f"model.dropout: expected in [0, 1), got {self.dropout}")


def _mlp(d_in: int, d: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d), nn.GELU(), nn.Linear(d, d_out))


class SlotModel(nn.Module):
    def __init__(self, cfg: ModelConfig, vocab: Vocab):
        super().__init__()
        self.cfg, self.vocab = cfg, vocab
        d = cfg.d_model
        self.n_types = len(vocab.types)
        self.register_buffer("codes", torch.as_tensor(vocab.codes), persistent=False)  # (O, len(FEATURES))
        self.register_buffer("second", torch.as_tensor(vocab.second), persistent=False)  # (O, 2)
        self.obj_id = nn.Embedding(vocab.n_objects, d)
        self.obj_feat = nn.ModuleList(nn.Embedding(n, d) for n in vocab.sizes)
        self.slot_in = _mlp(SLOT_DIM + 2 * 2 * 2 * N_FREQ, d, d)
        self.type_emb = nn.Embedding(self.n_types, d)
        self.votes_in = nn.Linear(d, d)
        self.table_id = nn.Embedding(len(vocab.tables) + 1, d)  # last row: a table unseen in training
        self.table_geom = _mlp(GEOM_DIM, d, d)
        layer = nn.TransformerEncoderLayer(d, cfg.n_heads, cfg.d_ff, cfg.dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, cfg.n_layers, norm=nn.LayerNorm(d), enable_nested_tensor=False)
        self.head = nn.Linear(d, 6)  # [set logit | residual dx, dy | residual sin, cos | residual step]
        self.obj_query = nn.Linear(d, d)
        self.copy = _mlp(5, 16, 1)

    def object_table(self) -> torch.Tensor:
        """(O, d) embedding of every catalog object: id + its discrete features."""
        e = self.obj_id.weight
        for i, emb in enumerate(self.obj_feat):
            e = e + emb(self.codes[:, i])
        return e + self.obj_feat[1](self.second[:, 0]) + self.obj_feat[2](self.second[:, 1])

    def forward(self, batch: dict) -> dict:
        """Per-slot outputs: "set" (B, S) logits, "obj" (B, S, O) log-probabilities (-inf off the slot's
        type), "xy" (B, S, 2) positions, "rot" (B, S, 2) unit (sin, cos), "step" (B, S); each of the last three
        is the slot's own (carried position, members' mean rotation and step) plus the head's correction."""
        E = self.object_table()
        feat, mask = batch["slot_feat"], batch["slot_mask"]
        votes = batch["slot_votes"]  # (B, S, O)
        members = votes.sum(-1, keepdim=True).clamp(min=1.0)
        x = (self.slot_in(torch.cat([feat, fourier(feat[..., POSITION], N_FREQ)], -1)) + self.type_emb(batch["slot_type"])
             + self.votes_in((votes / members) @ E))  # (B, S, d)
        tgt = self.table_id(batch["tgt_table"]) + self.table_geom(batch["tgt_geom"])  # (B, d)
        x = torch.cat([tgt[:, None], x], 1)
        pad = torch.cat([mask.new_zeros(mask.shape[0], 1), ~mask], 1)
        h = self.encoder(x, src_key_padding_mask=pad)[:, 1:]  # (B, S, d)
        out = self.head(h)
        # object choice: embedding match + copy features, restricted to the slot's type
        same_type = self.codes[:, 0][None, None] == batch["slot_type"][..., None]  # (B, S, O)
        type_votes = (votes * mask[..., None]).sum(1)  # (B, O) votes in every slot
        k = feat[..., CONTEXT:CONTEXT + 1].clamp(min=0.25) * 4  # context arrangements (population: 1)
        copy_feat = torch.cat([torch.stack([votes / members, batch["share"][:, None].expand_as(votes),
                                            (type_votes[:, None] - votes) / k], -1),
                               batch["taste"][:, None].expand(*votes.shape, 2)], -1)  # (B, S, O, 5)
        logits = (self.obj_query(h) @ E.T) / math.sqrt(self.cfg.d_model) + self.copy(copy_feat)[..., 0]
        logits = logits.masked_fill(~same_type, float("-inf"))
        rot = F.normalize(batch["slot_rot"] + out[..., 3:5], dim=-1, eps=1e-6)
        return {"set": out[..., 0], "obj": logits.log_softmax(-1), "xy": batch["slot_xy"] + RESIDUAL_SCALE * out[..., 1:3],
                "rot": rot, "step": feat[..., MEAN_STEP] + out[..., 5]}

    def loss(self, batch: dict, out: dict) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        mask, y_set = batch["slot_mask"], batch["y_set"]
        set_mask = mask & (y_set > 0)  # (B, S)
        n_set = set_mask.sum().clamp(min=1)
        l_set = F.binary_cross_entropy_with_logits(out["set"][mask], y_set[mask])
        y_obj = batch["y_obj"].clamp(min=0)
        l_obj = -torch.where(set_mask, out["obj"].gather(-1, y_obj[..., None])[..., 0], 0.0).sum() / n_set
        # position: translation-invariant squared error over the set slots of each episode
        w = set_mask.float()[..., None]
        err = (out["xy"] - batch["y_xy"]) * w  # (B, S, 2)
        mean_err = err.sum(1, keepdim=True) / w.sum(1, keepdim=True).clamp(min=1)
        l_pos = 100.0 * (((err - mean_err) * w) ** 2).sum() / n_set
        angle = torch.atan2(out["rot"][..., 0], out["rot"][..., 1])
        l_rot = ((1 - torch.cos(angle - batch["y_rot"])) * set_mask).sum() / n_set
        l_step = (((out["step"] - batch["y_step"]) ** 2) * set_mask).sum() / n_set
        total = (cfg.w_set * l_set + cfg.w_object * l_obj + cfg.w_position * l_pos + cfg.w_rotation * l_rot
                 + cfg.w_step * l_step)
        return {"loss": total, "set": l_set, "object": l_obj, "position": l_pos, "rotation": l_rot, "step": l_step}

    @torch.no_grad()
    def decode(self, batch: dict, min_objects: int = 1) -> tuple[list[list[int]], list[np.ndarray], list[np.ndarray]]:
        """Predict every episode of `batch` (see the module docstring).

        Returns:
            (objects, xy, rotations): per episode a list of catalog rows, an (n, 2) array of positions and an
            (n,) array of rotations in degrees [0, 360), in placement order.
        """
        was_training = self.training
        self.eval()
        out = self(batch)
        self.train(was_training)
        p_set = torch.sigmoid(out["set"].float()).cpu().numpy()
        logp = out["obj"].float().cpu().numpy()
        xy, rot = out["xy"].float().cpu().numpy(), out["rot"].float().cpu().numpy()
        step, mask = out["step"].float().cpu().numpy(), batch["slot_mask"].cpu().numpy()
        objs, xys, rots = [], [], []
        for b in range(len(mask)):
            real = np.nonzero(mask[b])[0]
            ranked = real[np.argsort(-p_set[b, real], kind="stable")]
            n = int((p_set[b, real] >= 0.5).sum())
            chosen = ranked[:min(max(n, min_objects), self.cfg.max_objects)]
            cost = np.where(np.isfinite(logp[b, chosen]), -logp[b, chosen], 1e9)  # (n, O)
            rows, cols = linear_sum_assignment(cost)
            keep = cost[rows, cols] < 1e9
            slots, obj = chosen[rows[keep]], cols[keep]
            order = np.argsort(step[b, slots], kind="stable")
            slots, obj = slots[order], obj[order]
            objs.append(obj.tolist())
            xys.append(xy[b, slots].astype(float))
            rots.append(np.rad2deg(np.arctan2(rot[b, slots, 0], rot[b, slots, 1])) % 360.0)
        return objs, xys, rots
