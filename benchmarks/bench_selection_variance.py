"""How noisy is a choice made on the validation participants? (issue 53, item 3)

Given a per_episode.csv of `degusta evaluate` over several candidates' validation predictions (adapters, seeds,
decodings: the things one of which is shipped), this resamples the validation participants and counts how often
each candidate comes out best, for the whole validation set and for subsets of the size a training run validates
on (`data.val_episodes`, e.g. 16 or 32 episodes). A choice is noise where the winner changes under resampling.

Usage:
    degusta evaluate --dataset data/naturalistic --out runs/sel --predictions CAND1.jsonl CAND2.jsonl ...
    python benchmarks/bench_selection_variance.py runs/sel/per_episode.csv --metric set_rmsd --sizes 16 32 100
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict

import numpy as np


def load(path: str, metric: str, only: list[str] | None = None) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    """(methods, episodes, participant index per episode, scores[method, episode]) of the episodes every method has
    (`only`: just these methods)."""
    rows: dict[str, dict[str, float]] = defaultdict(dict)
    who: dict[str, str] = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if only and r["method"] not in only:
                continue
            value = r[metric]
            rows[r["method"]][r["episode"]] = float(value) if value not in ("", "nan") else np.nan
            who[r["episode"]] = r["participant"]
    methods = sorted(rows)
    episodes = sorted(set.intersection(*(set(v) for v in rows.values())))
    people = sorted({who[e] for e in episodes})
    index = np.array([people.index(who[e]) for e in episodes])
    scores = np.array([[rows[m][e] for e in episodes] for m in methods])
    return methods, episodes, index, scores


def win_rates(scores: np.ndarray, person: np.ndarray, size: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Share of `n` draws each method is best (lowest mean) on: participants resampled with replacement, then
    `size` of their episodes drawn (all of them when size >= the episodes drawn)."""
    people = np.unique(person)
    by_person = [np.flatnonzero(person == p) for p in people]
    wins = np.zeros(scores.shape[0])
    for _ in range(n):
        chosen = np.concatenate([by_person[i] for i in rng.choice(len(people), len(people))])
        if size < len(chosen):
            chosen = rng.choice(chosen, size, replace=False)
        means = np.nanmean(scores[:, chosen], axis=1)
        wins[int(np.nanargmin(means))] += 1
    return wins / n


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("per_episode", help="per_episode.csv of degusta evaluate over the candidates' val predictions")
    ap.add_argument("--metric", default="set_rmsd", help="the per-episode column chosen on (lower is better)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 100], help="validation episodes per choice")
    ap.add_argument("--n", type=int, default=2000, help="resamples")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="+", default=None, help="the candidates (method names of the csv); default: all")
    args = ap.parse_args(argv)
    methods, episodes, person, scores = load(args.per_episode, args.metric, args.only)
    rng = np.random.default_rng(args.seed)
    full = np.nanmean(scores, axis=1)
    print(f"{len(methods)} candidates, {len(episodes)} validation episodes of {len(np.unique(person))} participants; "
          f"{args.metric}, lower is better; {args.n} resamples")
    header = f"| candidate | {args.metric} (all) | " + " | ".join(f"P(best), {s} ep." for s in args.sizes) + " |"
    print(header)
    print("|---|---:|" + "---:|" * len(args.sizes))
    rates = [win_rates(scores, person, s, args.n, rng) for s in args.sizes]
    for i in np.argsort(full):
        print(f"| {methods[i]} | {full[i]:.4f} | " + " | ".join(f"{r[i]:.2f}" for r in rates) + " |")


if __name__ == "__main__":
    main()
