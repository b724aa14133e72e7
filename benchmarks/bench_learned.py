"""Quality of a trained learned arrangement model beside the heuristic baselines and the oracle.

Runs `learned` (the given checkpoint), `random`, `population_mean`, `copy_nearest`, `consensus` and
`oracle` through their registered MethodSpecs (what `degusta predict` runs) on the held-out test
participants (split seed 0) of a SYNTHETIC naturalistic dataset folder at context length 0, 2 and 4, and
prints a markdown table: means with 95% bootstrap intervals over episodes, acceptable@t = fraction of
episodes with Kabsch RMSD <= t, and the ratios the quality bar is stated in (learned / oracle RMSD).

Usage:
    degusta data generate naturalistic --out data/naturalistic
    degusta train --config configs/learned_cpu.yaml
    python benchmarks/bench_learned.py --checkpoint runs/learned_cpu      # ~1 min on one core
    python benchmarks/bench_learned.py --checkpoint runs/learned_cpu --split val
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, set before numpy / torch are imported

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from degusta_learn.methods import get_method  # noqa: E402
from degusta_learn.metrics import (  # noqa: E402
    THRESHOLDS,
    bootstrap_ci,
    fraction_acceptable,
    paired_bootstrap,
    score_many,
)
from degusta_learn.scene import load_dataset, make_episodes  # noqa: E402

BASELINES = ("random", "population_mean", "copy_nearest", "consensus", "oracle")


def predict(name, ds, episodes, split, extra=None):
    spec = get_method(name)
    cfg = spec.config_cls(method=name, dataset=str(ds.root), out="", split=split, **(extra or {}))
    t0 = time.perf_counter()
    preds = spec.run(cfg, ds, episodes)
    return preds, time.perf_counter() - t0


def _ci(values, digits=3):
    mean, lo, hi = bootstrap_ci(values)
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", required=True, help="learned run folder or .ckpt")
    parser.add_argument("--dataset", default="data/naturalistic")
    parser.add_argument("--split", default="test", choices=["val", "test"])
    args = parser.parse_args()
    ds = load_dataset(args.dataset)
    print(f"# {ds.label}, split {args.split}, checkpoint {args.checkpoint}\n")
    print("| method | context | object accuracy | Kabsch RMSD | median RMSD | unregistered RMSD | count error "
          "| acc@0.01 | acc@0.05 | acc@0.10 |")
    print("|---|---:|---|---|---:|---|---|---:|---:|---:|")
    means, seconds, per_episode = {}, {}, {}
    for k in (0, 2, 4):
        episodes = make_episodes(ds, k, args.split, 0)
        gts = [ds.arrangement(e.participant, e.target) for e in episodes]
        for name in ("learned", *BASELINES):
            extra = {"checkpoint": args.checkpoint} if name == "learned" else None
            preds, seconds[name, k] = predict(name, ds, episodes, args.split, extra)
            scores = score_many(ds.catalog, gts, preds)
            rmsd = [s.rmsd for s in scores]
            per_episode[name, k] = (np.array(rmsd), np.array([s.object_accuracy for s in scores]))
            ok = fraction_acceptable(rmsd)
            means[name, k] = float(np.nanmean(rmsd))
            print(f"| {name} | {k} | {_ci([s.object_accuracy for s in scores])} | {_ci(rmsd)} | {np.nanmedian(rmsd):.3f} | "
                  f"{_ci([s.rmsd_unregistered for s in scores])} | {_ci([s.count_error for s in scores], 2)} | "
                  + " | ".join(f"{ok[t]:.3f}" for t in THRESHOLDS) + " |")
    print(f"\n{len(episodes)} {args.split} episodes per context length.")
    for k in (0, 2, 4):
        o = means["oracle", k]
        print(f"context {k}: learned / oracle RMSD = {means['learned', k] / o:.2f}x; consensus / oracle = "
              f"{means['consensus', k] / o:.2f}x; copy_nearest / oracle = {means['copy_nearest', k] / o:.2f}x; "
              f"learned predicted {len(episodes)} episodes in {seconds['learned', k]:.1f} s")
    print("\nPaired differences learned - baseline (mean [95% CI], two-sided p); RMSD: negative = learned better, "
          "object accuracy: positive = learned better.\n")
    print("| context | baseline | RMSD difference | p | object accuracy difference | p |")
    print("|---:|---|---|---:|---|---:|")
    for k in (0, 2, 4):
        for name in ("consensus", "copy_nearest", "population_mean"):
            ours, theirs = per_episode["learned", k], per_episode[name, k]
            both = ~np.isnan(ours[0]) & ~np.isnan(theirs[0])
            d_rmsd = paired_bootstrap(ours[0][both], theirs[0][both])
            d_acc = paired_bootstrap(ours[1], theirs[1])
            print(f"| {k} | {name} | {d_rmsd['diff']:+.4f} [{d_rmsd['lo']:+.4f}, {d_rmsd['hi']:+.4f}] | "
                  f"{d_rmsd['p_value']:.3f} | {d_acc['diff']:+.3f} [{d_acc['lo']:+.3f}, {d_acc['hi']:+.3f}] | "
                  f"{d_acc['p_value']:.3f} |")


if __name__ == "__main__":
    main()
