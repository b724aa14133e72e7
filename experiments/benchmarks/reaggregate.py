"""Sampled answers, combined three ways: does sampling fix a fine-tune's short lists? (docs/tiny_base.md point 35)

Reads the answers a sampled `degusta predict` run stored (`n` > 1: each prediction's `diagnostics.responses`)
and scores three ways of turning them into one plan, each paired against a greedy run of the same model on the
same episodes and against `population_mean`:

- **steps**: the paper's aggregation, what predict wrote (`prompting.aggregate.aggregate`: the mode length,
  per step the mode type and id);
- **votes**: predict's `aggregation: votes` (`prompting.aggregate.aggregate_votes`): objects ranked by how many
  answers name them (ties: the earlier mean step), as many as the median answer's length, each at the weighted
  mean of its cells over those answers, ordered by their mean step (the numbers of points 35 and 37 were measured
  with this script's own copy, which took at least one object where most answers were empty; predict's gives none
  then, as the paper's aggregation does);
- **greedy + votes**: the greedy answer's objects and places, lengthened to the sampled answers' median length by
  the best-voted objects it lacks (never shortened): the greedy answer's places, the samples' count
  (`prompting.aggregate.anchored_votes`, predict's `aggregation: greedy_votes`, here from two runs' files).

A research script for one question (can a decoding-side length fix the count error without losing Kabsch RMSD?);
two of its three ways became predict options (`votes`, `greedy_votes`; points 35, 37 and 39 record why).

Usage:
    degusta predict --config configs/predict_hf_base_finetuned.yaml --set model.adapter=RUN/adapter \\
        --set decoding.n=5 --set decoding.temperature=0.5 --set episodes=RUN/episodes.jsonl --set out=OUT/sampled.jsonl
    python benchmarks/reaggregate.py --dataset data/naturalistic --episodes RUN/episodes.jsonl \\
        --greedy RUN/predictions/tiny_vlm_lora.jsonl --sampled OUT/sampled.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

METRICS = ("object_accuracy", "rmsd", "set_rmsd", "count_error", "n_pred")


def parsed_answers(prediction, catalog, grid) -> list[list]:
    """The items of each stored answer that parses (an item naming an object again is dropped, as predict does)."""
    from degusta_learn.prompting.answers import AnswerParseError, read_answer

    out = []
    for text in (prediction.diagnostics or {}).get("responses") or []:
        if not isinstance(text, str):  # a failed sample
            continue
        try:
            out.append(read_answer(text, "grid", catalog, grid).items)
        except AnswerParseError:
            continue
    return out


def median_length(answers: list[list]) -> int:
    """The median of the answers' lengths, rounded (the samples' count; at least 1: fixed_length.py's grammar
    length)."""
    return max(1, int(round(np.median([len(a) for a in answers]))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--episodes", required=True, help="the episodes both runs answered (bench_vlm's episodes.jsonl)")
    ap.add_argument("--greedy", required=True, help="predictions of the model decoded greedily (n 1)")
    ap.add_argument("--sampled", required=True, help="predictions of the same model with n > 1 sampled answers")
    ap.add_argument("--extra", action="append", default=[], metavar="NAME=PATH",
                    help="another predictions file of the same episodes, scored as a row (repeatable)")
    ap.add_argument("--rows", type=int, default=8, help="grid rows (the answers' grid)")
    ap.add_argument("--cols", type=int, default=8)
    args = ap.parse_args()

    from degusta_learn.methods import get_method
    from degusta_learn.metrics import paired_bootstrap, score_many
    from degusta_learn.prompting.aggregate import aggregate_votes, anchored_votes
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset, read_episodes, read_predictions

    ds, grid = load_dataset(args.dataset), Grid(args.rows, args.cols)
    episodes = read_episodes(args.episodes)
    order = [e.id for e in episodes]
    greedy = {p.episode: p for p in read_predictions(args.greedy, ds.catalog)}
    sampled = {p.episode: p for p in read_predictions(args.sampled, ds.catalog)}
    missing = [i for i in order if i not in greedy or i not in sampled]
    if missing:
        raise SystemExit(f"error: {len(missing)} episodes of {args.episodes} lack a prediction (first: {missing[0]})")
    spec = get_method("population_mean")
    pop = {p.episode: p for p in spec.run(spec.config_cls(method="population_mean", dataset=args.dataset, out="",
                                                          split="test"), ds, episodes)}
    answers = {i: parsed_answers(sampled[i], ds.catalog, grid) for i in order}
    rows = {
        "greedy (n 1)": [greedy[i] for i in order],
        "steps (the paper's, as predicted)": [sampled[i] for i in order],
        "votes": [dataclasses.replace(sampled[i], placements=aggregate_votes(answers[i], "grid", grid)[0])
                  for i in order],
        "greedy + votes": [dataclasses.replace(greedy[i], placements=anchored_votes(
            (parsed_answers(greedy[i], ds.catalog, grid) or [None])[0], answers[i], "grid", grid)[0])
            for i in order],
    }
    for extra in args.extra:
        name, _, path = extra.partition("=")
        by = {p.episode: p for p in read_predictions(path, ds.catalog)}
        if any(i not in by for i in order):
            raise SystemExit(f"error: {path} lacks predictions of some of the episodes")
        rows[name] = [by[i] for i in order]
    rows["population_mean"] = [pop[i] for i in order]
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    cols = {name: {k: np.array([getattr(s, k) for s in score_many(ds.catalog, gts, preds)], float) for k in METRICS}
            for name, preds in rows.items()}
    print(f"\n{len(order)} episodes; sampled answers that parse, per episode: "
          f"{np.mean([len(a) for a in answers.values()]):.2f}")
    truth = np.array([len(gt.placements) for gt in gts], float)
    contexts = np.array([np.median([len(ds.arrangement(e.participant, t).placements) for t in e.context])
                         for e in episodes], float)
    lengths = {"greedy answer": np.array([len(greedy[i].placements) for i in order], float),
               "sampled answers' median": np.array([np.median([len(a) for a in answers[i]]) if answers[i] else 0
                                                    for i in order], float)}

    def r(a, b) -> float:  # nan where one side is constant (a few episodes)
        return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else float("nan")

    for name, n in lengths.items():  # does the length follow the person's count? (the contexts' median: a prior)
        print(f"length of the {name}: mean {n.mean():.2f} (truth {truth.mean():.2f}), correlation with the truth's "
              f"count {r(n, truth):.2f}, with the contexts' median count {r(n, contexts):.2f}")
    print(f"the contexts' median count itself: correlation with the truth's {r(contexts, truth):.2f}\n")
    print("| decoding | object accuracy | Kabsch RMSD (paper) | set RMSD | count error | objects / answer | "
          "vs greedy: object acc., count, set RMSD (p) | vs population_mean: Kabsch, set RMSD (p) |")
    print("|---|---|---|---|---|---|---|---|")
    fmt = lambda t: f"{t['diff']:+.3f} (p {t['p_value']:.3f})"  # noqa: E731
    for name, c in cols.items():
        g, p = cols["greedy (n 1)"], cols["population_mean"]
        vs_greedy = ", ".join(fmt(paired_bootstrap(c[k], g[k])) for k in ("object_accuracy", "count_error", "set_rmsd"))
        vs_pop = ", ".join(fmt(paired_bootstrap(c[k], p[k])) for k in ("rmsd", "set_rmsd"))
        means = " | ".join(f"{np.nanmean(c[k]):.3f}" if k != "n_pred" else f"{np.nanmean(c[k]):.2f}" for k in METRICS)
        print(f"| {name} | {means} | {vs_greedy} | {vs_pop} |")


if __name__ == "__main__":
    main()
