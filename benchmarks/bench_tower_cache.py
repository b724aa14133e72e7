"""How much the frozen-tower cache (`model.cache_tower`) saves a LoRA fine-tuning step of the tiny base, in one run.

The same training batches of `configs/finetune_tiny_base_cpu.yaml` (MOGMA, context 4, batch 8: 48 pictures a
step) go through forward + backward + AdamW twice, alternating per batch: with the vision tower run on
every picture, and through the cache (`finetune.tower_cache`). Each batch is first passed once through the
cache, so the cached timing is the steady state; the hit rate of one real epoch is counted separately by
walking the epoch's pictures through the cache without training. Prints the mean step times, their ratio, the
largest difference of the losses (the cache must not change a number) and the hit rate.

Usage:
    python benchmarks/bench_tower_cache.py                  # ~3 CPU minutes
    python benchmarks/bench_tower_cache.py --batches 6 --epoch-steps 20
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--base", default="tiny_vlm_base")
    ap.add_argument("--batches", type=int, default=10, help="timed batches per mode")
    ap.add_argument("--epoch-steps", type=int, default=None, help="batches of the hit-rate walk (default: an epoch)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)

    import torch

    from degusta_learn.config import load_config
    from degusta_learn.finetune import train as T
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.loss import lm_loss
    from degusta_learn.finetune.module import freeze_batch_norms
    from degusta_learn.finetune.tower_cache import TowerCache, cache_frozen_tower
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.synth import generate_dataset
    from degusta_learn.vlm.generate import chat_format

    torch.set_num_threads(args.threads)
    if not (Path(args.dataset) / "arrangements.jsonl").is_file():
        generate_dataset("naturalistic", args.dataset, seed=0)
    cfg = load_config(FinetuneConfig, "configs/finetune_tiny_base_cpu.yaml",
                      [f"dataset={args.dataset}", f"model.name={args.base}"])
    ds = load_dataset(cfg.dataset)
    model, processor = T.prepare_model(cfg)
    collator = Collator(processor, chat_format(model, processor), cfg.data.max_length,
                        getattr(model.config, "image_token_id", None))
    train, _ = T.build_examples(cfg, ds, Grid(cfg.data.grid.rows, cfg.data.grid.cols))
    size = cfg.data.batch_size
    batches = [collator([train[s * size + j] for j in range(size)]) for s in range(args.batches + 1)]
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=0.0)  # lr 0: same weights
    model.train()
    freeze_batch_norms(model)
    cache = cache_frozen_tower(model)
    if cache is None:
        raise SystemExit(f"{args.base}: no vision tower to cache")

    def step(batch) -> tuple[float, float]:
        t0 = time.perf_counter()
        loss, _ = lm_loss(model, batch)
        loss.backward()
        opt.step()
        opt.zero_grad()
        return time.perf_counter() - t0, loss.item()

    def uncached(batch):
        tower_forward, cache.tower.forward = cache.tower.forward, cache.forward
        try:
            return step(batch)
        finally:
            cache.tower.forward = tower_forward

    step(batches[0])  # warm-up (allocations, the first call's overheads)
    plain, cached, worst = [], [], 0.0
    for batch in batches[1:]:
        t_plain, loss_plain = uncached(batch)
        with torch.no_grad():
            model.get_image_features(pixel_values=batch["pixel_values"])  # into the cache
        t_cached, loss_cached = step(batch)
        plain.append(t_plain)
        cached.append(t_cached)
        worst = max(worst, abs(loss_plain - loss_cached))
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    print(f"{args.batches} batches of {size} ({batches[1]['pixel_values'].shape[0]} pictures a step), "
          f"{args.threads} threads")
    print(f"step, tower on every picture: {mean(plain):.2f} s; through the cache: {mean(cached):.2f} s; "
          f"ratio {mean(plain) / mean(cached):.2f}x; largest loss difference {worst:.2e}")

    walk = TowerCache(cache.tower)  # a fresh, empty cache for the epoch walk, over the tower's own forward
    walk.forward = cache.forward
    steps = args.epoch_steps or -(-len(train) // size)
    with torch.no_grad():
        for s in range(steps):
            pictures = collator([train[(s * size + j) % len(train)] for j in range(size)])["pixel_values"]
            walk(pictures)
    total = walk.hits + walk.misses
    print(f"one epoch's pictures ({steps} steps, {total} pictures): {walk.misses} distinct, hit rate "
          f"{walk.hits / total:.2f}")
    return {"plain_s": mean(plain), "cached_s": mean(cached), "loss_difference": worst, "distinct": walk.misses,
            "pictures": total}


if __name__ == "__main__":
    main()
