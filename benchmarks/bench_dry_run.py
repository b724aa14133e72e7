"""How long `degusta train --dry-run` takes on the SmolVLM-256M config: the token count as it is now (`token_budget`:
every example's text tokenized alone, the image processor on one example per image layout and a checked sample)
against the count it replaced (the image processor on every one of the 2,085 training examples).

Usage (the dataset first; the reference folder holds SmolVLM-256M-Instruct's config, processor and tokenizer files,
no weights):
    degusta data generate naturalistic --out /tmp/dry/naturalistic
    python benchmarks/bench_dry_run.py --dataset /tmp/dry/naturalistic
        [--reference ../shared/reference-models/SmolVLM-256M-Instruct] [--config configs/finetune_smolvlm_256m.yaml]
        [--set trainer.accelerator=cpu ...] [--exhaustive-now] [--bounded-only]

Every dry run is a fresh subprocess (imports, config, processor, meta-device model, token counts, report), timed by
its wall clock and its CPU time (user + system, the children's rusage), in this order:
  1. bounded: the command a user types,
       degusta train --dry-run --config <config> --set model.name=<reference> --set dataset=<dataset> [--set ...]
  2. before: the same dry run counting as it did before `token_budget`: `finetune.dry_run.dry_run(cfg, sample=None,
     heaviest=False)` (the processor on every training and validation example, epoch 0's contexts) with the blank
     images it used then (`BlankAsBefore`: every image size x size, GoMO sheets without their source, so the
     composed object sheet was a tiled canvas drawn for every example);
  3. with --exhaustive-now, the exhaustive count with today's blank images (`_SizeOnlyRenderer`: each image the
     renderer's size, the composed object sheet the cached `objects_canvas`): what the blanks alone changed;
  4. bounded again (a second reading brackets the slow ones, the machine's load drifting meanwhile).
Prints a markdown table (wall, CPU, exit status, the report's max / mean tokens), the ratio before / bounded
(wall and CPU, against the mean of the two bounded runs) and the 1-minute load average before and after. The maxima
and means must agree (the bounded count is exact; its maxima also cover the heaviest contexts an epoch could
draw). A GPU config on a CPU machine exits 3 (its trainer check FAILS, the whole report printed): expected.
Timings on a shared machine are noisy: quote the ratio of one run together with its wall times.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

TOKENS = re.compile(r"tokens per example\s+max (\d+) / mean ([\d.]+)")


class BlankAsBefore:
    """The dry run's blank images before `token_budget`: every image `size` x `size` (the renderer's size), GoMO
    sheets without `GOMO_SOURCE` (so `adapt_prompt` tiled the object sheets with `tile_canvas` for every example)."""

    def __init__(self, renderer, pixels: bool = True):
        self.size = renderer.size

    def _blank(self, *args, **kwargs):
        from PIL import Image

        return Image.new("RGB", (self.size, self.size), "white")

    gomo = gomo_sheet = uma = gma = table = _blank


def exhaustive_child(config: str, overrides: list[str], as_before: bool) -> int:
    """The dry run with the exhaustive count, in this process (run as `--child`); `as_before`: its blank images too."""
    from degusta_learn.config import load_config
    from degusta_learn.dryrun import recording
    from degusta_learn.finetune import train
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.dry_run import dry_run

    if as_before:
        train._SizeOnlyRenderer = BlankAsBefore
    cfg = load_config(FinetuneConfig, config, overrides)
    with recording() as report:
        dry_run(cfg, sample=None, heaviest=False)
    return 0 if report.ok else 3


def timed(cmd: list[str]) -> dict:
    """Run `cmd`; wall and CPU seconds, exit status, its "tokens per example" max and mean, and its output."""
    env = dict(os.environ, HF_HUB_OFFLINE="1")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    found = TOKENS.search(proc.stdout)
    return {"wall": wall, "cpu": cpu, "rc": proc.returncode, "out": proc.stdout, "err": proc.stderr,
            "max": int(found.group(1)) if found else None, "mean": float(found.group(2)) if found else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--reference", default="../shared/reference-models/SmolVLM-256M-Instruct")
    ap.add_argument("--config", default="configs/finetune_smolvlm_256m.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more overrides, for every run")
    ap.add_argument("--exhaustive-now", action="store_true", help="also the exhaustive count with today's blanks")
    ap.add_argument("--bounded-only", action="store_true", help="time the bounded dry run only")
    ap.add_argument("--child", choices=["before", "now"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    overrides = [f"model.name={args.reference}", f"dataset={args.dataset}", *args.set]
    if args.child:
        sys.exit(exhaustive_child(args.config, overrides, as_before=args.child == "before"))
    if not Path(args.dataset).is_dir():
        sys.exit(f"no dataset at {args.dataset}: degusta data generate naturalistic --out {args.dataset}")
    cli = [sys.executable, "-m", "degusta_learn.cli", "train", "--dry-run", "--config", args.config]
    cli += [x for o in overrides for x in ("--set", o)]
    child = [sys.executable, __file__, "--dataset", args.dataset, "--reference", args.reference,
             "--config", args.config] + [x for o in args.set for x in ("--set", o)] + ["--child"]
    plan = [("bounded", cli)]
    if not args.bounded_only:
        plan += [("before", child + ["before"])] + ([("exhaustive now", child + ["now"])] if args.exhaustive_now else [])
        plan += [("bounded", cli)]
    load0 = os.getloadavg()[0]
    runs = []
    for name, cmd in plan:
        r = timed(cmd)
        runs.append((name, r))
        print(f"{name}: {r['wall']:.1f} s wall, {r['cpu']:.1f} s CPU, exit {r['rc']}", file=sys.stderr, flush=True)
        if r["rc"] not in (0, 3) or r["max"] is None:
            sys.exit(f"{name} dry run failed (exit {r['rc']}):\n{r['out']}\n{r['err']}")
    load1 = os.getloadavg()[0]
    print("$ " + " ".join(cli[2:]).replace("degusta_learn.cli", "degusta", 1))
    print(next(line for line in runs[0][1]["out"].splitlines() if "tokens counted" in line).strip())
    print("\n| run | wall s | CPU s | exit | tokens max / mean |\n|---|---:|---:|---:|---|")
    for name, r in runs:
        print(f"| {name} | {r['wall']:.1f} | {r['cpu']:.1f} | {r['rc']} | {r['max']} / {r['mean']:.1f} |")
    bounded = [r for name, r in runs if name == "bounded"]
    if not args.bounded_only:
        full = next(r for name, r in runs if name == "before")
        wall = sum(r["wall"] for r in bounded) / len(bounded)
        cpu = sum(r["cpu"] for r in bounded) / len(bounded)
        same = all((r["max"], r["mean"]) == (full["max"], full["mean"]) for r in bounded)
        agree = "the same" if same else ("DIFFER (a bounded max above the exhaustive one: the heaviest contexts an "
                                         "epoch could draw, which the exhaustive count leaves out)")
        print(f"\nratio before / bounded: {full['wall'] / wall:.1f}x wall, {full['cpu'] / cpu:.1f}x CPU; "
              f"max / mean tokens {agree}")
    print(f"1-minute load average: {load0:.2f} before, {load1:.2f} after ({os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
