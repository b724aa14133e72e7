"""Seconds per training step of each stage of the base's pretraining recipe, on this machine (opt-in; NOT run in CI).

`degusta train --config configs/pretrain_tiny_vlm_cpu.yaml` runs three stages with different costs: the vision
stage (tower + projector + dense head on one-scene images), the one-scene curriculum (decoder, frozen tower) and
the final mix (multi-scene prompts, sheets, written lists). This builds the recipe's model and data exactly as
`pretrain.train.run` does, runs `--steps` optimizer steps of each stage on that stage's own examples (forward,
backward, AdamW; the module's `training_step`, so every auxiliary loss is in; the batches rendered beforehand),
and prints the median seconds a step, the projected minutes of the whole recipe (steps per stage x median) and,
with `--compare KEY=VALUE`, the same under another override as a ratio measured in the same run (timings on shared
machines are noisy: compare ratios, not seconds), timed in the order A, B, B, A and each the mean of its two rounds
(the configuration timed first in a process runs its vision stage 1.3-1.5x slower, whichever it is). The projection
leaves out rendering and collating (the stages' own data loading, which `data.num_workers` moves off the training
process), validations, checkpoints and Lightning's loop, and a stage's batches differ in length (the final mix's
most): the recipe's own log is the measure of its time (benchmarks/RESULTS.md, "The recipe's time").

Usage:
    python benchmarks/bench_pretrain_steps.py --steps 30
    python benchmarks/bench_pretrain_steps.py --steps 30 --set trainer.cpu_kernels=native   # the CPU's own kernels
    python benchmarks/bench_pretrain_steps.py --steps 30 --set channels_last=false --compare channels_last=true
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"


def build(overrides: list[str], run_dir: Path):
    """(module, training examples, their collator, cfg) of the recipe under `overrides`, built by `build_recipe` as
    `pretrain.train.run` builds them."""
    from degusta_learn.config import load_config
    from degusta_learn.pretrain.export import RECIPE
    from degusta_learn.pretrain.train import PretrainConfig, build_recipe
    from degusta_learn.shipped import SHIPPED_DIR

    cfg = load_config(PretrainConfig, str(SHIPPED_DIR / RECIPE), overrides)
    parts = build_recipe(cfg, run_dir, module_cls=stepped_module())
    return parts.module, parts.train, parts.collate, cfg


def stepped_module():
    """PerceptionModule with a settable step (there is no Trainer here) and `log` a no-op."""
    from degusta_learn.pretrain.module import PerceptionModule

    class Stepped(PerceptionModule):
        step = 0

        @property
        def global_step(self) -> int:
            return self.step

        def log(self, *args, **kwargs) -> None:
            pass

    return Stepped


def time_stage(module, examples, collate, cfg, first_step: int, steps: int, warmup: int = 2) -> list[float]:
    """Seconds of each of `steps` optimizer steps (forward, backward, clipping, AdamW) from step `first_step` on,
    after `warmup` untimed ones. The batches are rendered and collated before the clock starts: rendering fills
    caches that a second measurement would find warm, and in training it is the same for every model setting."""
    import torch

    module.step = first_step
    module.on_train_batch_start(None, 0)  # freezes the tower after the vision stage, as training does
    params = [p for p in module.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=1e-4)
    b = cfg.data.batch_size
    starts = [(first_step + k) * b for k in range(warmup + steps)]
    batches = [collate([examples[j] for j in range(i, i + b)]) for i in starts]
    out = []
    for k, batch in enumerate(batches):
        t = time.perf_counter()
        loss = module.training_step(batch, k)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)
        if k >= warmup:
            out.append(time.perf_counter() - t)
    return out


def measure(overrides: list[str], steps: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        module, examples, collate, cfg = build(overrides, Path(tmp))
        d = cfg.data
        final = cfg.trainer.max_steps - d.tower_steps - d.curriculum_steps
        stages = {"vision": (0, d.tower_steps), "curriculum": (d.tower_steps, d.curriculum_steps),
                  "final mix": (d.tower_steps + d.curriculum_steps, final)}
        result = {}
        for name, (first, n) in stages.items():
            if n <= 0:
                continue
            secs = statistics.median(time_stage(module, examples, collate, cfg, first, steps))
            result[name] = (secs, n)
        return result


def mean_of(r1: dict, r2: dict) -> dict:
    return {k: ((r1[k][0] + r2[k][0]) / 2, n) for k, (_, n) in r1.items()}


def report(label: str, result: dict) -> float:
    total = sum(s * n for s, n in result.values()) / 60
    parts = ", ".join(f"{k} {n} x {s:.2f} s" for k, (s, n) in result.items())
    print(f"{label}: {parts}; training steps ~{total:.0f} min (rendering, validations and checkpoints not included)")
    return total


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=30, help="timed steps a stage (after two warm-up steps)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override of the recipe")
    p.add_argument("--compare", action="append", default=[], metavar="KEY=VALUE",
                   help="also time the recipe with these overrides added, and print the ratio")
    a = p.parse_args(argv)
    if any(o.split("=")[0].strip() == "trainer.cpu_kernels" for o in a.compare):
        p.error("--compare trainer.cpu_kernels: the kernels are chosen once per process; run the script twice "
                "with --set trainer.cpu_kernels=native and without it")
    import torch

    from degusta_learn.config import load_config
    from degusta_learn.pretrain.export import RECIPE
    from degusta_learn.pretrain.train import PretrainConfig
    from degusta_learn.shipped import SHIPPED_DIR
    from degusta_learn.training import pin_cpu_kernels

    kernels = pin_cpu_kernels(load_config(PretrainConfig, str(SHIPPED_DIR / RECIPE), a.set).trainer.cpu_kernels)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {kernels} kernels (the recipe's "
          "trainer.cpu_kernels, as degusta train asks for them)")
    if not a.compare:
        report("recipe", measure(a.set, a.steps))
        return 0
    # A, B, B, A: whichever configuration runs first in a process finds its caches and thread pool cold (the first
    # vision stage timed ran 1.26-1.52x slower whichever it was); each is reported as the mean of its two rounds
    a1 = measure(a.set, a.steps)
    b1 = measure(a.set + a.compare, a.steps)
    b2 = measure(a.set + a.compare, a.steps)
    base, other = mean_of(a1, measure(a.set, a.steps)), mean_of(b1, b2)
    t0, t1 = report("recipe", base), report(" ".join(a.compare), other)
    for k in base:
        print(f"  {k}: {base[k][0] / other[k][0]:.2f}x faster with {' '.join(a.compare)}")
    print(f"  whole recipe: {t0 / t1:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
