"""The set-prediction transformer: an encoder over the context objects, N learned queries, one object per query.

Architecture (B batch, T context tokens, Q = `n_queries`, d = `d_model`, O = catalog objects):

    object embedding E_o (O, d) = id + type + colours + materials + shape + pattern embeddings
    context token (B, T, d) = MLP(token features + Fourier features of its positions; encoding.py)
                              + E[its object] + context-trial embedding + table embedding
    target token (B, 1, d)  = table embedding + MLP(table geometry, k / 4) + a learned "target" vector
    encoder: a transformer over [target | context tokens], full attention, padding masked (a set: no order
             besides the step and trial features each token carries)
    decoder: Q learned query embeddings; self-attention among the queries, cross-attention to the encoder output
    pointer: per query, one attention a (B, Q, 1 + T) over the encoder outputs [target | context tokens]
             (softmax of (W_q h) . (W_k m) / sqrt(d), padding masked): the query points at context objects
    per query, from its output h and its pointer a:
      present: a logit;
      object:  p(o) = sum over context tokens t of a_t [object_t = o]  +  a_target * g(o), where the generator
               g = softmax((W h) . E_o / sqrt(d) + copy(share_o)) over the whole catalog, share_o the fraction of
               context arrangements holding o and copy a small MLP (a pointer-generator; at context 0 every query
               points at the target token and g decides alone);
      where, rotation, step: for the object o it places, the pointer's mean over the context tokens *of that
               object* of their positions carried onto the target table, their (sin, cos) and their placement steps
               (`placing`; an object the context lacks: the whole pointer's mean, the target token standing for
               the table's centre, (sin, cos) = (0, 0) (no rotation to start from) and the first step), each
               plus a linear correction: RESIDUAL_SCALE x (dx, dy); (sin, cos) added, then normalised; step
               (step / n_queries) added. What the person did
               with this object before is the starting point, as the slot heuristic's answer is the learned slot
               model's.

Why a pointer, and classification over the catalog (not features + nearest catalog object): the prediction must
name catalog ids (object accuracy is by id, matching by features), and what a person sets is mostly what they set
before, where they set it: pointing at the context objects copies both, and attending to the same object in several
context arrangements averages its positions, which is what an alignment would do, learned instead of hand-built.
Restricting the position to the tokens of the placed object keeps a query that hesitates between two objects
from placing either at the midpoint of both. The generator covers what the context does not show (context 0, an object the person never used), with tied
embeddings so that objects sharing features share evidence. Regressing features and snapping to the nearest
catalog object would lose the id of an object the person used and tie between objects with equal features.

Training: the Hungarian matching loss (matching.py). Decoding: the queries with P(present) >= `threshold` (at
least `min_objects`, most likely first, at most Q); their objects by one Hungarian assignment on -log p(object |
query) (`linear_sum_assignment`: no catalog object twice, as in every arrangement of the data); each position,
rotation and step for the object placed (`placing`); in order of the predicted step.

Usage:
    model = SetTransformer(ModelConfig(d_model=32, n_encoder_layers=1, n_decoder_layers=1), vocab)
    out = model(batch)                                  # per-query outputs
    objs, xy, rot = model.decode(batch, min_objects=3)  # per episode: catalog rows, (n, 2), (n,) degrees
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
from degusta_learn.baselines.set_transformer.encoding import CARRIED, POSITIONS, ROTATION, STEP, TOKEN_DIM
from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError
from degusta_learn.names import CONTEXT_LENGTHS

N_FREQ = 4
RESIDUAL_SCALE = 0.1  # the position head's output x this = the residual added to the pointed-at positions
N_POSITIONS = POSITIONS.stop - POSITIONS.start


@dataclass
class ModelConfig:
    """The `model:` section of a set_transformer train config."""

    d_model: int = bounded(128, 1, 8192)
    """Token width; larger fits more styles but trains slower."""
    n_heads: int = bounded(4, 1, 256)
    """Attention heads (must divide d_model)."""
    n_encoder_layers: int = bounded(3, 1, 128)
    """Transformer layers over the context tokens."""
    n_decoder_layers: int = bounded(3, 1, 128)
    """Decoder layers (query self-attention + cross-attention to the context)."""
    d_ff: int = bounded(256, 1, 65_536)
    """Feed-forward width inside each layer."""
    dropout: float = 0.0
    """Dropout in the transformer layers."""
    n_queries: int = bounded(20, 1, 1000)
    """Learned queries: the most objects one prediction can place; at least the largest arrangement's object
    count of the dataset (checked when training starts)."""
    w_present: float = bounded(1.0, 0.0)
    """Loss weight of present / absent per query."""
    absent_weight: float = bounded(1.0, 0.0)
    """Weight of an unmatched query inside the present loss (DETR's no-object weight). 1 keeps P(present)
    calibrated, so decoding's P >= 0.5 rule places about as many objects as the person; below 1 places more."""
    w_object: float = bounded(1.0, 0.0)
    """Loss weight of the object classification; also the class term's weight in the matching cost."""
    w_position: float = bounded(1.0, 0.0)
    """Loss weight of the squared position error (x 100); also the position term's weight in the matching cost."""
    w_rotation: float = bounded(0.2, 0.0)
    """Loss weight of the circular rotation loss (1 - cos of the error)."""
    w_step: float = bounded(0.2, 0.0)
    """Loss weight of the placement-step regression (it orders the prediction)."""

    def __post_init__(self):
        for key in ("d_model", "n_heads", "n_encoder_layers", "n_decoder_layers", "d_ff", "n_queries"):
            if getattr(self, key) < 1:
                raise DegustaError(f"model.{key}: expected >= 1, got {getattr(self, key)}")
        if self.d_model % self.n_heads:
            raise DegustaError(f"model.n_heads: {self.n_heads} does not divide model.d_model={self.d_model}")
        if not 0.0 <= self.dropout < 1.0:
            raise DegustaError(f"model.dropout: expected in [0, 1), got {self.dropout}")
        for key in ("w_present", "absent_weight", "w_object", "w_position", "w_rotation", "w_step"):
            if getattr(self, key) < 0 or not math.isfinite(getattr(self, key)):
                raise DegustaError(f"model.{key}: expected a finite weight >= 0, got {getattr(self, key)}")
        if self.w_object == 0 and self.w_position == 0:
            raise DegustaError("model.w_object / model.w_position: both 0 leaves the matching cost empty; "
                               "give at least one a positive weight")


def _mlp(d_in: int, d: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d), nn.GELU(), nn.Linear(d, d_out))


class SetTransformer(nn.Module):
    def __init__(self, cfg: ModelConfig, vocab: Vocab):
        super().__init__()
        self.cfg, self.vocab = cfg, vocab
        d = cfg.d_model
        self.register_buffer("codes", torch.as_tensor(vocab.codes), persistent=False)  # (O, len(FEATURES))
        self.register_buffer("second", torch.as_tensor(vocab.second), persistent=False)  # (O, 2)
        self.obj_id = nn.Embedding(vocab.n_objects, d)
        self.obj_feat = nn.ModuleList(nn.Embedding(n, d) for n in vocab.sizes)
        self.tok_in = _mlp(TOKEN_DIM + GEOM_DIM + N_POSITIONS * 2 * N_FREQ, d, d)
        self.trial = nn.Embedding(max(CONTEXT_LENGTHS), d)
        self.table = nn.Embedding(len(vocab.tables) + 1, d)  # last row: a table unseen in training
        self.tgt_in = _mlp(GEOM_DIM + 1, d, d)
        self.tgt_flag = nn.Parameter(torch.zeros(d))
        enc = nn.TransformerEncoderLayer(d, cfg.n_heads, cfg.d_ff, cfg.dropout, activation="gelu", batch_first=True,
                                         norm_first=True)
        self.encoder = nn.TransformerEncoder(enc, cfg.n_encoder_layers, norm=nn.LayerNorm(d),
                                             enable_nested_tensor=False)
        self.queries = nn.Embedding(cfg.n_queries, d)
        dec = nn.TransformerDecoderLayer(d, cfg.n_heads, cfg.d_ff, cfg.dropout, activation="gelu", batch_first=True,
                                         norm_first=True)
        self.decoder = nn.TransformerDecoder(dec, cfg.n_decoder_layers, norm=nn.LayerNorm(d))
        self.head = nn.Linear(d, 6)  # [present | dx, dy | sin, cos | step]
        self.ptr_q, self.ptr_k = nn.Linear(d, d), nn.Linear(d, d)
        self.obj_query = nn.Linear(d, d)
        self.copy = _mlp(1, 16, 1)

    def object_table(self) -> torch.Tensor:
        """(O, d) embedding of every catalog object: id + its discrete features (both colours and materials)."""
        e = self.obj_id.weight
        for i, emb in enumerate(self.obj_feat):
            e = e + emb(self.codes[:, i])
        return e + self.obj_feat[1](self.second[:, 0]) + self.obj_feat[2](self.second[:, 1])

    def forward(self, batch: dict) -> dict:
        """Per-query outputs: "present" (B, Q) logits, "obj" (B, Q, O) log-probabilities; from the whole pointer,
        "xy" (B, Q, 2) image coordinates, "rot" (B, Q, 2) unit (sin, cos), "step" (B, Q); and "placing", the
        position, rotation and step of a query for a given object (see below), which training and decoding use."""
        E = self.object_table()
        feat, mask = batch["tok_feat"], batch["tok_mask"]  # (B, T, F), (B, T)
        x = (self.tok_in(torch.cat([feat, fourier(feat[..., POSITIONS], N_FREQ)], -1)) + E[batch["tok_obj"]]
             + self.trial(batch["tok_trial"]) + self.table(batch["tok_table"]))  # (B, T, d)
        k = batch["k"].to(feat.dtype)[:, None] / max(CONTEXT_LENGTHS)
        tgt = self.table(batch["tgt_table"]) + self.tgt_in(torch.cat([batch["tgt_geom"], k], -1)) + self.tgt_flag
        pad = torch.cat([mask.new_zeros(len(mask), 1), ~mask], 1)  # (B, 1 + T); the target token is never padding
        memory = self.encoder(torch.cat([tgt[:, None], x], 1), src_key_padding_mask=pad)  # (B, 1 + T, d)
        h = self.decoder(self.queries.weight.expand(len(mask), -1, -1), memory, memory_key_padding_mask=pad)
        out = self.head(h)  # (B, Q, 6)
        # the pointer: (B, Q, 1 + T) attention over [target | context tokens]
        att = (self.ptr_q(h) @ self.ptr_k(memory).transpose(1, 2)) / math.sqrt(self.cfg.d_model)
        att = att.masked_fill(pad[:, None, :], float("-inf")).softmax(-1)
        centre = batch["tgt_geom"][:, None, 6:8]  # table_geometry: cx, cy
        carried = feat[..., CARRIED]  # (B, T, 2)
        # what each pointed-at token shows: [position on the target table | rotation (sin, cos) | placement step];
        # the target token stands for the table's centre, (sin, cos) = (0, 0) (nothing to start from), the first step
        shown = torch.cat([torch.cat([centre, feat.new_zeros(len(feat), 1, 3)], -1),
                           torch.cat([carried, feat[..., ROTATION], feat[..., STEP, None]], -1)], 1)  # (B, 1 + T, 5)
        # objects: copied from the pointed-at tokens, the target token's share from the generator
        gen = ((self.obj_query(h) @ E.T) / math.sqrt(self.cfg.d_model)
               + self.copy(batch["share"][..., None])[..., 0][:, None]).softmax(-1)  # (B, Q, O)
        copied = torch.zeros_like(gen).scatter_add_(-1, batch["tok_obj"][:, None].expand(-1, gen.shape[1], -1),
                                                    att[..., 1:])
        p_obj = copied + att[..., :1] * gen
        pointed = att @ shown  # (B, Q, 5): what the query points at, whatever object it places

        def corrected(seen: torch.Tensor, head: torch.Tensor) -> dict[str, torch.Tensor]:
            """What a query points at, `seen` (..., 5), plus its heads' corrections, `head` (..., 6)."""
            return {"xy": seen[..., :2] + RESIDUAL_SCALE * head[..., 1:3],
                    "rot": F.normalize(seen[..., 2:4] + head[..., 3:5], dim=-1, eps=1e-6),
                    "step": seen[..., 4] + head[..., 5]}

        def placing(b: torch.Tensor, q: torch.Tensor, o: torch.Tensor) -> dict[str, torch.Tensor]:
            """Position (..., 2), rotation (..., 2) and step (...) of query q of episode b when it places catalog
            row o (index tensors of one shape): the pointer restricted to the context tokens of that object, else
            (an object the context lacks) the whole pointer; plus the heads' corrections."""
            w = att[b, q, 1:] * ((batch["tok_obj"][b] == o[..., None]) & mask[b])  # (..., T)
            total = w.sum(-1, keepdim=True)
            same = (w[..., None] * shown[b, 1:]).sum(-2) / total.clamp_min(1e-30)
            return corrected(torch.where(total > 0, same, pointed[b, q]), out[b, q])

        return {"present": out[..., 0], "obj": p_obj.clamp_min(1e-12).log(), **corrected(pointed, out),
                "placing": placing}

    @torch.no_grad()
    def decode(self, batch: dict, min_objects: int = 1, threshold: float = 0.5
               ) -> tuple[list[list[int]], list[np.ndarray], list[np.ndarray]]:
        """Predict every episode of `batch` (see the module docstring).

        Returns:
            (objects, xy, rotations): per episode a list of catalog rows, an (n, 2) array of positions and an
            (n,) array of rotations in degrees [0, 360), in placement order.
        """
        was_training = self.training
        self.eval()
        out = self(batch)
        self.train(was_training)
        p = torch.sigmoid(out["present"].float()).cpu().numpy()
        logp = out["obj"].float().cpu().numpy()
        objs, xys, rots = [], [], []
        for b in range(len(p)):
            ranked = np.argsort(-p[b], kind="stable")
            n = int((p[b] >= threshold).sum())
            chosen = ranked[:min(max(n, min_objects), len(ranked))]
            rows, cols = linear_sum_assignment(-logp[b, chosen])  # no catalog object twice
            q = torch.as_tensor(chosen[rows], device=out["step"].device)
            placed = {k: v.float().cpu().numpy().astype(float)
                      for k, v in out["placing"](torch.full_like(q, b), q, torch.as_tensor(cols, device=q.device)).items()}
            order = np.argsort(placed["step"], kind="stable")
            objs.append(cols[order].tolist())
            xys.append(placed["xy"][order])
            rots.append(np.rad2deg(np.arctan2(placed["rot"][order, 0], placed["rot"][order, 1])) % 360.0)
        return objs, xys, rots
