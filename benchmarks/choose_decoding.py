"""Choose a decoding on the validation participants, then score only that one on the test episodes.

A fine-tune's answers to the same prompts can become one plan in the ways `degusta predict` offers
(`task/aggregate.py`): the greedy answer alone (`n: 1, temperature: 0`), the paper's per-step modes of the samples
(`steps`), and the greedy answer lengthened by the samples' votes, every object placed from every answer naming it
(`greedy_votes_pooled`). One `degusta predict` run with `aggregation: greedy_votes_pooled` stores everything they
need per episode (the n sampled answers in `diagnostics.responses`, the greedy one in
`diagnostics.greedy_response`), so every way is scored from the same answers here, without asking the model
again.

It chooses on the validation participants only (`--split val`: the last weights, `adapter/`, of runs without
early stopping may be predicted there; docs/finetune.md, the leakage guard), by `--by` (default: the set-aware
score, which no short answer games), and `--samples` chooses n the same way. `--split test` is refused unless
`--only` names the way already chosen: the test participants give the final number of a frozen choice, looked at
once (docs/metrics.md, "Protocol: validation for choices, test once"). The usual final number is `degusta
predict --set split=test` with the chosen `decoding.aggregation` and `degusta evaluate`, whose report names the
split and the choices the predictions were made with; `--only` scores it here from the same stored answers. Several
files (one per training seed, the same episodes) add a row of each episode's mean over the seeds, which the paired
tests against `population_mean` use (nan where no seed matched an object).

Usage:
    degusta predict --config configs/predict_hf_base_finetuned.yaml --set split=val \\
        --set model.adapter=RUN/adapter --set out=OUT/val_s0.jsonl              # one per seed
    python benchmarks/choose_decoding.py --dataset data/naturalistic --split val OUT/val_s0.jsonl OUT/val_s1.jsonl
    python benchmarks/choose_decoding.py ... --split val --samples 5 VAL_n9_s0.jsonl   # n = 5 from a run with n = 9
    # once every choice is frozen, the chosen way alone on the test participants (one look):
    python benchmarks/choose_decoding.py --dataset data/naturalistic --split test --only steps TEST_s0.jsonl ...
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

METRICS = ("object_accuracy", "rmsd", "set_rmsd", "count_error", "n_pred")
WAYS = ("greedy", "steps", "greedy_votes_pooled")
"""The aggregations `decodings` scores, in its order."""
LOWER_IS_BETTER = {"rmsd": True, "set_rmsd": True, "count_error": True, "object_accuracy": False}


def parsed(text, catalog, grid):
    """The items of one stored answer, or None when it is missing or does not parse (as predict reads it)."""
    from degusta_learn.task.answers import AnswerParseError, read_answer

    if not isinstance(text, str):
        return None
    try:
        return read_answer(text, "grid", catalog, grid).items
    except AnswerParseError:
        return None


def decodings(prediction, catalog, grid, samples: int | None = None) -> dict[str, list]:
    """Every way's placements for one prediction of a greedy_votes_pooled run; `samples`: from its first that many
    sampled answers only (what a run with that `n` would have combined: predict samples answer i with the same seed
    whatever n is), all of them when None."""
    from degusta_learn.task.aggregate import aggregate, anchored_votes

    diag = prediction.diagnostics or {}
    stored = diag.get("responses") or []
    if samples is not None and len(stored) < samples:
        raise SystemExit(f"error: episode {prediction.episode}: {len(stored)} sampled answers stored, --samples "
                         f"{samples} asked (predict with n >= {samples})")
    answers = [parsed(t, catalog, grid) for t in stored[:samples]]
    greedy = parsed(diag.get("greedy_response"), catalog, grid)
    if not answers or "greedy_response" not in diag:
        raise SystemExit(f"error: episode {prediction.episode}: no stored answers (predict with n > 1 and "
                         "aggregation: greedy_votes_pooled)")
    return {
        "greedy": anchored_votes(greedy, [], "grid", grid)[0] if greedy is not None else [],
        "steps": aggregate(answers, "grid", grid)[0],
        "greedy_votes_pooled": anchored_votes(greedy, answers, "grid", grid)[0],
    }


def refuse_choosing_on_test(split: str, only: str | None) -> None:
    """Exit with one line when the run would choose (no `--only`) on participants that hold the test split."""
    from degusta_learn.errors import DegustaError
    from degusta_learn.training.protocol import refuse_test_split

    if only is not None:  # scoring the way chosen on validation: the final number, not a choice
        return
    try:
        refuse_test_split(split, "--split", "choosing a decoding")
    except DegustaError as e:
        raise SystemExit(f"error: {e}; choose with --split val, then score the chosen way with --only WAY") from None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("predictions", nargs="+", help="greedy_votes_pooled predictions, one file per training seed")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--split", required=True, choices=["val", "test"],
                    help="val: choose; test: only with --only, the final number of the way chosen on val")
    ap.add_argument("--context", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0, help="the participant split seed (the training run's)")
    ap.add_argument("--only", choices=WAYS, help="score this way alone (the one chosen on the validation participants)")
    ap.add_argument("--by", default="set_rmsd", choices=sorted(LOWER_IS_BETTER), help="the score that chooses")
    ap.add_argument("--samples", type=int, default=None, help="combine each episode's first K sampled answers only "
                    "(choose n from one run with more; default: all stored)")
    ap.add_argument("--rows", type=int, default=8)
    ap.add_argument("--cols", type=int, default=8)
    args = ap.parse_args()
    if args.samples is not None and args.samples < 1:
        ap.error(f"--samples {args.samples}: give at least 1")
    refuse_choosing_on_test(args.split, args.only)

    from degusta_learn.methods import get_method
    from degusta_learn.metrics import paired_bootstrap, score_many
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset, make_episodes, read_predictions

    ds, grid = load_dataset(args.dataset), Grid(args.rows, args.cols)
    episodes = make_episodes(ds, args.context, args.split, args.seed)
    order = [e.id for e in episodes]
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    spec = get_method("population_mean")
    pop = {p.episode: p for p in spec.run(spec.config_cls(method="population_mean", dataset=args.dataset, out="",
                                                          split=args.split), ds, episodes)}

    def scores(preds) -> dict[str, np.ndarray]:
        return {k: np.array([getattr(s, k) for s in score_many(ds.catalog, gts, preds)], float) for k in METRICS}

    runs = []  # per file: way -> metric -> per-episode values
    for path in args.predictions:
        by = {p.episode: p for p in read_predictions(path, ds.catalog)}
        missing = [i for i in order if i not in by]
        if missing:
            raise SystemExit(f"error: {path} lacks {len(missing)} of the {len(order)} {args.split} episodes "
                             f"(context {args.context}, seed {args.seed}; first: {missing[0]})")
        ways = {e.id: decodings(by[e.id], ds.catalog, grid, args.samples) for e in episodes}
        names = [args.only] if args.only else WAYS
        runs.append({w: scores([dataclasses.replace(by[i], placements=ways[i][w]) for i in order]) for w in names})
    base = scores([pop[i] for i in order])
    mean = {w: {k: np.nanmean([r[w][k] for r in runs], axis=0) for k in METRICS} for w in runs[0]}

    print(f"{len(order)} {args.split} episodes (context {args.context}), {len(runs)} file(s); population_mean: "
          + ", ".join(f"{k} {np.nanmean(base[k]):.3f}" for k in METRICS if k != "n_pred"))
    if args.split == "test":
        print(f"test participants: the final number of {args.only}, chosen on the validation participants (one look)")
    print("\n| decoding | object accuracy | Kabsch RMSD (paper) | set RMSD | count error | objects / answer | "
          "Kabsch vs population_mean (p) | set RMSD vs population_mean (p) | per file: object acc. / Kabsch |")
    print("|---|---|---|---|---|---|---|---|---|")
    for w, c in mean.items():
        cells = " | ".join(f"{np.nanmean(c[k]):.{2 if k == 'n_pred' else 3}f}" for k in METRICS)
        vs = " | ".join(f"{t['diff']:+.4f} [{t['lo']:+.4f}, {t['hi']:+.4f}] (p {t['p_value']:.4f})"
                        for t in (paired_bootstrap(c[k], base[k], n_resamples=10_000) for k in ("rmsd", "set_rmsd")))
        per = ", ".join(f"{np.nanmean(r[w]['object_accuracy']):.3f} / {np.nanmean(r[w]['rmsd']):.3f}" for r in runs)
        print(f"| {w} | {cells} | {vs} | {per} |")
    if not args.only:
        sign = 1 if LOWER_IS_BETTER[args.by] else -1
        best = min(mean, key=lambda w: sign * np.nanmean(mean[w][args.by]))
        print(f"\nchosen by {args.by} (mean over the files): {best}")


if __name__ == "__main__":
    main()
