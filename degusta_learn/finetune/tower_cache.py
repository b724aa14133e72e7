"""A frozen vision tower's features, computed once per distinct image.

Fine-tuning on the preference task shows the same pictures again and again: every MOGMA prompt carries the
same composed object sheet, the target table of a GMA prompt is one of a few empty tables, and a person's
context arrangements come back in many episodes. When LoRA leaves the vision tower frozen (no trainable
weight, BatchNorms in eval mode, no active dropout), its output for a picture never changes, so
`cache_frozen_tower` makes the tower look each picture up by the bytes of its pixel values and run only on
the pictures it has not seen (measured on the tiny base's CPU fine-tuning: benchmarks/RESULTS.md).

The cache is off, and the tower runs as before, whenever any of this does not hold at the time of a call:
a trainable tower weight (full fine-tuning, `lora.vision_targets`), a tower module in training mode that
behaves differently there (BatchNorm, dropout with p > 0), gradients asked of the pixels, or tensor
arguments besides the pixels (e.g. Idefics3's patch masks). Only `last_hidden_state` is kept, which is what
the image-feature paths of FastVLM, LLaVA-style and Idefics3 models read.

Example:
    cache = cache_frozen_tower(model)      # None when the model has no vision tower to cache
    ...train...
    cache.hits, cache.misses
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import torch
from torch import nn

TOWER_NAMES = ("vision_tower", "vision_model")
_STATEFUL = (nn.modules.batchnorm._BatchNorm, nn.Dropout)


def find_tower(model: nn.Module) -> nn.Module | None:
    """The vision tower of a transformers VLM (optionally PEFT-wrapped), or None."""
    for name, module in model.named_modules():
        if name.rsplit(".", 1)[-1] in TOWER_NAMES:
            return module
    return None


def tower_is_frozen(tower: nn.Module) -> bool:
    """Whether the tower's output depends on nothing but its input: no trainable weight, and no module that
    behaves differently in training mode (BatchNorm, dropout with p > 0) left in it."""
    if any(p.requires_grad for p in tower.parameters()):
        return False
    return not any(m.training and (not isinstance(m, nn.Dropout) or m.p > 0)
                   for m in tower.modules() if isinstance(m, _STATEFUL))


MAX_BYTES = 1 << 30
"""Default size of the cache: 1 GiB of features (the tiny base's are 64 kB a picture; a CLIP ViT-L's ~1 MB in
bfloat16, on its GPU). Beyond it the least recently used pictures go (and are computed again if they come back)."""


class TowerCache:
    """Per-image `last_hidden_state` of a frozen tower, keyed by its pixel values' bytes (LRU, `max_bytes`)."""

    def __init__(self, tower: nn.Module, max_bytes: int = MAX_BYTES):
        self.tower, self.max_bytes, self.bytes = tower, max_bytes, 0
        self.forward = tower.forward  # the tower's own bound forward, called for the pictures not yet seen
        self.features: OrderedDict[bytes, torch.Tensor] = OrderedDict()
        self.output_cls = None  # the tower's output type, seen at its first call
        self.hits = self.misses = 0

    def usable(self, pixel_values, kwargs: dict) -> bool:
        return (isinstance(pixel_values, torch.Tensor) and pixel_values.dim() >= 2 and not pixel_values.requires_grad
                and not any(isinstance(v, torch.Tensor) for v in kwargs.values()) and tower_is_frozen(self.tower))

    @staticmethod
    def key(image: torch.Tensor, context: str = "") -> bytes:
        """The picture's identity: its values' bytes, shape and dtype, and `context` (device, autocast)."""
        t = image.detach().contiguous().cpu()
        h = hashlib.blake2b(t.reshape(-1).view(torch.uint8).numpy().tobytes(), digest_size=16)
        h.update(f"{tuple(t.shape)} {t.dtype} {context}".encode())
        return h.digest()

    def __call__(self, pixel_values=None, *args, **kwargs):
        if args or not self.usable(pixel_values, kwargs):
            return self.forward(pixel_values, *args, **kwargs)
        device = pixel_values.device.type  # features computed under another autocast are other numbers
        context = f"{device} {torch.is_autocast_enabled(device)} {torch.get_autocast_dtype(device)}"
        keys = [self.key(img, context) for img in pixel_values]
        first_row: dict[bytes, int] = {}  # the distinct pictures, in order, with the first row of each
        for row, k in enumerate(keys):
            first_row.setdefault(k, row)
        found = {k: self.features[k] for k in first_row if k in self.features}
        missing = [k for k in first_row if k not in found]
        if missing:
            with torch.no_grad():
                out = self.forward(pixel_values[[first_row[k] for k in missing]], **kwargs)
            self.output_cls = type(out) if hasattr(out, "last_hidden_state") else tuple
            hidden = out.last_hidden_state if self.output_cls is not tuple else out[0]
            found.update((k, h.detach().clone()) for k, h in zip(missing, hidden))
        for k in missing:
            self.features[k] = found[k]
            self.bytes += found[k].nelement() * found[k].element_size()
        for k in found:  # this call's pictures become the most recent; the least recent go beyond max_bytes
            self.features.move_to_end(k)
        while self.bytes > self.max_bytes and self.features:
            old = self.features.popitem(last=False)[1]
            self.bytes -= old.nelement() * old.element_size()
        self.misses += len(missing)
        self.hits += len(keys) - len(missing)
        stacked = torch.stack([found[k] for k in keys])
        # the output type the caller expects, with only the features it reads
        return (stacked,) if self.output_cls is tuple else self.output_cls(last_hidden_state=stacked)


def cache_frozen_tower(model: nn.Module, max_bytes: int = MAX_BYTES) -> TowerCache | None:
    """Route the model's vision tower through a `TowerCache` (used at each call only while the tower is frozen);
    returns it, or None for a model without a vision tower."""
    tower = find_tower(model)
    if tower is None:
        return None
    cache = TowerCache(tower, max_bytes)
    tower.forward = cache
    return cache
