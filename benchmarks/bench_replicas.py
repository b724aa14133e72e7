"""Full-size replicas of the GPU fine-tuning configs, run for real on the CPU, or with --gpu on one GPU as the config
is written (opt-in; NOT run in CI; benchmarks/gpu_check.sh runs the --gpu form).

Per replica (degusta_learn/vlm/random_models/replicas.py: published sizes, random weights, built offline):
  1. token budget over the WHOLE training set, exactly as `degusta train --dry-run` counts it (image / other
     prompt / answer tokens per example, max and mean), and the dry run's predicted memory (model in
     degusta_learn/dryrun.py) for the CPU fp32 run below and for the config as written (GPU bf16);
  2. the config itself, on the CPU, through `degusta_learn.methods.run_train` with overrides: the replica
     as model.name, fp32 (model.dtype=float32, trainer.precision=32-true), trainer.max_steps=2 with
     trainer.accumulate_grad_batches=1 (2 optimizer steps = 2 batches of the config's batch size),
     data.max_train_episodes = 2 batches, data.val_episodes=1, decoding.max_new_tokens small (one constrained
     validation generation), data.num_workers=0 (one process: its RSS is the whole run). Each training run
     is a fresh subprocess: peak RSS (a 20 ms sampling thread on /proc/self/status and getrusage's
     ru_maxrss) covers only that replica; seconds per step = on_train_batch_start -> on_train_batch_end.
  With --gpu (a machine with a CUDA GPU): step 2 only, the config's own dtype, precision, accelerator and
     workers, --steps steps, a validation that generates one batch; per step the allocator's peak
     (torch.cuda.max_memory_allocated, synchronized), and the validation's seconds. Results under NAME@gpu.

Usage (one replica at a time; Qwen2-VL-2B needs ~12+ GB and a long time on 2 cores):
    degusta data generate naturalistic --out /tmp/repl/data
    python benchmarks/bench_replicas.py --data /tmp/repl/data --out /tmp/repl \
        --reference ../shared/reference-models/SmolVLM-256M-Instruct smolvlm_256m smolvlm_500m
    python benchmarks/bench_replicas.py --data /tmp/repl/data --out /tmp/repl qwen2vl_2b --batch-size 1
    python benchmarks/bench_replicas.py --gpu --steps 8 --data /tmp/repl/data --out /tmp/repl \
        --reference ../shared/reference-models/SmolVLM-256M-Instruct smolvlm_256m      # on a GPU
Writes <out>/results.json (appended per replica) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"
ROOT = Path(__file__).resolve().parent.parent
GiB = 1024**3


def rss_bytes() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


class PeakRSS:
    """Samples this process's RSS every `interval` s; `peak` since start or the last `reset()`."""

    def __init__(self, interval: float = 0.02):
        self.interval, self.peak, self._stop = interval, rss_bytes(), threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes())
            time.sleep(self.interval)

    def reset(self) -> None:
        self.peak = rss_bytes()

    def stop(self) -> int:
        self._stop.set()
        self._thread.join()
        return max(self.peak, rss_bytes())


def config_path(name: str) -> Path:
    from degusta_learn.vlm.random_models.replicas import replica_spec

    return ROOT / replica_spec(name)["configs"][0]


def overrides(name: str, replica: Path, data: Path, runs: Path, batch_size: int | None, new_tokens: int,
              checkpointing: bool | None = None, run_name: str | None = None, gpu: bool = False,
              steps: int = 2) -> list[str]:
    """The config's run, cut to `steps` optimizer steps of one batch and one validation generation. On the CPU in
    fp32 (the CPU run); with `gpu`, the config's own dtype, precision and accelerator on one GPU, and the
    validation generates a whole batch of episodes (its time per token is the one the configs estimate)."""
    from degusta_learn.config import load_config
    from degusta_learn.finetune.config import FinetuneConfig

    cfg = load_config(FinetuneConfig, config_path(name), [])
    bs = batch_size or cfg.data.batch_size
    device = (["trainer.devices=1", "trainer.strategy=auto", f"data.val_episodes={bs}"] if gpu else
              ["model.dtype=float32", "trainer.accelerator=cpu", "trainer.devices=1", "trainer.strategy=auto",
               "trainer.precision=32-true", "data.val_episodes=1", "data.num_workers=0"])
    return [f"model.name={replica}", f"dataset={data}"] + device + [
            f"trainer.max_steps={steps}", "trainer.accumulate_grad_batches=1", "trainer.val_check_interval=1.0",
            "trainer.log_every_n_steps=1", "trainer.progress_bar=false", f"trainer.run_dir={runs}",
            f"trainer.run_name={run_name or name}", f"data.batch_size={bs}", f"data.max_train_episodes={steps * bs}",
            f"decoding.max_new_tokens={new_tokens}", "decoding.report_unconstrained=false"] + (
            [] if checkpointing is None else [f"model.gradient_checkpointing={str(checkpointing).lower()}"])


def token_stats(name: str, over: list[str]) -> dict:
    """Token counts over the whole training set (the dry run's counting) and the dry run's text."""
    import dataclasses

    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.dry_run import meta_model
    from degusta_learn.finetune.token_count import count_tokens, set_budget
    from degusta_learn.finetune.train import build_examples
    from degusta_learn.methods import run_train
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor

    full = [o for o in over if not o.startswith(("data.max_train_episodes", "data.val_episodes"))]
    cfg = load_config(FinetuneConfig, config_path(name), full)
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, max_train_episodes=None))
    processor = load_processor(cfg.model.name)
    model, config = meta_model(cfg.model.name)
    set_budget(cfg, processor, config)
    collator = Collator(processor, ChatFormat(processor, model.generation_config), cfg.data.max_length,
                        getattr(config, "image_token_id", None))
    train, _ = build_examples(cfg, load_dataset(cfg.dataset), Grid(cfg.data.grid.rows, cfg.data.grid.cols))
    counts = count_tokens(train, collator)
    out = {"n_train": len(counts)}
    for key in ("image", "text", "answer", "total"):
        values = [c[key] for c in counts]
        out[key] = {"max": max(values), "mean": round(sum(values) / len(values), 1)}
    lines: list[str] = []
    run_train(config_path(name), [o for o in over if o.startswith("model.name=")] + [f"dataset={cfg.dataset}"],
              dry_run=True, log=lines.append)
    out["dry_run_gpu_config"] = lines
    lines = []
    run_train(config_path(name), over, dry_run=True, log=lines.append)
    out["dry_run_cpu_run"] = lines
    return out


def child(name: str, over: list[str], out_json: Path) -> None:
    """One training run (its steps + one constrained validation generation), measured; writes out_json. On a GPU
    also the allocator's peak per step and for the run (torch.cuda.max_memory_allocated); always the validation's
    time (generation and scoring)."""
    import torch

    from degusta_learn.finetune import module as fm
    from degusta_learn.methods import run_train

    torch.set_num_threads(max(1, os.cpu_count() or 1))
    sampler = PeakRSS()
    marks: dict = {"rss_start": rss_bytes(), "steps": [], "rss_step_peaks": [], "cuda_step_peaks": [],
                   "val_s": []}
    cuda = torch.cuda.is_available() and "trainer.accelerator=cpu" not in over
    if cuda:
        marks["device"] = torch.cuda.get_device_name(0)
    orig_start = getattr(fm.FinetuneModule, "on_train_batch_start", None)
    orig_end = getattr(fm.FinetuneModule, "on_train_batch_end", None)
    orig_val_start = getattr(fm.FinetuneModule, "on_validation_start", None)
    orig_val_end = getattr(fm.FinetuneModule, "on_validation_end", None)

    def on_start(self, batch, batch_idx):
        if "rss_before_train" not in marks:
            marks["rss_before_train"] = rss_bytes()
            marks["params_total"] = sum(p.numel() for p in self.parameters())
            marks["params_trainable"] = sum(p.numel() for p in self.parameters() if p.requires_grad)
            marks["batch_tokens"] = []
        marks["batch_tokens"].append(list(batch["input_ids"].shape))
        sampler.reset()
        if cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        marks["_t"] = time.perf_counter()
        return orig_start(self, batch, batch_idx) if orig_start else None

    def on_end(self, outputs, batch, batch_idx):
        if cuda:
            torch.cuda.synchronize()
            marks["cuda_step_peaks"].append(torch.cuda.max_memory_allocated())
        marks["steps"].append(time.perf_counter() - marks.pop("_t"))
        print(f"step {len(marks['steps'])}: {marks['steps'][-1]:.2f} s, batch {marks['batch_tokens'][-1]}"
              + (f", allocated peak {marks['cuda_step_peaks'][-1] / GiB:.2f} GiB" if cuda else ""), flush=True)
        marks["rss_step_peaks"].append(max(sampler.peak, rss_bytes()))
        return orig_end(self, outputs, batch, batch_idx) if orig_end else None

    def on_val_start(self):
        marks["_v"] = time.perf_counter()
        return orig_val_start(self) if orig_val_start else None

    def on_val_end(self):
        if cuda:
            torch.cuda.synchronize()
        marks["val_s"].append(time.perf_counter() - marks.pop("_v"))
        print(f"validation: {marks['val_s'][-1]:.1f} s", flush=True)
        return orig_val_end(self) if orig_val_end else None

    fm.FinetuneModule.on_train_batch_start = on_start
    fm.FinetuneModule.on_train_batch_end = on_end
    fm.FinetuneModule.on_validation_start = on_val_start
    fm.FinetuneModule.on_validation_end = on_val_end
    t0 = time.perf_counter()
    try:
        run_dir = run_train(config_path(name), over)
        metrics = sorted(Path(run_dir).rglob("metrics.csv"))
        marks["metrics_tail"] = metrics[0].read_text().splitlines()[-3:] if metrics else []
    except Exception as e:  # keep what was measured (the steps) and say what failed
        marks["error"] = f"{type(e).__name__}: {e}"
    marks.pop("_v", None)  # a validation that failed before its end
    marks["wall_s"] = time.perf_counter() - t0
    marks["rss_peak_sampled"] = sampler.stop()
    marks["ru_maxrss"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    if cuda:
        marks["cuda_run_peak"] = torch.cuda.max_memory_allocated()  # since the last step's reset: validation too
        marks["cuda_reserved_peak"] = torch.cuda.max_memory_reserved()
    out_json.write_text(json.dumps(marks, indent=1))


def main(argv=None) -> int:
    from degusta_learn.vlm.random_models.replicas import REPLICAS, build_replica

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", default=list(REPLICAS))
    ap.add_argument("--data", type=Path, default=Path("/tmp/repl/data"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/repl"))
    ap.add_argument("--reference", type=Path, default=None,
                    help="SmolVLM-256M-Instruct's real tokenizer/processor folder (SmolVLM replicas use it)")
    ap.add_argument("--batch-size", type=int, default=None, help="override data.batch_size (default: the config's)")
    ap.add_argument("--new-tokens", type=int, default=256, help="decoding.max_new_tokens of the validation generation")
    ap.add_argument("--skip-train", action="store_true", help="token counts and dry runs only")
    ap.add_argument("--gradient-checkpointing", choices=["on", "off"], default=None,
                    help="override the config's model.gradient_checkpointing (results under NAME+gc / NAME-gc)")
    ap.add_argument("--gpu", action="store_true",
                    help="run the config as written (its dtype, precision, accelerator) on one GPU; results under NAME@gpu")
    ap.add_argument("--steps", type=int, default=2, help="optimizer steps of the training run (default 2)")
    ap.add_argument("--child", nargs=2, metavar=("NAME", "JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child[0], args.set, Path(args.child[1]))
        return 0
    results_file = args.out / "results.json"
    results = json.loads(results_file.read_text()) if results_file.is_file() else {}
    for name in args.names:
        replica = args.out / name
        ref = args.reference if (args.reference and REPLICAS[name]["family"] == "idefics3") else None
        record = replica / "degusta_replica.json"
        # a config-only replica (built for dry runs: weights false) cannot train: rebuild it with weights
        if not record.is_file() or (not args.skip_train and not json.loads(record.read_text()).get("weights", True)):
            t = time.perf_counter()
            build_replica(name, replica, reference_dir=ref)
            print(f"{name}: built in {time.perf_counter() - t:.0f} s", flush=True)
        gc = None if args.gradient_checkpointing is None else args.gradient_checkpointing == "on"
        key = name + {None: "", True: "+gc", False: "-gc"}[gc] + ("@gpu" if args.gpu else "")  # entry and run name
        over = overrides(name, replica, args.data, args.out / "runs", args.batch_size, args.new_tokens, gc, key,
                         gpu=args.gpu, steps=args.steps)
        cached = results.get(key, {})
        # the whole training set's token counts take minutes of CPU: a GPU run leaves them to the CPU run's entry
        tokens = (None if args.gpu else
                  cached["tokens"] if cached.get("overrides") == over else token_stats(name, over))
        res = {"overrides": over, "tokens": tokens,
               "replica": json.loads((replica / "degusta_replica.json").read_text())}
        results[key] = res
        results_file.write_text(json.dumps(results, indent=1))
        if not args.skip_train:
            import shutil

            shutil.rmtree(args.out / "runs" / key, ignore_errors=True)
            out_json = args.out / f"{key}.train.json"
            cmd = [sys.executable, __file__, "--child", name, str(out_json)] + [x for o in over for x in ("--set", o)]
            subprocess.run(cmd, check=True)
            res["train"] = json.loads(out_json.read_text())
        results[key] = res
        results_file.write_text(json.dumps(results, indent=1))
        report(key, res)
    return 0


def report(name: str, res: dict) -> None:
    tk = res["tokens"]
    print(f"\n== {name} ({res['replica']['tokenizer']})")
    if tk:
        report_tokens(tk)
    tr = res.get("train")
    if tr:
        report_train(tr)


def report_tokens(tk: dict) -> None:
    print("  tokens over {n} training examples (max / mean): image {i[max]} / {i[mean]}, other prompt {t[max]} / "
          "{t[mean]}, answer {a[max]} / {a[mean]}, total {T[max]} / {T[mean]}".format(
              n=tk["n_train"], i=tk["image"], t=tk["text"], a=tk["answer"], T=tk["total"]))
    for line in tk["dry_run_cpu_run"] + tk["dry_run_gpu_config"]:
        if "predicted memory" in line:
            print("  " + line.strip())


def report_train(tr: dict) -> None:
    if tr.get("error"):
        print(f"  FAILED after {len(tr['steps'])} steps: {tr['error']}")
    if "params_trainable" not in tr:  # failed before the first step: nothing else was measured
        return
    print(f"  params: {tr['params_trainable']:,} trainable of {tr['params_total']:,}; batches {tr['batch_tokens']}")
    print(f"  seconds per step: {', '.join(f'{s:.2f}' for s in tr['steps'])}; wall {tr['wall_s']:.0f} s")
    print(f"  RSS: start {tr['rss_start'] / GiB:.2f} GiB, before training {tr['rss_before_train'] / GiB:.2f} GiB, "
          f"step peaks {', '.join(f'{r / GiB:.2f}' for r in tr['rss_step_peaks'])} GiB, run peak "
          f"{tr['rss_peak_sampled'] / GiB:.2f} GiB (ru_maxrss {tr['ru_maxrss'] / GiB:.2f} GiB)")
    if tr.get("cuda_step_peaks"):
        print(f"  {tr['device']}: allocated peak per step {', '.join(f'{b / GiB:.2f}' for b in tr['cuda_step_peaks'])} "
              f"GiB; last step + validation {tr['cuda_run_peak'] / GiB:.2f} GiB (reserved {tr['cuda_reserved_peak'] / GiB:.2f})")
    if tr.get("val_s"):
        print(f"  validation (generate + score): {', '.join(f'{v:.1f}' for v in tr['val_s'])} s")


if __name__ == "__main__":
    sys.exit(main())
