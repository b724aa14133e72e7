"""The arrangement model: a prefix-LM transformer over context object tokens that places objects one by one.

Architecture (shapes: B batch, C context tokens, T target objects, d = `d_model`):

    context tokens (B, C, d) = object(id + type + colours + materials + shape + pattern)
                               + MLP(position: absolute x, y, bounds-relative u, v, sin/cos rotation, Fourier)
                               + MLP(offset from its arrangement's centroid, centroid relative to the bounds)
                               + alignment group (identity embedding) + MLP(group support)   (align.py)
                               + placement index + context slot + table(id + geometry) + segment
    target-table token (B, 1, d) = table(id + geometry) + segment          (doubles as the start token)
    placed tokens (B, T, d)  = the same object/position embedding of each object placed so far
    one transformer over [context | target table | placed]: context and table see each other both ways
    (a set, order-free apart from the placement-index feature); placed tokens are causal.
    Output j (B, T+1, d) predicts step j+1:
      1. type (5 types + stop): linear head + a learned function of count features (how many of each type
         the context arrangements hold on average, how many are placed already);
      2. object id: dot product with the object embedding table + a learned copy prior (the share of
         context arrangements holding the object), restricted to that type and to objects not yet placed;
      3. position: each of K mixture components *points* (attention) at the tokens the output can see and
         takes the attention-weighted mean of their proposed positions (context object: carried onto the
         target table keeping its physical offset from its layout's centroid; placed object: where it is;
         target table: its centre), plus a small learned offset. The pointer logits get a learned bonus
         for context tokens holding the chosen object and for their alignment groups;
      4. rotation (sin, cos) from the same head.

Why autoregressive (not a set decoder): the metric registers the predicted layout to the truth (Kabsch)
after matching objects by features, so what counts is the *relative* layout of the right types. Placing
objects one at a time conditioned on those already placed keeps the layout self-consistent (the knife goes
beside the plate actually placed, not beside the average plate); a set decoder predicts all positions in
parallel and needs a matching loss. It also gives the count for free (the stop class) and matches the
data, which records placement order. Training uses teacher forcing; decoding is greedy.

Why a pointer for positions: a person's habit for an object is recorded in the context, so "where" is
mostly "where the corresponding object went in the other arrangements", averaged (which removes their
noise). Plain regression from the hidden state had to learn that lookup through an MLP and stalled at
~0.2 position error in the CPU budget; the pointer reaches it in one attention step. An auxiliary loss
(`w_pointer`) teaches the pointer which tokens correspond: in each context arrangement, the object of the
same type nearest the true position. Without the alignment groups and the identity bonus the pointer often
sent an object to another object's spot (in multi-setting layouts: the top plate to the bottom setting),
which the feature-matched Kabsch RMSD punishes hard (validation RMSD at context 4: 0.096 -> 0.083).

Position head (`position_head`): "mixture" (default) is a K-component Gaussian mixture (NLL loss) decoded as
the mean of the most likely component; "mse" is one pointer + offset with a squared-error loss. The squared
error targets the conditional mean, which is blurred where a style leaves two choices open (which of two
forks, which of two place settings); the mixture picks one mode and the later, conditioned steps build
around it. On validation the mixture was better (context 4 RMSD 0.084 vs 0.096 after 3 epochs). Positions
are absolute image coordinates, the metric's units. Rotation: (sin, cos) with a circular loss
1 - cos(error), since rotation is not scored and that loss is smooth and unambiguous at 0/360.

Usage:
    model = ArrangementModel(ModelConfig(d_model=32, n_layers=1), vocab)
    out = model(batch)                          # teacher-forced outputs
    losses = model.loss(batch, out)             # dict with "loss" and its parts
    objs, xy, rot = decode.greedy_decode(model, batch, min_objects=3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from degusta_learn.baselines.learned.features import GEOM_DIM, MAX_GROUPS, POS_DIM, REL_DIM, Vocab, fourier
from degusta_learn.errors import DegustaError

N_FREQ = 6
LOG_SIGMA0 = math.log(0.05)


@dataclass
class ModelConfig:
    """The `model:` section of a learned train config."""

    d_model: int = 128
    """Token width; larger fits more styles but trains slower."""
    n_layers: int = 3
    """Transformer layers."""
    n_heads: int = 4
    """Attention heads (must divide d_model)."""
    d_ff: int = 256
    """Feed-forward width inside each layer."""
    dropout: float = 0.1
    """Dropout in the transformer and heads."""
    max_objects: int = 20
    """Most objects one arrangement may have (and the most a prediction places)."""
    max_context: int = 4
    """Most context arrangements per episode."""
    position_head: str = "mixture"
    """"mixture" (Gaussian mixture, decode the top component's mean) or "mse" (direct regression)."""
    n_mixture: int = 4
    """Mixture components (position_head: mixture)."""
    align_context: bool = True
    """Give context tokens their alignment group (align.py: which objects play the same part across the
    context arrangements) as an identity embedding plus the group's support."""
    transfer: str = "centroid"
    """How the pointer carries a context object onto the target table: "centroid" (the layout's centre
    keeps its place relative to the surface bounds, objects keep their physical offsets from it) or
    "bounds" (each object keeps its own position relative to the bounds)."""
    w_type: float = 1.0
    """Loss weight of the type / stop classification."""
    w_object: float = 1.0
    """Loss weight of the object-id classification (within the true type)."""
    w_position: float = 1.0
    """Loss weight of the position (NLL for mixture, MSE * 100 for mse)."""
    w_rotation: float = 0.2
    """Loss weight of the circular rotation loss."""
    w_pointer: float = 1.0
    """Loss weight of the auxiliary pointer loss (look at the corresponding objects in the context)."""

    def __post_init__(self):
        if self.d_model % self.n_heads:
            raise DegustaError(f"model.n_heads: {self.n_heads} does not divide model.d_model={self.d_model}")
        if self.transfer not in ("centroid", "bounds"):
            raise DegustaError(f"model.transfer: expected 'centroid' or 'bounds', got {self.transfer!r}")
        if self.position_head not in ("mixture", "mse"):
            raise DegustaError(f"model.position_head: expected 'mixture' or 'mse', got {self.position_head!r}")
        for key in ("d_model", "n_layers", "d_ff", "max_objects", "n_mixture"):
            if getattr(self, key) < 1:
                raise DegustaError(f"model.{key}: expected >= 1, got {getattr(self, key)}")


def _mlp(d_in: int, d: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d), nn.GELU(), nn.Linear(d, d_out))


class ArrangementModel(nn.Module):
    def __init__(self, cfg: ModelConfig, vocab: Vocab):
        super().__init__()
        self.cfg, self.vocab = cfg, vocab
        d = cfg.d_model
        self.n_types = len(vocab.types)
        self.register_buffer("codes", torch.as_tensor(vocab.codes), persistent=False)  # (n_obj, len(FEATURES))
        self.register_buffer("second", torch.as_tensor(vocab.second), persistent=False)  # (n_obj, 2)
        self.obj_id = nn.Embedding(vocab.n_objects, d)
        self.obj_feat = nn.ModuleList(nn.Embedding(n, d) for n in vocab.sizes)
        self.pos = _mlp(POS_DIM + 4 * 2 * N_FREQ, d, d)
        self.rel = _mlp(REL_DIM, d, d)
        self.group = nn.Embedding(MAX_GROUPS, d) if cfg.align_context else None
        self.support = nn.Linear(1, d) if cfg.align_context else None
        self.step = nn.Embedding(cfg.max_objects, d)
        self.slot = nn.Embedding(cfg.max_context, d)
        self.segment = nn.Embedding(3, d)  # context token, target table, placed token
        self.table_id = nn.Embedding(len(vocab.tables) + 1, d)  # last row: a table unseen in training
        self.table_geom = _mlp(GEOM_DIM, d, d)
        layer = nn.TransformerEncoderLayer(d, cfg.n_heads, cfg.d_ff, cfg.dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, cfg.n_layers, norm=nn.LayerNorm(d), enable_nested_tensor=False)
        self.type_head = nn.Linear(d, self.n_types + 1)  # last class: stop
        self.type_cond = nn.Embedding(self.n_types, d)
        self.type_bias = _mlp(4, 16, 1)  # from per-type context counts (see context_counts)
        self.stop_bias = _mlp(4, 16, 1)
        self.copy_bias = _mlp(2, 16, 1)
        self.query = _mlp(d, d, d)
        self.obj_cond = nn.Linear(d, d)
        self.n_comp = cfg.n_mixture if cfg.position_head == "mixture" else 1
        self.place_in = _mlp(d, d, d)
        self.place_head = nn.Linear(d, 5 * self.n_comp + 2)  # [logits K | offsets 2K | log sigmas 2K | rot 2]
        self.ptr_query = nn.Linear(d, self.n_comp * d)
        self.ptr_key = nn.Linear(d, d)
        self.ptr_bias = nn.Parameter(torch.ones(self.n_comp, 2))  # identity cues, see identity_bias

    # --- embeddings ------------------------------------------------------------------------------------
    def object_table(self) -> torch.Tensor:
        """(n_obj, d) embedding of every catalog object: id + its discrete features."""
        e = self.obj_id.weight
        for i, emb in enumerate(self.obj_feat):
            e = e + emb(self.codes[:, i])
        return e + self.obj_feat[1](self.second[:, 0]) + self.obj_feat[2](self.second[:, 1])

    def _place(self, feat: torch.Tensor) -> torch.Tensor:
        return self.pos(torch.cat([feat, fourier(feat[..., :4], N_FREQ)], dim=-1))

    @staticmethod
    def position_features(xy: torch.Tensor, rot: torch.Tensor, geom: torch.Tensor) -> torch.Tensor:
        """Torch twin of `features.position_features`: xy (B, T, 2), rot (B, T) radians, geom (B, GEOM_DIM)."""
        lo, size = geom[:, None, 0:2], geom[:, None, 4:6].clamp(min=1e-6)
        uv = (xy - lo) / size * 2 - 1
        return torch.cat([xy, uv, rot.sin()[..., None], rot.cos()[..., None]], dim=-1)  # (B, T, POS_DIM)

    def _table(self, idx: torch.Tensor, geom: torch.Tensor) -> torch.Tensor:
        return self.table_id(idx) + self.table_geom(geom)

    def encode(self, batch: dict, y_obj: torch.Tensor, y_feat: torch.Tensor, y_mask: torch.Tensor) -> dict:
        """Run the transformer over [context | target table | placed objects].

        Returns a dict: "h" (B, T+1, d) outputs at [target table, placed_1..placed_T] (output j predicts
        step j+1), and for the position pointer "keys" (B, L, d) of every token, "cand" (B, L, 2) the
        position each token proposes on the target table (context object: its position carried over
        relative to the surface bounds; target table: its centre; placed object: where it was placed) and
        "allowed" (B, T+1, L) which tokens each output may point at (what it may attend to).
        """
        E = self.object_table()
        C, T = batch["ctx_obj"].shape[1], y_obj.shape[1]
        geom = batch["tgt_geom"]
        ctx = (E[batch["ctx_obj"]] + self._place(batch["ctx_feat"]) + self.rel(batch["ctx_rel"])
               + (self.group(batch["ctx_group"]) + self.support(batch["ctx_support"]) if self.cfg.align_context else 0)
               + self.step(batch["ctx_step"])
               + self.slot(batch["ctx_slot"].clamp(max=self.cfg.max_context - 1))
               + self._table(batch["ctx_table"], batch["ctx_geom"]) + self.segment.weight[0])  # (B, C, d)
        tgt = self._table(batch["tgt_table"], geom)  # (B, d)
        steps = torch.arange(T, device=y_obj.device).clamp(max=self.cfg.max_objects - 1)
        placed = E[y_obj] + self._place(y_feat) + self.step(steps) + tgt[:, None] + self.segment.weight[2]
        x = torch.cat([ctx, (tgt + self.segment.weight[1])[:, None], placed], dim=1)  # (B, C+1+T, d)
        L = C + 1 + T
        # attn_mask True = blocked: prefix tokens never see placed tokens; placed token j sees placed <= j.
        q = torch.arange(L, device=x.device)
        blocked = (q[None, :] > C) & (q[None, :] > q[:, None])  # (L, L)
        pad = torch.cat([~batch["ctx_mask"], y_mask.new_zeros(y_mask.shape[0], 1), ~y_mask], dim=1)  # (B, L)
        h = self.encoder(x, mask=blocked, src_key_padding_mask=pad)  # (B, L, d)
        lo, size = geom[:, None, 0:2], geom[:, None, 4:6]
        rel = batch["ctx_rel"]  # context candidates keep their physical offsets from their layout's centre
        carried = lo + (rel[..., 2:4] + 1) / 2 * size + rel[..., 0:2] if self.cfg.transfer == "centroid" else \
            lo + (batch["ctx_feat"][..., 2:4] + 1) / 2 * size
        cand = torch.cat([carried, geom[:, None, 6:8], y_feat[..., :2]], 1)
        allowed = ~blocked[None, C:] & ~pad[:, None, :]  # (B, T+1, L)
        return {"h": h[:, C:], "keys": self.ptr_key(h), "cand": cand, "allowed": allowed,
                "ctx_obj": batch["ctx_obj"], "ctx_group": batch["ctx_group"],
                **self.context_counts(batch, y_obj, y_mask)}

    def context_counts(self, batch: dict, y_obj: torch.Tensor, y_mask: torch.Tensor) -> dict:
        """Count features that make "set what this person usually sets" one linear step away.

        "share" (B, n_obj): fraction of the context arrangements that contain each object;
        "type_feat" (B, T+1, n_types, 3): per output and type, [mean count per context arrangement,
        count placed so far, their difference]; "k" (B,): number of context arrangements.
        """
        n_obj = self.vocab.n_objects
        mask = batch["ctx_mask"]
        onehot = F.one_hot(batch["ctx_obj"], n_obj).float() * mask[..., None]  # (B, C, n_obj)
        slots = torch.where(mask, batch["ctx_slot"] + 1, 0)  # (B, C); a zero column keeps amax defined at C = 0
        k = torch.cat([slots, slots.new_zeros(slots.shape[0], 1)], 1).amax(1).float()  # (B,)
        share = onehot.sum(1) / k.clamp(min=1)[:, None]  # (B, n_obj)
        by_type = F.one_hot(self.codes[:, 0], self.n_types).float()  # (n_obj, n_types)
        mean_count = share @ by_type  # (B, n_types)
        placed = F.one_hot(y_obj, n_obj).float() * y_mask[..., None]  # (B, T, n_obj)
        placed = torch.cat([placed.new_zeros(placed.shape[0], 1, n_obj), placed.cumsum(1)], 1) @ by_type  # (B, T+1, n_types)
        mc = mean_count[:, None].expand_as(placed)
        return {"share": share, "k": k, "type_feat": torch.stack([mc, placed, mc - placed], -1)}

    def type_logits(self, enc: dict) -> torch.Tensor:
        """(B, T+1, n_types + 1) logits of each type and of stopping, for every output."""
        tf, has = enc["type_feat"], (enc["k"] > 0).float()[:, None, None, None]
        tf = torch.cat([tf, has.expand(*tf.shape[:-1], 1)], -1)  # (B, T+1, n_types, 4)
        left = torch.cat([tf[..., 2:3].clamp(min=0).sum(2), tf[..., :2].sum(2), tf[:, :, :1, 3]], -1)  # (B, T+1, 4)
        bias = torch.cat([self.type_bias(tf).squeeze(-1), self.stop_bias(left)], -1)
        return self.type_head(enc["h"]) + bias

    # --- heads ---------------------------------------------------------------------------------------
    def object_logits(self, enc: dict, type_idx: torch.Tensor, rows: slice = slice(None)) -> torch.Tensor:
        """Logits (B, Q, n_obj) of each object for outputs `enc["h"][:, rows]`, given the step's type (B, Q).

        A learned function of how often the object appears in the context is added (a copy prior)."""
        q = self.query(enc["h"][:, rows] + self.type_cond(type_idx))
        share = enc["share"]
        prior = self.copy_bias(torch.stack([share, (share > 0).float()], -1)).squeeze(-1)  # (B, n_obj)
        return q @ self.object_table().T / math.sqrt(self.cfg.d_model) + prior[:, None]

    def placement(self, enc: dict, obj: torch.Tensor, rows: slice = slice(None)) -> dict:
        """Position / rotation of placing object `obj` (B, Q) (catalog rows) at outputs `enc["h"][:, rows]`.

        Each of the K mixture components (K = 1 for "mse") points at one token's proposed position
        (softmax attention over the tokens the output may see) and adds a learned offset: copying a context
        object's place, or placing next to an object already put down, is one attention step away.
        """
        h, allowed = enc["h"][:, rows], enc["allowed"][:, rows]  # (B, Q, d), (B, Q, L)
        z = self.place_in(h + self.obj_cond(self.object_table()[obj]))  # (B, Q, d)
        K = self.n_comp
        out = self.place_head(z)  # (B, Q, K * 5 + 2)
        qk = self.ptr_query(z).unflatten(-1, (K, -1))  # (B, Q, K, d)
        att = torch.einsum("bqkd,bld->bqkl", qk, enc["keys"]) / math.sqrt(qk.shape[-1])
        att = att + self.identity_bias(enc, obj)  # look where this very object (and its group) went
        att = att.masked_fill(~allowed[:, :, None, :], float("-inf")).softmax(-1)  # (B, Q, K, L)
        base = torch.einsum("bqkl,blc->bqkc", att, enc["cand"])  # (B, Q, K, 2)
        res = {"rot": out[..., -2:], "mu": base + 0.1 * out[..., K:3 * K].unflatten(-1, (K, 2)), "att": att,
               "cand": enc["cand"]}
        if self.cfg.position_head == "mse":
            res["xy"] = res["mu"][..., 0, :]
        else:
            res["logit"] = out[..., :K]
            # sigma starts near 0.05 (a few cm of table), so the NLL pulls the means from the first step
            res["log_sigma"] = (out[..., 3 * K:5 * K].unflatten(-1, (K, 2)) + LOG_SIGMA0).clamp(-7.0, 0.0)
            top = res["logit"].argmax(-1)[..., None, None].expand(*res["logit"].shape[:-1], 1, 2)
            res["xy"] = res["mu"].gather(-2, top).squeeze(-2)
        return res

    def identity_bias(self, enc: dict, obj: torch.Tensor) -> torch.Tensor:
        """(B, Q, K, L) pointer-logit bonus, learned per component: for context tokens holding the object
        being placed, and (with align_context) for tokens in the same alignment group as any of them."""
        ctx_obj = enc["ctx_obj"]  # (B, C)
        C, L = ctx_obj.shape[1], enc["cand"].shape[1]
        same = (ctx_obj[:, None, :] == obj[..., None]).float()  # (B, Q, C)
        cues = [same]
        if self.cfg.align_context:
            groups = F.one_hot(enc["ctx_group"], MAX_GROUPS).float()  # (B, C, G)
            has = (same @ groups).clamp(max=1)  # (B, Q, G): groups holding the object
            cues.append(has @ groups.transpose(1, 2))  # (B, Q, C): tokens of those groups
        bonus = torch.einsum("bqcn,kn->bqkc", torch.stack(cues, -1), self.ptr_bias[:, :len(cues)])
        return F.pad(bonus, (0, L - C))  # no bonus for the target-table and placed tokens

    def forward(self, batch: dict) -> dict:
        """Teacher-forced outputs for a batch with targets."""
        enc = self.encode(batch, batch["y_obj"], batch["y_feat"], batch["y_mask"])  # h: (B, T+1, d)
        y_type = self.codes[batch["y_obj"], 0]  # (B, T)
        steps = slice(0, -1)  # outputs that predict the T real objects
        return {"type_logits": self.type_logits(enc), "obj_logits": self.object_logits(enc, y_type, steps),
                "place": self.placement(enc, batch["y_obj"], steps)}

    def loss(self, batch: dict, out: dict) -> dict[str, torch.Tensor]:
        """Weighted sum of the type/stop, object, position and rotation losses (means over real steps)."""
        cfg, y_obj, mask = self.cfg, batch["y_obj"], batch["y_mask"]
        B, T = y_obj.shape
        lengths = mask.sum(1)  # (B,)
        type_tgt = torch.full((B, T + 1), -100, dtype=torch.long, device=y_obj.device)
        type_tgt[:, :T] = torch.where(mask, self.codes[y_obj, 0], -100)
        type_tgt[torch.arange(B), lengths] = self.n_types  # stop after the last object
        l_type = F.cross_entropy(out["type_logits"].flatten(0, 1), type_tgt.flatten(), ignore_index=-100)
        # object: restrict to the true type and to objects not yet placed
        logits = out["obj_logits"]
        same_type = self.codes[:, 0][None, None, :] == self.codes[y_obj, 0][..., None]  # (B, T, n_obj)
        onehot = F.one_hot(y_obj, self.vocab.n_objects) * mask[..., None]
        placed = (onehot.cumsum(1) - onehot) > 0
        logits = logits.masked_fill(~same_type | placed, float("-inf"))
        l_obj = F.cross_entropy(logits[mask], y_obj[mask])
        p, xy = out["place"], batch["y_xy"]
        if cfg.position_head == "mse":
            l_pos = 100.0 * ((p["xy"] - xy) ** 2).sum(-1)[mask].mean()
        else:
            z = (xy[..., None, :] - p["mu"]) / p["log_sigma"].exp()  # (B, T, K, 2)
            comp = -0.5 * (z**2).sum(-1) - p["log_sigma"].sum(-1) - math.log(2 * math.pi)
            ll = torch.logsumexp(F.log_softmax(p["logit"], -1) + comp, -1)  # (B, T)
            l_pos = -ll[mask].mean() / 10.0  # scaled so a few mm of error moves it like the other terms
        rot = F.normalize(p["rot"], dim=-1, eps=1e-6)
        ang = batch["y_rot"]
        l_rot = (1 - (rot[..., 0] * ang.sin() + rot[..., 1] * ang.cos()))[mask].mean()
        l_ptr = self.pointer_loss(batch, p)
        total = (cfg.w_type * l_type + cfg.w_object * l_obj + cfg.w_position * l_pos + cfg.w_rotation * l_rot
                 + cfg.w_pointer * l_ptr)
        return {"loss": total, "type": l_type, "object": l_obj, "position": l_pos, "rotation": l_rot,
                "pointer": l_ptr}

    def pointer_loss(self, batch: dict, p: dict) -> torch.Tensor:
        """Auxiliary: the position pointer should look, in every context arrangement, at the object that
        plays the part of the one being placed: of the same type, the one whose carried-over position is
        nearest the true position. Averaging those is what a careful person would do to denoise a habit.

        -log of the attention mass (mixture-weighted over components) on those tokens, averaged over the
        steps that have any; 0 when no step has (context length 0).
        """
        y_obj, mask, C = batch["y_obj"], batch["y_mask"], batch["ctx_obj"].shape[1]
        if C == 0:
            return p["att"].sum() * 0.0
        att = p["att"][..., :C]  # (B, T, K, C): attention on the context tokens
        w = p["logit"].softmax(-1) if "logit" in p else torch.ones_like(att[..., 0])  # (B, T, K)
        att = (att * w[..., None]).sum(2)  # (B, T, C)
        ctx, ctx_mask = batch["ctx_obj"][:, None, :], batch["ctx_mask"][:, None, :]
        kind = (self.codes[ctx, 0] == self.codes[y_obj, 0][..., None]) & ctx_mask  # (B, T, C)
        dist = (p["cand"][:, None, :C] - batch["y_xy"][:, :, None]).norm(dim=-1).masked_fill(~kind, float("inf"))
        slots = F.one_hot(batch["ctx_slot"].clamp(max=self.cfg.max_context - 1), self.cfg.max_context).bool()
        per_slot = dist[:, :, None, :].masked_fill(~slots.transpose(1, 2)[:, None], float("inf"))  # (B, T, S, C)
        best, idx = per_slot.min(-1)  # (B, T, S)
        idx = torch.where(torch.isfinite(best), idx, C)  # slots without that type point at a dummy column
        target = kind.new_zeros(*kind.shape[:-1], C + 1).scatter_(-1, idx, True)[..., :C]  # (B, T, C)
        has = target.any(-1) & mask  # (B, T)
        if not bool(has.any()):
            return att.sum() * 0.0
        mass = (att * target).sum(-1)[has]
        return -(mass + 1e-6).log().mean()
