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
    """(mean cross-entropy over supervised tokens, number of supervised tokens)."""
    inputs = {k: v for k, v in batch.items() if k != "labels"}
    labels = batch["labels"]
    hf = unwrap(model)
    inner, head = getattr(hf, "model", None), hf.get_output_embeddings()
    target = labels[:, 1:]  # (B, T-1): token t+1 is predicted at position t
    sel = target != IGNORE
    n = int(sel.sum())
    if inner is None or head is None:  # generic fallback: full logits
        logits = model(**inputs).logits[:, :-1]  # (B, T-1, V)
        if n == 0:
            return logits.sum() * 0.0, 0
        return F.cross_entropy(logits[sel].float(), target[sel]), n
    hidden = inner(**inputs, use_cache=False).last_hidden_state[:, :-1]  # (B, T-1, H)
    if n == 0:
        return hidden.sum() * 0.0, 0
    logits = head(hidden[sel])  # (N, V)
    return F.cross_entropy(logits.float(), target[sel]), n
