"""A dense auxiliary loss on the image tokens: teach the vision tower directly, not only through the decoder.

The answer loss reaches the vision tower only through the decoder's attention, which at first looks
nowhere in particular, so a vision tower trained from random weights gets a weak signal. During
pretraining a linear head on the projector's output (the tokens the decoder sees) is trained on each
image token's own targets (`tasks.PerceptionExamples.cell_labels`: with 8 x 8 image tokens over an 8 x 8
grid, token k stands for grid cell k):

- which object types, which object ids and which directions cover the token's region (multi-label);
- the token's row and column (so every image token carries where it is: a convolutional tower has no
  position embedding, and the decoder must name grid cells).

Images without labels (the composed object sheets, mark sheets) are left out. The head is not part of
the model: it is dropped when the base is exported.

Example:
    labels = DenseLabels(catalog, side=8)
    targets, keep = labels(examples)                 # (n_labelled_images, 64, C), (n_images,) bool
    loss = DenseHead(256, labels.n_labels, 8).loss(projected_tokens, targets, keep)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from degusta_learn.errors import DegustaError
from degusta_learn.render.grid import DIRECTIONS


class DenseLabels:
    """Builds the dense targets of a batch of perception examples (runs in DataLoader workers)."""

    def __init__(self, catalog, side: int):
        self.side = side
        types, ids = list(catalog.types), sorted(catalog.ids)
        self._type = {o.id: types.index(o.type) for o in catalog}
        self._id = {o: len(types) + i for i, o in enumerate(ids)}
        self._dir = {d: len(types) + len(ids) + i for i, d in enumerate(DIRECTIONS)}
        self.n_labels = len(types) + len(ids) + len(DIRECTIONS)

    def __call__(self, examples) -> tuple[torch.Tensor | None, torch.Tensor]:
        """Multi-hot targets (n_labelled, side^2, n_labels) and which of all images are labelled (n_images,)."""
        rows, keep = [], []
        for ex in examples:
            for labels in ex.meta.get("cell_labels", []):
                keep.append(labels is not None)
                if labels is None:
                    continue
                t = torch.zeros(len(labels), self.n_labels)
                for k, objects in enumerate(labels):
                    for oid, direction in objects:
                        t[k, self._type[oid]] = t[k, self._id[oid]] = t[k, self._dir[direction]] = 1.0
                rows.append(t)
        return (torch.stack(rows) if rows else None), torch.tensor(keep, dtype=torch.bool)


class DenseHead(nn.Module):
    """Per image token: labels present (multi-label BCE) and the token's row and column (cross-entropy)."""

    def __init__(self, hidden: int, n_labels: int, side: int):
        super().__init__()
        self.n_labels, self.side = n_labels, side
        self.proj = nn.Linear(hidden, n_labels + 2 * side)

    def loss(self, tokens: torch.Tensor | None, targets: torch.Tensor | None, keep: torch.Tensor) -> torch.Tensor:
        """tokens (n_images, side^2, hidden) -> summed BCE per token + row and column cross-entropy."""
        if tokens is None or targets is None or tokens.shape[0] != keep.numel() or tokens.shape[1] != targets.shape[1]:
            return self.proj.weight.sum() * 0.0  # nothing labelled, or images the tower dropped: no signal
        out = self.proj(tokens[keep.to(tokens.device)]).float()  # (n, side^2, n_labels + 2 side)
        n, t = targets.shape[:2]
        targets = targets.to(out.device)
        bce = F.binary_cross_entropy_with_logits(out[..., :self.n_labels], targets, reduction="sum") / (n * t)
        pos = torch.arange(t, device=out.device)
        row, col = (pos // self.side).repeat(n), (pos % self.side).repeat(n)
        where = out[..., self.n_labels:].reshape(n * t, 2, self.side)
        return bce + F.cross_entropy(where[:, 0], row) + F.cross_entropy(where[:, 1], col)


def projector_of(model):
    """The module whose output is the image tokens the decoder sees (FastVLM projector / Idefics3 connector)."""
    inner = getattr(model, "model", model)
    for name in ("multi_modal_projector", "connector"):
        if hasattr(inner, name):
            return getattr(inner, name)
    raise DegustaError("data.dense_weight: this model has no multi_modal_projector or connector to attach the "
                       "dense head to; set data.dense_weight: 0")
