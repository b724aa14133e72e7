"""The paper's matching beside ours: how much the scores move when predictions are matched greedily.

Runs the heuristic baselines (random, population_mean, copy_nearest, consensus, and the oracle) in-process on
the default data (data/naturalistic, test participants, split seed 0, context 4), plus any predictions files
given, and scores each under both matching rules (`matching="hungarian"`, ours, and `"paper"`, the paper's
greedy rule: metrics/matching.py). Prints one markdown table: mean object accuracy, mean Kabsch RMSD (over
non-failed predictions) and mean set RMSD under each rule, and how many episodes the rules pair differently,
of them how many with a higher total Hamming distance under the greedy rule (greedy was not optimal) rather
than only another tie broken, and how many predict fewer objects than the ground truth holds (the greedy rule
then leaves the last true objects unmatched, whatever was predicted), and on how many the object accuracy
differs. Times are one `score_many` call per rule.

Usage:
    python benchmarks/bench_matching.py                                  # ~10 s on a free core
    python benchmarks/bench_matching.py --predictions runs/cmp/predictions/mogma.jsonl
    python benchmarks/bench_matching.py --dataset data/simulated --context 2
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, set before numpy is imported

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from degusta_learn.methods import get_method  # noqa: E402
from degusta_learn.metrics import matched_pairs, score_many  # noqa: E402
from degusta_learn.metrics.matching import feature_table  # noqa: E402
from degusta_learn.scene import load_dataset, make_episodes, read_predictions  # noqa: E402

BASELINES = ("oracle", "consensus", "copy_nearest", "population_mean", "random")


def run_baseline(name, ds, episodes, seed):
    spec = get_method(name)
    cfg = spec.config_cls(method=name, dataset=str(ds.root), out="", seed=seed)
    return spec.run(cfg, ds, episodes)


def total_hamming(table, gt, placements, pairs) -> int:
    """Total Hamming distance of the matched pairs (what the Hungarian rule minimizes)."""
    g = table.rows_of([gt.placements[p.gt_index].object for p in pairs], "ground truth")
    q = table.rows_of([placements[p.pred_index].object for p in pairs], "prediction")
    return int(sum(table.hamming[a, b] for a, b in zip(g, q))) if table.hamming is not None else 0


def compare_rules(ds, gts, preds) -> dict:
    """Scores under both rules, and per-episode differences of the pairings."""
    scores, seconds = {}, {}
    for rule in ("hungarian", "paper"):
        start = time.perf_counter()
        scores[rule] = score_many(ds.catalog, gts, preds, tables=ds.tables, matching=rule)
        seconds[rule] = time.perf_counter() - start
    table = feature_table(ds.catalog)
    differ = worse = fewer = acc_differ = 0
    for gt, pred, h, p in zip(gts, preds, scores["hungarian"], scores["paper"]):
        a, b = (matched_pairs(ds.catalog, gt, pred, matching=rule) for rule in ("hungarian", "paper"))
        if [(x.gt_index, x.pred_index) for x in a] != [(x.gt_index, x.pred_index) for x in b]:
            differ += 1
            worse += total_hamming(table, gt, pred.placements, b) > total_hamming(table, gt, pred.placements, a)
            fewer += h.n_pred < h.n_gt  # the greedy rule leaves the last true objects unmatched
        acc_differ += h.object_accuracy != p.object_accuracy
    out = {"n": len(gts), "differ": differ, "worse": worse, "fewer": fewer, "acc_differ": acc_differ,
           "seconds": seconds}
    for rule, ss in scores.items():
        out[rule] = {"acc": float(np.mean([s.object_accuracy for s in ss])),
                     "rmsd": float(np.nanmean([s.rmsd for s in ss])) if any(math.isfinite(s.rmsd) for s in ss)
                     else math.nan,
                     "set": float(np.mean([s.set_rmsd for s in ss]))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--context", type=int, default=4)
    ap.add_argument("--split", default="test")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--predictions", nargs="*", default=[], help="predictions files on the same episodes")
    args = ap.parse_args()
    ds = load_dataset(args.dataset)
    episodes = make_episodes(ds, args.context, args.split, args.seed)
    methods = {name: run_baseline(name, ds, episodes, args.seed) for name in BASELINES}
    wanted = {e.id for e in episodes}
    for path in args.predictions:
        preds = [p for p in read_predictions(path, ds.catalog) if p.episode in wanted]
        methods[preds[0].method if preds else Path(path).stem] = preds
    print(f"{ds.label}: {len(episodes)} episodes ({args.split} participants, context {args.context}, "
          f"split seed {args.seed})\n")
    print("| method | object accuracy: ours / paper | Kabsch RMSD: ours / paper | set RMSD: ours / paper | "
          "episodes paired differently | of which higher total Hamming | of which fewer predicted than true | "
          "accuracy differs | score s: ours / paper |")
    print("|---|---|---|---|---:|---:|---:|---:|---|")
    for name, preds in methods.items():
        gts = [ds.arrangement(p.participant, p.target) for p in preds]
        r = compare_rules(ds, gts, preds)
        h, p = r["hungarian"], r["paper"]
        print(f"| {name} | {h['acc']:.3f} / {p['acc']:.3f} | {h['rmsd']:.4f} / {p['rmsd']:.4f} | "
              f"{h['set']:.4f} / {p['set']:.4f} | {r['differ']} of {r['n']} | {r['worse']} | {r['fewer']} | {r['acc_differ']} | "
              f"{r['seconds']['hungarian']:.3f} / {r['seconds']['paper']:.3f} |")


if __name__ == "__main__":
    main()
