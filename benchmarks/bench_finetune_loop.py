"""Lightning fine-tuning loop vs a bare PyTorch loop on the same tiny VLM and batches; data loading vs step.

For each tiny model (Idefics3 LoRA, Idefics3 full, Qwen2-VL LoRA): real MOGMA examples of the
naturalistic train participants are rendered and collated into fixed batches once; then the same
initial weights train on the same batches (a) in a bare loop (loss, backward, clip 1.0, AdamW step) and
(b) in the toolkit's Lightning loop (`FinetuneModule` in the `trainer.build_trainer` Trainer: CSV +
TensorBoard loggers, checkpoint callback, progress bar, gradient clipping 1.0). Step time = time between
consecutive batch starts (so all per-step framework work counts), median over steps after warm-up,
bare and Lightning runs interleaved `--repeats` times (the machine is shared: ratios within one run).
Data loading = rendering + collating one batch in the main process (warm sprite cache).

Usage:
    python benchmarks/bench_finetune_loop.py                 # ~5 min on 1 CPU thread
    python benchmarks/bench_finetune_loop.py --steps 10 --repeats 1
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

os.environ["HF_HUB_OFFLINE"] = "1"


def batches_for(kind: str, n: int, batch_size: int, ds, cache: Path):
    """(model, processor, batches, data seconds per batch) for tiny `kind`."""
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.data import LiftedExamples
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import make_episodes
    from degusta_learn.vlm.generate import chat_format
    from degusta_learn.vlm.inputs import set_image_budget
    from degusta_learn.vlm.load import load_vlm
    from degusta_learn.vlm.prompt_options import PromptOptions
    from degusta_learn.vlm.random_models.tiny import ensure_tiny

    model, processor = load_vlm(str(ensure_tiny(cache / kind, kind)), device="cpu", dtype="float32")
    set_image_budget(processor, model.config, None)
    examples = LiftedExamples(ds, make_episodes(ds, 2, "train", 0), "mogma", Grid(8, 8), 224,
                              PromptOptions(compose=["objects"]))
    collate = Collator(processor, chat_format(model, processor), 4096, model.config.image_token_id)
    collate([examples[0]])  # warm the sprite cache
    out, times = [], []
    for b in range(n):
        t = time.perf_counter()
        out.append(collate([examples[(b * batch_size + j) % len(examples)] for j in range(batch_size)]))
        times.append(time.perf_counter() - t)
    return model, processor, out, statistics.median(times)


def bare_loop(model, batches, lr: float) -> list[float]:
    import torch

    from degusta_learn.finetune.loss import lm_loss

    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr)
    model.train()
    starts = []
    for batch in batches:
        starts.append(time.perf_counter())
        loss, _ = lm_loss(model, batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        opt.zero_grad()
    starts.append(time.perf_counter())
    return [b - a for a, b in zip(starts, starts[1:])]


def lightning_loop(model, processor, batches, lr: float, mode: str) -> list[float]:
    import lightning as L
    from torch.utils.data import DataLoader

    from degusta_learn.finetune.lora import LoraConfig
    from degusta_learn.finetune.module import FinetuneModule
    from degusta_learn.training import TrainerConfig, build_trainer

    starts: list[float] = []

    class Clock(L.Callback):
        def on_train_batch_start(self, *args):
            starts.append(time.perf_counter())

        def on_train_end(self, *args):
            starts.append(time.perf_counter())

    cfg = SimpleNamespace(lora=LoraConfig(mode=mode), optim=SimpleNamespace(
        lr=lr, weight_decay=0.0, warmup_steps=0, schedule="constant"))
    module = FinetuneModule(model, processor, cfg, None, None, "grid")
    with tempfile.TemporaryDirectory() as tmp:
        tc = TrainerConfig(run_name="bench", run_dir=tmp, max_epochs=-1, max_steps=len(batches), accelerator="cpu",
                           devices=1, monitor=None, log_every_n_steps=10, progress_bar=True)
        trainer = build_trainer(tc, Path(tmp) / "bench", callbacks=[Clock()])
        trainer.fit(module, train_dataloaders=DataLoader(batches, batch_size=None, shuffle=False))
    # on_train_end comes after the last step's optimizer work: the last interval is a full step too.
    return [b - a for a, b in zip(starts, starts[1:])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--steps", type=int, default=24)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from degusta_learn.finetune.lora import LoraConfig, apply_lora
    from degusta_learn.scene import load_dataset
    from degusta_learn.vlm.load import quiet_transformers

    quiet_transformers()
    ds = load_dataset(args.dataset)
    cache = Path(tempfile.mkdtemp(prefix="degusta-bench-tiny-"))
    rows = []
    for kind, mode in [("idefics3", "lora"), ("idefics3", "full"), ("qwen2vl", "lora")]:
        base, processor, batches, data_s = batches_for(kind, args.steps, args.batch_size, ds, cache)
        tokens = sum(int(b["attention_mask"].sum()) for b in batches) / len(batches)
        bare_t, light_t = [], []
        for _ in range(args.repeats):
            for loop in ("bare", "lightning"):
                torch.manual_seed(0)
                model = apply_lora(copy.deepcopy(base), LoraConfig(mode=mode, r=16, dropout=0.0))
                if loop == "bare":
                    bare_t += bare_loop(model, batches, 1e-3)[args.warmup:]
                else:
                    light_t += lightning_loop(model, processor, batches, 1e-3, mode)[args.warmup:]
        b, li = statistics.median(bare_t), statistics.median(light_t)
        rows.append((kind, mode, tokens, b, li, data_s))
    print(f"\n{args.steps} steps x {args.repeats} repeats (first {args.warmup} of each dropped), batch "
          f"{args.batch_size}, torch threads {args.threads}\n")
    print("| tiny model | mode | tokens/batch | bare step ms | Lightning step ms | overhead | data ms/batch | data / step |")
    print("|---|---|---|---|---|---|---|---|")
    for kind, mode, tokens, b, li, d in rows:
        print(f"| {kind} | {mode} | {tokens:.0f} | {1000 * b:.1f} | {1000 * li:.1f} | {100 * (li / b - 1):+.1f}% | "
              f"{1000 * d:.1f} | {d / b:.2f} |")


if __name__ == "__main__":
    main()
