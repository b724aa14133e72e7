"""The fine-tuning loss: next-token cross-entropy on the supervised (answer) tokens only.

Labels come unshifted from the collator and are shifted here, once. The LM head runs only on the
positions that are supervised (hidden states are gathered first), so a 2k-token prompt with a 49k or
150k vocabulary never materialises (B, T, V) logits. A batch with no supervised token gives a zero loss
that still touches the graph (no NaN, and DDP sees every parameter used).

Example:
    loss, n_tokens = lm_loss(model, batch)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from degusta_learn.finetune.collate import IGNORE


def unwrap(model):
    """The transformers model inside a PeftModel (or the model itself)."""
    get_base = getattr(model, "get_base_model", None)
    return get_base() if callable(get_base) else model


def lm_loss(model, batch: dict) -> tuple[torch.Tensor, int]:
    """(mean cross-entropy over supervised tokens, number of supervised tokens); weighted by the batch's
    `label_weights` where it has them (`Collator(list_end_weight=...)`): sum(w * ce) / sum(w)."""
    inputs = {k: v for k, v in batch.items() if k not in ("labels", "label_weights")}
    labels = batch["labels"]
    weights = batch.get("label_weights")
    hf = unwrap(model)
    inner, head = getattr(hf, "model", None), hf.get_output_embeddings()
    target = labels[:, 1:]  # (B, T-1): token t+1 is predicted at position t
    sel = target != IGNORE
    n = int(sel.sum())
    if inner is None or head is None:  # generic fallback: full logits
        logits = model(**inputs).logits[:, :-1]  # (B, T-1, V)
        if n == 0:
            return logits.sum() * 0.0, 0
        return _mean_ce(logits[sel].float(), target[sel], weights, sel), n
    hidden = inner(**inputs, use_cache=False).last_hidden_state[:, :-1]  # (B, T-1, H)
    if n == 0:
        return hidden.sum() * 0.0, 0
    logits = head(hidden[sel])  # (N, V)
    return _mean_ce(logits.float(), target[sel], weights, sel), n


def _mean_ce(logits: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None, sel: torch.Tensor):
    """Cross-entropy of the selected positions, plain or weighted by `weights` (B, T; unshifted like labels)."""
    if weights is None:
        return F.cross_entropy(logits, target)
    w = weights[:, 1:].to(logits.device)[sel].float()
    return (F.cross_entropy(logits, target, reduction="none") * w).sum() / w.sum().clamp_min(1e-12)
