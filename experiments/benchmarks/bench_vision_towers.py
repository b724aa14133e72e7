"""Which vision tower learns to see lifted scenes from random weights on a CPU: a ViT (Idefics3) or a CNN (FastVLM)?

Trains only the vision tower + its projector + a linear probe on the dense targets of the pretraining
(`finetune/pretrain/dense.py`: which object types and ids cover each image token), from random weights,
on the same freshly rendered single-scene GMA images, for the same number of steps and batch size, and
prints the probe's type and id losses (summed binary cross-entropies per token) against the loss of
predicting each label's base rate everywhere. The towers have the sizes the tiny base would use:

- Idefics3 (SmolVLM's architecture): SigLIP-style ViT, width 128, 4 layers, 160 px images, 10 px
  patches, pixel shuffle 2 -> 8 x 8 tokens;
- FastVLM: timm ResNet (stages 32-64-128-256, blocks 1-1-2-1), 256 px images, output stride 32 ->
  8 x 8 tokens (the shipped base's tower).

Usage:
    python benchmarks/bench_vision_towers.py              # 600 steps of 16 images per tower, ~12 CPU minutes
    python benchmarks/bench_vision_towers.py --steps 100  # a quick look
"""

from __future__ import annotations

import argparse
import os
import time

os.environ["HF_HUB_OFFLINE"] = "1"


def tower(kind: str):
    """(image_size, function images -> image tokens (n, 64, hidden), trainable parameters, hidden)."""
    import torch

    if kind == "fastvlm":
        from degusta_learn.finetune.pretrain.base import BaseArchitecture, build_base

        model, _ = build_base(BaseArchitecture())
        inner = model.model

        def encode(x):
            return inner.get_image_features(pixel_values=x).pooler_output

        params = list(inner.vision_tower.parameters()) + list(inner.multi_modal_projector.parameters())
        return 256, encode, params, model.config.text_config.hidden_size
    from transformers import PreTrainedTokenizerFast

    from degusta_learn.vlm.tiny import IDEFICS3_ROLES, IDEFICS3_SPECIAL, _wrap, idefics3, train_tokenizer

    tok = _wrap(train_tokenizer(IDEFICS3_SPECIAL), PreTrainedTokenizerFast, IDEFICS3_SPECIAL, **IDEFICS3_ROLES)
    model, _ = idefics3(tok, 160, 10, 2, vision=dict(hidden_size=128, intermediate_size=512, num_hidden_layers=4,
                                                     num_attention_heads=4),
                        text=dict(hidden_size=256, intermediate_size=768, num_hidden_layers=1, num_attention_heads=4,
                                  num_key_value_heads=2))
    inner = model.model

    def encode(x):
        mask = torch.ones(x.shape[0], 16, 16, dtype=torch.bool)
        return inner.connector(inner.vision_model(pixel_values=x, patch_attention_mask=mask).last_hidden_state)

    params = list(inner.vision_model.parameters()) + list(inner.connector.parameters())
    return 160, encode, params, 256


def run(kind: str, steps: int, batch: int, seed: int = 0) -> list[tuple[int, float, float, float, float]]:
    import numpy as np
    import torch
    import torch.nn.functional as F

    from degusta_learn.finetune.pretrain.dense import DenseLabels
    from degusta_learn.finetune.pretrain.tasks import PerceptionExamples, TaskMix
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import default_catalog, default_tables

    torch.manual_seed(seed)
    size, encode, params, hidden = tower(kind)
    catalog = default_catalog()
    mix = TaskMix(lists=1, describe=0, gomo=0, scenes=[1, 0, 0, 0], objects_sheet=0, empty_table=0)
    data = PerceptionExamples(catalog, {t.id: t for t in default_tables()}, Grid(8, 8), size, seed, 10**7, mix)
    labels = DenseLabels(catalog, 8)
    probe = torch.nn.Linear(hidden, labels.n_labels)
    opt = torch.optim.AdamW(params + list(probe.parameters()), lr=1e-3)
    out, window, t0 = [], [], time.time()
    for step in range(steps):
        exs = [data[step * batch + j] for j in range(batch)]
        x = torch.stack([torch.from_numpy(np.array(e.prompt.images[0].image.convert("RGB"))).permute(2, 0, 1)
                         for e in exs]).float() / 127.5 - 1
        target, _ = labels(exs)  # (B, 64, n_labels): types, then ids, then directions
        logits = probe(encode(x))
        parts = [F.binary_cross_entropy_with_logits(logits[..., a:b], target[..., a:b], reduction="sum") / (batch * 64)
                 for a, b in ((0, 5), (5, 130))]
        (parts[0] + parts[1]).backward()
        opt.step()
        opt.zero_grad()
        rate = target.mean((0, 1))  # (n_labels,) the base rates: what a probe that cannot see predicts
        prior = [float(-(r * torch.log(r.clamp(1e-9)) + (1 - r) * torch.log((1 - r).clamp(1e-9))).sum())
                 for r in (rate[:5], rate[5:130])]
        window.append([p.item() for p in parts] + prior)
        if (step + 1) % max(1, steps // 6) == 0:
            w = np.mean(window, 0)
            out.append((step + 1, *w))
            print(f"{kind:8s} step {step + 1:4d} ({time.time() - t0:4.0f} s): type {w[0]:.3f} (base rate {w[2]:.3f}), "
                  f"id {w[1]:.3f} (base rate {w[3]:.3f})", flush=True)
            window = []
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    results = {kind: run(kind, args.steps, args.batch) for kind in ("idefics3", "fastvlm")}
    print("\n| tower | images seen | type loss / base rate | id loss / base rate |")
    print("|---|---:|---:|---:|")
    for kind, rows in results.items():
        for step, t, i, tp, ip in rows[1::2] if len(rows) > 2 else rows:
            print(f"| {kind} | {step * args.batch} | {t / tp:.2f} | {i / ip:.2f} |")
    last = {k: v[-1] for k, v in results.items()}
    ratio = (last["fastvlm"][1] / last["fastvlm"][3]) / (last["idefics3"][1] / last["idefics3"][3])
    print(f"\nafter {args.steps * args.batch} images the CNN's type loss, relative to the base rate, is {ratio:.2f}x "
          "the ViT's (lower is better)")


if __name__ == "__main__":
    main()
