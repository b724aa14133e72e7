"""Can the tiny base's vision tower tell a type's objects apart? Top-1 readouts of its tokens, trained alone.

The scenes draw no id marks: which of a type's ~25 objects covers a cell is only its colour and pattern at
256 px. This trains the base's tower (timm ResNet, output stride 32: 8 x 8 tokens), its projector and the
dense head of the pretraining (`finetune/pretrain/dense.py`) on the dense loss alone (no decoder), on fresh
single-scene images, and every `--eval-every` steps reads, on the single-object cells of held-out scenes
(another seed), the head's top-1 type, id among the objects of the true type, and direction
(`DenseHead.readouts`, also logged as val/tower_* by every pretraining run). Chance: type 0.2, id within its
type 0.04. Compare with the same readout of a full pretraining run's tower
(docs/tiny_base.md, points 14-15), whose dense loss has weight `data.dense_weight`.

Usage:
    python benchmarks/bench_tower_ids.py                       # 3000 steps of 16 images, ~21 CPU minutes
    python benchmarks/bench_tower_ids.py --steps 500 --eval-every 250
    python benchmarks/bench_tower_ids.py --run RUN --checkpoint RUN/last.ckpt --held-out 64
        # no training: the same readout of a pretraining run's own tower and dense head
"""

from __future__ import annotations

import argparse
import os
import time

os.environ["HF_HUB_OFFLINE"] = "1"

CHANCE = {"type": 0.2, "id_within_type": 1 / 25}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--held-out", type=int, default=24, help="held-out scenes read at every evaluation")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--run", default=None, help="a pretraining run folder (init/): read its tower, train nothing")
    ap.add_argument("--checkpoint", default=None, help="with --run: the checkpoint to read (default RUN/last.ckpt)")
    args = ap.parse_args()

    import torch

    from degusta_learn.finetune.pretrain.base import BaseArchitecture, build_base
    from degusta_learn.finetune.pretrain.dense import DenseHead, DenseLabels
    from degusta_learn.finetune.pretrain.tasks import PerceptionExamples, TaskMix
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import default_catalog, default_tables
    from degusta_learn.trainer import cpu_has_native_bf16

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    model, processor = build_base(BaseArchitecture())
    inner = model.model
    labels = DenseLabels(catalog, 8)
    head = DenseHead(model.config.get_text_config().hidden_size, labels.n_labels, 8)  # the projector's width
    params = [*inner.vision_tower.parameters(), *inner.multi_modal_projector.parameters(), *head.parameters()]
    opt = torch.optim.AdamW(params, lr=args.lr, weight_decay=0.01, betas=(0.9, 0.98))
    scenes = TaskMix(lists=0, describe=1, gomo=0, locate=0)
    train = PerceptionExamples(catalog, tables, Grid(8, 8), 256, 0, (args.steps + 1) * args.batch, scenes, 1)
    held = [PerceptionExamples(catalog, tables, Grid(8, 8), 256, 2_000_077, args.held_out, scenes, 1)[i]
            for i in range(args.held_out)]

    if args.run:  # the run's own weights and dense head instead of a fresh tower
        from pathlib import Path

        from degusta_learn.vlm.load import load_vlm

        model, processor = load_vlm(str(Path(args.run) / "init"), device="cpu", dtype="float32", key="run")
        state = torch.load(args.checkpoint or Path(args.run) / "last.ckpt", map_location="cpu",
                           weights_only=True)
        model.load_state_dict({k[6:]: v for k, v in state["state_dict"].items() if k.startswith("model.")})
        head.load_state_dict({k[6:]: v for k, v in state["state_dict"].items() if k.startswith("dense.")})
        inner = model.model

    def tokens(examples):
        images = [getattr(e.prompt.images[0], "image", e.prompt.images[0]) for e in examples]
        pixels = processor.image_processor(images=images, return_tensors="pt")["pixel_values"]
        return inner.get_image_features(pixel_values=pixels).pooler_output

    if args.run:
        with torch.no_grad():
            r = head.readouts(tokens(held), held, catalog)
        print(f"{args.checkpoint or args.run} (step {state['global_step']}): type {r['type']:.3f}, "
              f"id within type {r['id']:.3f}, direction {r['direction']:.3f} ({r['cells']} cells)")
        return
    rows, t0 = [], time.time()
    bf16 = cpu_has_native_bf16()  # emulated bfloat16 (AVX2 CPUs) is ~60x slower than float32
    print(f"tower + projector + dense head, {sum(p.numel() for p in params):,} parameters, batch {args.batch}, "
          f"{'bf16 autocast' if bf16 else 'float32 (no native bfloat16 on this CPU)'}")
    for step in range(1, args.steps + 1):
        for group in opt.param_groups:
            group["lr"] = args.lr * min(1.0, step / 100)
        batch = [train[(step - 1) * args.batch + j] for j in range(args.batch)]
        targets, keep = labels(batch)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss = head.loss(tokens(batch), targets, keep)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        opt.zero_grad()
        if step % args.eval_every == 0 or step == args.steps:
            with torch.no_grad():
                r = head.readouts(tokens(held), held, catalog)
            rows.append((step, r))
            print(f"step {step:5d} ({time.time() - t0:5.0f} s, {step * args.batch} images): dense loss "
                  f"{loss.item():.3f}, type {r['type']:.3f}, id within type {r['id']:.3f}, direction "
                  f"{r['direction']:.3f} ({r['cells']} cells)", flush=True)
    print("\n| images seen | type | id within its type | direction |")
    print("|---:|---:|---:|---:|")
    for step, r in rows:
        print(f"| {step * args.batch} | {r['type']:.3f} | {r['id']:.3f} | {r['direction']:.3f} |")
    print(f"| chance | {CHANCE['type']:.3f} | {CHANCE['id_within_type']:.3f} | - |")


if __name__ == "__main__":
    main()
