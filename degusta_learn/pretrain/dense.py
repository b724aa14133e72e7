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

    @torch.no_grad()
    def readouts(self, tokens: torch.Tensor, examples, catalog) -> dict[str, float]:
        """`label_readouts` of this head's logits."""
        return label_readouts(self.proj(tokens).float(), examples, catalog)


@torch.no_grad()
def label_readouts(out: torch.Tensor, examples, catalog) -> dict[str, float]:
    """Top-1 accuracies of per-token label logits `out` (n_images, side^2, >= n_labels, in `DenseLabels`' order)
    on every labelled grid cell covered by exactly one object: its type, its id among the objects of that type
    ("id", chance 1/25 in the default catalog) and its direction. The rows of `out` are `examples`' images in
    order (unlabelled images, e.g. object sheets, are skipped). "cells" is how many cells were read."""
    types, ids = list(catalog.types), sorted(catalog.ids)
    nt, ni = len(types), len(ids)
    n_labels = nt + ni + len(DIRECTIONS)
    same = {t: [j for j, x in enumerate(ids) if catalog[x].type == t] for t in types}
    labels = [cells for ex in examples for cells in ex.meta.get("cell_labels", [])]
    right, n = {"type": 0, "id": 0, "direction": 0}, 0
    if len(labels) != out.shape[0]:
        return {k: float("nan") for k in right} | {"cells": 0}
    for cells, logits in zip(labels, out):
        for k, objects in enumerate(cells or []):
            if len(objects) != 1:
                continue
            oid, direction = objects[0]
            kind, n = catalog[oid].type, n + 1
            right["type"] += int(logits[k, :nt].argmax()) == types.index(kind)
            of_type = same[kind]
            right["id"] += ids[of_type[int(logits[k, nt:nt + ni][of_type].argmax())]] == oid
            right["direction"] += int(logits[k, nt + ni:n_labels].argmax()) == DIRECTIONS.index(direction)
    return {k: (v / n if n else float("nan")) for k, v in right.items()} | {"cells": n}


def projector_of(model):
    """The module whose output is the image tokens the decoder sees (FastVLM projector / Idefics3 connector)."""
    inner = getattr(model, "model", model)
    for name in ("multi_modal_projector", "connector"):
        if hasattr(inner, name):
            return getattr(inner, name)
    raise DegustaError("data.dense_weight: this model has no multi_modal_projector or connector to attach the "
                       "dense head to; set data.dense_weight: 0")


def single_token(tokenizer, text: str, key: str, what: str) -> int:
    """The one token id of `text`, or a one-line error naming `data.<key>` when the tokenizer splits it."""
    ids = tokenizer.encode(text, add_special_tokens=False)
    if len(ids) != 1:
        raise DegustaError(f"data.{key}: the tokenizer splits {text!r} into {len(ids)} tokens; {what} needs cells, "
                           f"types, ids and directions as single tokens (the domain tokenizer); set data.{key}: 0")
    return ids[0]


class OracleTokens:
    """Per image token, the token ids whose embeddings sum to a *perfect* image token (the oracle teacher).

    Token k of a labelled image stands for grid cell k (`DenseLabels`); its oracle is the sum of the input
    embeddings of that cell id and of the type, id and direction of every object covering it, e.g.
    E["D5"] + E["fork"] + E["48"] + E["S"]: exactly the tokens an answer copies from it. Early in pretraining
    the decoder sees these sums instead of the vision tower's tokens (`OracleTeacher`), so it learns to
    retrieve and copy before it must read the tower's; the tied readout (`TiedReadout`) trains the projector's
    tokens towards what these sums name. Runs in DataLoader workers.
    """

    def __init__(self, catalog, tokenizer, grid, key: str = "teacher_steps"):
        def one(text: str) -> int:
            return single_token(tokenizer, text, key, "the oracle teacher (and the tied readout)")

        self.cell = [one(c) for c in grid.cells]
        self.type = {o.id: one(o.type) for o in catalog}
        self.id = {o.id: one(str(o.id)) for o in catalog}
        self.dir = {d: one(d) for d in DIRECTIONS}

    def __call__(self, examples) -> torch.Tensor | None:
        """(n_labelled_images, cells, width) token ids, padded with -1; None when no image is labelled."""
        rows = []
        for ex in examples:
            for labels in ex.meta.get("cell_labels", []):
                if labels is None:
                    continue
                rows.append([[self.cell[k]] + [t for oid, d in objects for t in (self.type[oid], self.id[oid], self.dir[d])]
                             for k, objects in enumerate(labels)])
        if not rows:
            return None
        width = max(len(ids) for image in rows for ids in image)
        return torch.tensor([[ids + [-1] * (width - len(ids)) for ids in image] for image in rows])


class OracleTeacher:
    """Replaces the projector's image tokens by their oracle sums with a probability that falls to 0.

    `probability(step)` is 1 until step `hold`, then falls linearly to 0 over `steps` more; per labelled
    image a coin decides.
    """

    def __init__(self, embeddings: nn.Embedding, steps: int, hold: int = 0):
        self.embeddings, self.steps, self.hold = embeddings, steps, hold
        self.ids: torch.Tensor | None = None
        self.keep: torch.Tensor | None = None

    def probability(self, step: int) -> float:
        if self.steps <= 0:
            return 0.0
        return 1.0 if step < self.hold else max(0.0, 1.0 - (step - self.hold) / self.steps)

    def oracle(self) -> torch.Tensor:
        ids = self.ids.to(self.embeddings.weight.device)
        mask = (ids >= 0).unsqueeze(-1)
        return (self.embeddings(ids.clamp(min=0)) * mask).sum(dim=2)  # (n_labelled, cells, hidden)

    def replace(self, tokens: torch.Tensor, step: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """`tokens` (n_images, cells, hidden) with labelled images swapped for their oracle sums by coin flip."""
        p = self.probability(step)
        if p <= 0 or self.ids is None or self.keep is None or tokens.shape[0] != self.keep.numel() \
                or tokens.shape[1] != self.ids.shape[1]:
            return tokens
        keep = self.keep.to(tokens.device)
        swap = torch.zeros_like(keep)
        swap[keep] = torch.rand(int(keep.sum()), generator=generator).to(tokens.device) < p
        if not swap.any():
            return tokens
        out = tokens.clone()
        out[swap] = self.oracle()[swap[keep]].to(tokens.dtype)
        return out


class TiedReadout:
    """The image tokens read through the decoder's own output layer (tied to its input embeddings).

    The decoder names an object by copying an image token into its answer, whose logits are the output layer's
    dot products with it. Under the oracle teacher it learned to copy sums of embeddings (E["D5"] + E["fork"] +
    E["48"] + E["S"]); tokens that merely let a separate head tell ids apart were not read.
    `loss` is the cross-entropy of each labelled token's output-layer logits towards every token of
    its cell's oracle sum (`OracleTokens`), so the projector writes what the decoder's copy can name; the output
    layer is detached (the decoder owns it). `readouts` scores the same logits as `DenseHead.readouts` does its
    own (type, id within type, direction of single-object cells): what a perfect copy of the token would name.
    """

    def __init__(self, output: nn.Module, oracle: OracleTokens, catalog):
        self.output = output  # the model's output embeddings (a Linear whose weight is the input embeddings)
        by_type = {o.type: oracle.type[o.id] for o in catalog}
        self.label_tokens = torch.tensor([by_type[t] for t in catalog.types] + [oracle.id[i] for i in sorted(catalog.ids)]
                                         + [oracle.dir[d] for d in DIRECTIONS])

    def _logits(self, tokens: torch.Tensor) -> torch.Tensor:
        return tokens.float() @ self.output.weight.detach().float().T

    def loss(self, tokens: torch.Tensor | None, ids: torch.Tensor | None, keep: torch.Tensor | None) -> torch.Tensor | None:
        """Mean negative log-probability of the oracle tokens `ids` (n_labelled, cells, width; -1 padding) under
        the labelled images' `tokens` (n_images, cells, hidden) read through the output layer; None without labels."""
        if tokens is None or ids is None or keep is None or tokens.shape[0] != keep.numel() \
                or tokens.shape[1] != ids.shape[1]:
            return None
        logp = F.log_softmax(self._logits(tokens[keep.to(tokens.device)]), dim=-1)
        ids = ids.to(logp.device)
        mask = ids >= 0
        return -(logp.gather(-1, ids.clamp(min=0)) * mask).sum() / mask.sum().clamp(min=1)

    @torch.no_grad()
    def readouts(self, tokens: torch.Tensor, examples, catalog) -> dict[str, float]:
        return label_readouts(self._logits(tokens)[..., self.label_tokens.to(tokens.device)], examples, catalog)
