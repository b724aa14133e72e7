"""Placement error by the item's place in the answer: are the later objects a method names placed worse?

For each predictions file, every matched (ground-truth, predicted) pair of every episode, as the scorer matches them
(`degusta_learn.metrics.matched_pairs`), grouped by the predicted item's index in its answer (1 = the first object
named; the last row pools that index and beyond): how many pairs, the fraction with the right object id, the mean
unregistered distance (all pairs; those whose id is right; those whose id is wrong) and the RMS residual after the
episode's Kabsch registration. The ground truth lists objects in the person's placing order, so a heuristic's rows
show how much harder the later-placed objects are anyway.

Usage:
    python benchmarks/by_position.py --dataset data/naturalistic PRED.jsonl [PRED.jsonl ...] [--last 6]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from degusta_learn.metrics import matched_pairs
from degusta_learn.scene import load_dataset, read_predictions


def by_position(ds, predictions, last: int = 6) -> list[dict]:
    """One row per item index 1..last (the last pools `last` and beyond), over every episode's matched pairs."""
    groups: dict[int, list] = {}
    for pred in predictions:
        gt = ds.arrangement(pred.participant, pred.target)
        for pair in matched_pairs(ds.catalog, gt, pred):
            groups.setdefault(min(pair.pred_index + 1, last), []).append(pair)

    def mean(values):
        return float(np.mean(values)) if values else float("nan")

    return [{"item": k, "pooled": k == last, "pairs": len(v),
             "right_id": mean([p.same_object for p in v]),
             "distance": mean([p.distance for p in v]),
             "distance_right": mean([p.distance for p in v if p.same_object]),
             "distance_wrong": mean([p.distance for p in v if not p.same_object]),
             "residual": float(np.sqrt(np.mean([p.residual ** 2 for p in v])))}
            for k, v in sorted(groups.items())]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("predictions", type=Path, nargs="+")
    ap.add_argument("--last", type=int, default=6, help="the last row pools this index and beyond (default 6)")
    args = ap.parse_args(argv)
    ds = load_dataset(args.dataset)
    for path in args.predictions:
        print(f"\n{path}\n| item | pairs | right id | unregistered distance: all, right id, wrong id | "
              f"residual after Kabsch |\n|---|---:|---:|---|---:|")
        for r in by_position(ds, read_predictions(path, ds.catalog), args.last):
            print(f"| {r['item']}{'+' if r['pooled'] else ''} | {r['pairs']} | {r['right_id']:.3f} | "
                  f"{r['distance']:.3f}, {r['distance_right']:.3f}, {r['distance_wrong']:.3f} | {r['residual']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
