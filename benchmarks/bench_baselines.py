"""Quality of the heuristic baselines beside the oracle floor, on the SYNTHETIC naturalistic default.

Generates the naturalistic dataset (seed 0) into a temporary folder exactly as `degusta data generate`
does, loads it back, and runs `random`, `population_mean`, `copy_nearest`, `consensus` and `oracle`
through their registered MethodSpecs (what `degusta predict` runs) on the held-out test participants
(split seed 0) at context length 0, 2 and 4. Prints markdown tables: means with 95% bootstrap intervals
over episodes, the acceptability calibration of the simulated jitter-study ratings against the paper's
table, and the simulated benchmark's 72 experiments (reconstruction vs generalization).

Usage:
    python benchmarks/bench_baselines.py            # ~20 s on a free core
    python benchmarks/bench_baselines.py --seed 1   # another draw of the synthetic data
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, set before numpy is imported

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from degusta_learn.methods import get_method  # noqa: E402
from degusta_learn.metrics import (  # noqa: E402
    PAPER_ACCEPTABILITY,
    THRESHOLDS,
    acceptability_curve,
    bootstrap_ci,
    fraction_acceptable,
    score_many,
)
from degusta_learn.scene import load_dataset, make_episodes, read_episodes  # noqa: E402
from degusta_learn.synth import generate_dataset, naturalistic_with_styles  # noqa: E402

METHODS = ("random", "population_mean", "copy_nearest", "consensus", "oracle")


def run(name, ds, episodes, seed):
    spec = get_method(name)
    cfg = spec.config_cls(method=name, dataset=str(ds.root), out="", seed=seed)
    return spec.run(cfg, ds, episodes)


def _ci(values, digits=3):
    mean, lo, hi = bootstrap_ci(values)
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def score_row(ds, episodes, preds):
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    scores = score_many(ds.catalog, gts, preds)
    rmsd = [s.rmsd for s in scores]
    ok = fraction_acceptable(rmsd)
    return {"acc": [s.object_accuracy for s in scores], "rmsd": rmsd,
            "unreg": [s.rmsd_unregistered for s in scores], "count": [s.count_error for s in scores], "ok": ok}


def baseline_table(ds, seed):
    print("| method | context | object accuracy | Kabsch RMSD | unregistered RMSD | count error "
          "| acc@0.01 | acc@0.05 | acc@0.10 |")
    print("|---|---:|---|---|---|---|---:|---:|---:|")
    means = {}
    for k in (0, 2, 4):
        episodes = make_episodes(ds, k, "test", seed)
        for name in METHODS:
            r = score_row(ds, episodes, run(name, ds, episodes, seed))
            means[name, k] = (np.mean(r["acc"]), np.nanmean(r["rmsd"]))
            print(f"| {name} | {k} | {_ci(r['acc'])} | {_ci(r['rmsd'])} | {_ci(r['unreg'])} | "
                  f"{_ci(r['count'], 2)} | " + " | ".join(f"{r['ok'][t]:.3f}" for t in THRESHOLDS) + " |")
    print(f"\n{len(episodes)} test episodes per context length ({len(episodes) // 5} held-out participants).")
    o, c, p = (means[m, 4] for m in ("oracle", "copy_nearest", "population_mean"))
    print(f"At context 4: Kabsch RMSD copy_nearest / oracle = {c[1] / o[1]:.2f}x, population_mean / copy_nearest "
          f"= {p[1] / c[1]:.2f}x; object accuracy oracle {o[0]:.3f}, copy_nearest {c[0]:.3f}, "
          f"consensus {means['consensus', 4][0]:.3f}, population_mean {p[0]:.3f}.")


def acceptability_table(ds):
    curve = acceptability_curve(ds.ratings)
    n = {t: sum(r.rmsd_jitter <= t for r in ds.ratings) for t in THRESHOLDS}
    print("| RMSD threshold | " + " | ".join(f"{t:.2f}" for t in THRESHOLDS) + " |")
    print("|---|" + "---:|" * len(THRESHOLDS))
    print("| paper (human ratings) | " + " | ".join(f"{PAPER_ACCEPTABILITY[t]:.3f}" for t in THRESHOLDS) + " |")
    print("| SYNTHETIC ratings | " + " | ".join(f"{curve[t]:.3f}" for t in THRESHOLDS) + " |")
    print("| jitter trials with RMSD <= t | " + " | ".join(str(n[t]) for t in THRESHOLDS) + " |")


def simulated_table(root: Path, seed):
    folder = generate_dataset("simulated", root / "simulated", seed=seed)
    ds = load_dataset(folder)
    episodes = read_episodes(folder / "episodes.jsonl", ds)
    print("| method | task | episodes | object accuracy | Kabsch RMSD | unregistered RMSD |")
    print("|---|---|---:|---|---|---|")
    for name in METHODS[1:]:
        preds = run(name, ds, episodes, seed)
        for task in ("reconstruction", "generalization"):
            idx = [i for i, e in enumerate(episodes) if e.task == task]
            r = score_row(ds, [episodes[i] for i in idx], [preds[i] for i in idx])
            print(f"| {name} | {task} | {len(idx)} | {_ci(r['acc'])} | {_ci(r['rmsd'])} | {_ci(r['unreg'])} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=0, help="data seed (the split seed stays 0)")
    args = parser.parse_args()
    t0 = time.process_time()
    naturalistic_with_styles(args.seed)
    gen_cpu = time.process_time() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        folder = generate_dataset("naturalistic", Path(tmp) / "naturalistic", seed=args.seed)
        gen_wall = time.perf_counter() - t0
        ds = load_dataset(folder)
        print(f"# {ds.label}: {len(ds.participants)} participants, {len(ds.arrangements)} arrangements; "
              f"generated in {gen_cpu:.2f} s CPU in memory, {gen_wall:.2f} s wall with files\n")
        baseline_table(ds, 0)
        print("\n## Simulated jitter-study ratings\n")
        acceptability_table(ds)
        print("\n## Simulated benchmark (72 experiments)\n")
        simulated_table(Path(tmp), args.seed)


if __name__ == "__main__":
    main()
