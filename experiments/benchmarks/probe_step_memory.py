"""Where a replica's training-step memory goes: RSS around one forward and backward (opt-in; NOT run in CI).

Runs ONE training step of a replica already measured by `bench_replicas.py` (its overrides are read from
`<out>/results.json`), through `run_train` like the benchmark's child, and prints: the RSS before the step,
when the vision tower is done, the peak and the end of the forward, the RSS after `malloc_trim(0)` (what glibc
kept of freed memory), the bytes of the tensors saved for backward (`saved_tensors_hooks`), and the peak and
end of the backward. Run it with `MALLOC_MMAP_THRESHOLD_=1048576` in the environment to see the peak without
glibc's retention (benchmarks/RESULTS.md, "glibc and gradient checkpointing").

Usage:
    python benchmarks/probe_step_memory.py smolvlm_256m+gc --out /tmp/repl
    MALLOC_MMAP_THRESHOLD_=1048576 python benchmarks/probe_step_memory.py qwen2vl_2b --out /tmp/repl
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import sys
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"
sys.path.insert(0, str(Path(__file__).resolve().parent))
GiB = 1024**3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", help="a results.json entry of bench_replicas.py (smolvlm_256m, smolvlm_256m+gc, ...)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/repl"), help="bench_replicas.py's --out")
    args = ap.parse_args(argv)

    import torch

    from bench_replicas import PeakRSS, config_path, rss_bytes
    from degusta_learn.finetune import module as fm
    from degusta_learn.methods import run_train

    results = json.loads((args.out / "results.json").read_text())
    if args.name not in results:
        raise SystemExit(f"{args.name}: not in {args.out / 'results.json'} (run bench_replicas.py first); "
                         f"there: {', '.join(results)}")
    keep = ("trainer.max_steps", "trainer.run_name", "data.val_episodes", "trainer.monitor")
    over = [o for o in results[args.name]["overrides"] if not o.startswith(keep)]
    over += ["trainer.max_steps=1", "trainer.run_name=probe_step_memory", "data.val_episodes=0", "trainer.monitor=null"]
    training_step = fm.FinetuneModule.training_step

    def one_step(self, batch, batch_idx):
        sampler, before = PeakRSS(), rss_bytes()
        tower = next(m for n, m in fm.unwrap(self.model).named_modules() if n.endswith(("vision_model", "visual")))
        marks: dict = {}
        hook = tower.register_forward_hook(lambda m, i, o: marks.setdefault("tower", rss_bytes()) and None)
        saved: list = []

        def pack(t):
            saved.append(t)
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            loss = training_step(self, batch, batch_idx)
        forward_peak, after_forward = sampler.peak, rss_bytes()
        gc.collect()
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        trimmed = rss_bytes()
        storages = {t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in saved}
        sampler.reset()
        loss.backward()
        backward_peak, end = sampler.stop(), rss_bytes()
        hook.remove()
        print(f"{args.name} (MALLOC_MMAP_THRESHOLD_={os.environ.get('MALLOC_MMAP_THRESHOLD_', 'unset')}), GiB: "
              f"before {before / GiB:.2f}; tower done {marks.get('tower', 0) / GiB:.2f}; forward peak "
              f"{forward_peak / GiB:.2f}, end {after_forward / GiB:.2f}, after malloc_trim {trimmed / GiB:.2f}; "
              f"saved for backward {sum(storages.values()) / GiB:.2f} in {len(storages)} storages; "
              f"backward peak {backward_peak / GiB:.2f}, end {end / GiB:.2f}", flush=True)
        os._exit(0)

    fm.FinetuneModule.training_step = one_step
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    run_train(config_path(results[args.name]["replica"]["replica"]), over)
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
