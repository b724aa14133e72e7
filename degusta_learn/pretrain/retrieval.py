"""Attention supervision of retrieval: teach one decoder head where an answer's cells are.

An answer item copies its cells and direction from the image: `{'type': 'cup', 'id': 18, 'position':
['E5', ...], 'cardinal_direction': 'S'}` is right only if, at each cell and at the direction, the decoder
reads the image tokens of object 18. A decoder from scratch finds that circuit (match the id against the
image tokens, copy what is there) late and at a seed-dependent step: on the same data, 0.14 first-cell
accuracy at step 450 from the pipeline's initial weights against 0.64 from another draw.
The labels say exactly where to look, so one head is told:

- `RetrievalTargets` (collate side, in DataLoader workers): for every supervised answer position whose next
  token is a grid cell or a direction, the positions of the image tokens (of the image the question asks
  about) whose grid cell the object named by the latest supervised id covers. Image token k of a labelled
  image stands for grid cell k (`tasks.PerceptionExamples.cell_labels`), as for the dense loss.
- `RetrievalLoss` (module side): a forward pre-hook captures the input of decoder layer `layer`'s attention;
  `loss()` recomputes head `head`'s causal attention scores (RoPE included) at those positions and returns
  the mean of -log(attention mass on the target tokens).

The loss only shapes where the head looks; what it copies and how the answer uses it is learned by the
answer loss as before. It runs in training only and adds no weights (nothing to drop at export).

Example:
    targets = RetrievalTargets(catalog, tokenizer, image_token_id, tokens_per_image=64)
    batch.update(targets(examples, batch["input_ids"], batch["labels"]))    # in the collator
    sup = RetrievalLoss(model, layer=1, head=2)                            # hooks the attention
    loss = lm_loss(model, batch) + w * sup.loss(rows, queries, targets)    # after the forward
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from degusta_learn.errors import DegustaError

KEYS = ("retrieval_rows", "retrieval_queries", "retrieval_targets")


class RetrievalTargets:
    """Builds the attention targets of a collated batch (see the module docstring)."""

    def __init__(self, catalog, tokenizer, image_token_id: int, tokens_per_image: int, grid):
        from degusta_learn.pretrain.dense import single_token
        from degusta_learn.render.grid import DIRECTIONS

        def one(text: str) -> int:
            return single_token(tokenizer, text, "retrieval_weight", "attention supervision")

        self.object_of = {one(str(o.id)): o.id for o in catalog}
        self.copied = {one(c) for c in grid.cells} | {one(d) for d in DIRECTIONS}
        self.image_token_id, self.tokens_per_image = image_token_id, tokens_per_image

    def __call__(self, examples, input_ids: torch.Tensor, labels: torch.Tensor) -> dict:
        """{"retrieval_rows": (n,), "retrieval_queries": (n,), "retrieval_targets": (n, T) bool}: query n is
        position queries[n] of batch row rows[n]; targets[n] marks the image tokens it should attend to."""
        rows, queries, targets = [], [], []
        width = input_ids.shape[1]
        for b, ex in enumerate(examples):
            cells = self._object_positions(ex, input_ids[b])
            if cells is None:
                continue
            lab = labels[b].tolist()
            current = None
            for t in range(width - 1):
                if lab[t] in self.object_of:  # a supervised id: the answer item's object
                    current = self.object_of[lab[t]]
                if lab[t + 1] in self.copied and current in cells:
                    row = torch.zeros(width, dtype=torch.bool)
                    row[cells[current]] = True
                    rows.append(b)
                    queries.append(t)
                    targets.append(row)
        if not rows:
            return {"retrieval_rows": torch.zeros(0, dtype=torch.long),
                    "retrieval_queries": torch.zeros(0, dtype=torch.long),
                    "retrieval_targets": torch.zeros(0, width, dtype=torch.bool)}
        return {"retrieval_rows": torch.tensor(rows), "retrieval_queries": torch.tensor(queries),
                "retrieval_targets": torch.stack(targets)}

    def _object_positions(self, ex, input_ids: torch.Tensor) -> dict[int, list[int]] | None:
        """Object id -> sequence positions of the image tokens it covers in the asked image; None when the
        example has no asked labelled image or its image tokens are not one per grid cell per image."""
        labels = ex.meta.get("cell_labels", [])
        asked = ex.meta.get("asked_image")
        if asked is None or not 0 <= asked < len(labels) or labels[asked] is None:
            return None
        where = (input_ids == self.image_token_id).nonzero().flatten().tolist()
        n = self.tokens_per_image
        if len(where) != n * len(labels) or len(labels[asked]) != n:
            return None
        first = asked * n
        out: dict[int, list[int]] = {}
        for k, objects in enumerate(labels[asked]):
            for oid, _ in objects:
                out.setdefault(oid, []).append(where[first + k])
        return out


class RetrievalLoss:
    """-log of one attention head's mass on the retrieval targets (see the module docstring)."""

    def __init__(self, model, layer: int, head: int):
        decoder = model.get_decoder()
        layers = getattr(decoder, "layers", None)
        text = model.config.get_text_config()
        if layers is None or not 0 <= layer < len(layers):
            raise DegustaError(f"data.retrieval_layer: {layer} is not a decoder layer of this model "
                               f"(0 .. {len(layers or []) - 1})")
        if not 0 <= head < text.num_attention_heads:
            raise DegustaError(f"data.retrieval_head: {head} is not an attention head of this model "
                               f"(0 .. {text.num_attention_heads - 1})")
        self.attn, self.head = layers[layer].self_attn, head
        self.group = head // (text.num_attention_heads // text.num_key_value_heads)
        self._inputs = None
        self.attn.register_forward_pre_hook(self._capture, with_kwargs=True)

    def _capture(self, module, args, kwargs):
        hidden = kwargs.get("hidden_states", args[0] if args else None)
        self._inputs = (hidden, kwargs.get("position_embeddings"))

    def loss(self, rows: torch.Tensor, queries: torch.Tensor, targets: torch.Tensor) -> torch.Tensor | None:
        """Mean -log(attention mass on the targets) over the queries of the last forward; None without any."""
        from transformers.models.llama.modeling_llama import apply_rotary_pos_emb

        inputs, self._inputs = self._inputs, None
        if inputs is None or inputs[1] is None or rows.numel() == 0:
            return None
        hidden, (cos, sin) = inputs
        attn, d = self.attn, self.attn.head_dim
        q_rows, k_rows = slice(self.head * d, (self.head + 1) * d), slice(self.group * d, (self.group + 1) * d)
        bias = lambda proj, r: None if proj.bias is None else proj.bias[r]  # noqa: E731
        q = F.linear(hidden, attn.q_proj.weight[q_rows], bias(attn.q_proj, q_rows))  # (B, T, d)
        k = F.linear(hidden, attn.k_proj.weight[k_rows], bias(attn.k_proj, k_rows))
        q, k = apply_rotary_pos_emb(q.unsqueeze(1), k.unsqueeze(1), cos, sin)
        rows, queries = rows.to(hidden.device), queries.to(hidden.device)
        q = q[:, 0][rows, queries]  # (n, d)
        scores = torch.einsum("nd,ntd->nt", q.float(), k[:, 0][rows].float()) * attn.scaling  # (n, T)
        width = scores.shape[1]
        future = torch.arange(width, device=scores.device)[None, :] > queries[:, None]
        scores = scores.masked_fill(future, float("-inf"))
        hit = targets.to(scores.device)[:, :width] & ~future
        keep = hit.any(dim=1)  # a target after its query (never for an answer) would give -inf
        if not keep.any():
            return None
        scores, hit = scores[keep], hit[keep]
        return (torch.logsumexp(scores, 1) - torch.logsumexp(scores.masked_fill(~hit, float("-inf")), 1)).mean()
