"""The `optim:` section every trainer shares (learned, finetune, pretrain): AdamW and its schedule.

The schedules are transformers' (`get_cosine_with_min_lr_schedule_with_warmup`,
`get_constant_schedule_with_warmup`), the ones TRL and most fine-tuning recipes run: linear warmup from 0
over `warmup_steps` optimizer steps (capped at half the run), then cosine decay to `min_lr_ratio * lr` at
the last step, or constant.

Usage (in a LightningModule):
    def configure_optimizers(self):
        opt = torch.optim.AdamW(groups, lr=cfg.lr, betas=(0.9, cfg.beta2))
        return {"optimizer": opt, "lr_scheduler": lr_schedule(opt, cfg, self.trainer.estimated_stepping_batches)}
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

from degusta_learn.config import bounded, check_choices
from degusta_learn.errors import DegustaError


@dataclass
class OptimConfig:
    """The `optim:` section: AdamW, linear warmup, then cosine decay to `min_lr_ratio * lr` (or constant)."""

    lr: float = bounded(1e-3, 0.0, 100.0)
    """Peak learning rate (LoRA ~1e-4..5e-4; full fine-tuning ~1e-5..5e-5; small models from scratch ~1e-3)."""
    weight_decay: float = bounded(0.0, 0.0, 10.0)
    """AdamW weight decay."""
    warmup_steps: int = bounded(10, 0, 1_000_000_000)
    """Linear warmup optimizer steps (at most half the run)."""
    schedule: Literal["cosine", "constant"] = "cosine"
    """cosine (to min_lr_ratio * lr at the last step) or constant after warmup."""
    min_lr_ratio: float = bounded(0.05, 0.0, 1.0)
    """Final learning rate of the cosine schedule as a fraction of lr."""
    beta2: float = bounded(0.999, 0.0, 0.9999999)
    """AdamW's second-moment decay (torch's default 0.999; 0.95-0.98 is usual when training from scratch)."""

    def __post_init__(self):
        check_choices(self, 'optim')
        if self.lr <= 0:
            raise DegustaError(f"optim.lr: expected > 0, got {self.lr}")


def adamw_optimizers(model: torch.nn.Module, cfg: OptimConfig, total_steps: float) -> dict:
    """Lightning's `configure_optimizers` answer for a model trained from scratch: AdamW with weight decay on the
    matrices only (biases, LayerNorm and embedding weights are not decayed), and `lr_schedule` over `total_steps`."""
    decay, no_decay = [], []
    for mod in model.modules():
        for p in mod.parameters(recurse=False):
            plain = p.dim() < 2 or isinstance(mod, (torch.nn.Embedding, torch.nn.LayerNorm))
            (no_decay if plain else decay).append(p)
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": cfg.weight_decay},
                             {"params": no_decay, "weight_decay": 0.0}], lr=cfg.lr, betas=(0.9, cfg.beta2))
    return {"optimizer": opt, "lr_scheduler": lr_schedule(opt, cfg, total_steps)}


def lr_schedule(optimizer: torch.optim.Optimizer, cfg: OptimConfig, total_steps: float) -> dict:
    """Lightning's `lr_scheduler` entry (stepped every optimizer step) for `cfg` over `total_steps`."""
    from transformers import get_constant_schedule_with_warmup, get_cosine_with_min_lr_schedule_with_warmup

    total = max(1, int(total_steps)) if total_steps != float("inf") else 1_000_000
    warm = min(cfg.warmup_steps, total // 2)
    if cfg.schedule == "constant":
        sched = get_constant_schedule_with_warmup(optimizer, num_warmup_steps=warm)
    else:
        sched = get_cosine_with_min_lr_schedule_with_warmup(optimizer, num_warmup_steps=warm, num_training_steps=total,
                                                            min_lr_rate=cfg.min_lr_ratio)
    return {"scheduler": sched, "interval": "step"}


def warmup_factor(cfg: OptimConfig, step: int, total_steps: int) -> float:
    """The multiplier of `cfg.lr` at optimizer step `step` of `total_steps` under `lr_schedule` (the same linear
    warmup, then cosine to `min_lr_ratio` or constant), for a schedule that starts later than step 0, e.g. the
    decoder's after pretraining's vision stage (`pretrain/module.py`)."""
    total = max(1, int(total_steps))
    warm = min(cfg.warmup_steps, total // 2)
    if step < warm:
        return step / max(1, warm)
    if cfg.schedule == "constant":
        return 1.0
    progress = min(1.0, (step - warm) / max(1, total - warm))
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))
