"""What each shortcut does to each column: a method's answers transformed, scored, and set beside the original.

A shortcut is a change to a method's answers that needs no knowledge of the table: keep only the first k
objects, pad with random extra objects, name the whole catalog, give everyone the same answer, reverse the
placement order, turn every object to 0 degrees, shift the whole arrangement. For 3 baselines on the
naturalistic test split (context 4) this script scores every transformation with `score_predictions` and
`summarize` (what `degusta compare` runs) and prints one Markdown table per baseline: rows = transformation,
cells = transformed minus original for every summary column, bold where a paper's column (marked "(paper)")
improves, with the degeneracy reasons the transformed answers get and whether `rank_methods` still puts the
original first. The transformations are the ones tests/test_shortcuts.py checks (it imports them from here).

Usage:
    python benchmarks/bench_shortcuts.py                 # ~30 s on a free core
    python benchmarks/bench_shortcuts.py --context 2 --methods consensus
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, set before numpy is imported

import argparse  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

from degusta_learn.evaluate.scoring import EpisodeRow, score_predictions  # noqa: E402
from degusta_learn.evaluate.summary import rank_methods, summarize  # noqa: E402
from degusta_learn.methods import get_method  # noqa: E402
from degusta_learn.metrics import score_many  # noqa: E402
from degusta_learn.scene import Dataset, Episode, Placement, Prediction, load_dataset, make_episodes  # noqa: E402

Shortcut = Callable[[list[Prediction], Dataset], list[Prediction]]
"""A transformation of one method's predictions (one per episode, same order) -> new predictions."""


def _each(preds: list[Prediction], fn: Callable[[Prediction, np.random.Generator], list[Placement]],
          seed: int = 0) -> list[Prediction]:
    """`fn` applied to the placements of every answered prediction; failed ones stay failed (nothing to change)."""
    rng = np.random.default_rng(seed)
    return [p if p.failed or not p.placements else replace(p, placements=fn(p, rng), diagnostics={})
            for p in preds]


def _random_placements(ds: Dataset, pred: Prediction, objects: list[int], rng) -> list[Placement]:
    """`objects` at uniform random spots inside the target table's surface bounds, uniform random rotations."""
    x0, y0, x1, y1 = ds.tables[ds.arrangement(pred.participant, pred.target).table].bounds
    xy = rng.uniform([x0, y0], [x1, y1], size=(len(objects), 2))
    return [Placement(int(o), float(x), float(y), float(r))
            for o, (x, y), r in zip(objects, xy, rng.uniform(0, 360, len(objects)))]


def truncate(k: int) -> Shortcut:
    """Keep the first k objects of each answer."""
    return lambda preds, ds: _each(preds, lambda p, rng: list(p.placements[:k]))


def pad(extra: int | None = None, seed: int = 0) -> Shortcut:
    """Add `extra` random catalog objects absent from the answer at random spots (None: as many as the answer has)."""
    def apply(preds, ds):
        def fn(p, rng):
            absent = sorted(set(ds.catalog.ids) - {q.object for q in p.placements})
            n = min(len(p.placements) if extra is None else extra, len(absent))
            return [*p.placements, *_random_placements(ds, p, rng.choice(absent, n, replace=False).tolist(), rng)]
        return _each(preds, fn, seed)
    return apply


def whole_catalog(seed: int = 0) -> Shortcut:
    """The answer plus every other catalog object at a random spot: every true object is named."""
    def apply(preds, ds):
        def fn(p, rng):
            absent = [o for o in ds.catalog.ids if o not in {q.object for q in p.placements}]
            return [*p.placements, *_random_placements(ds, p, absent, rng)]
        return _each(preds, fn, seed)
    return apply


def constant(answer: list[Placement]) -> Shortcut:
    """The same answer for every episode (failed ones included: a constant answer never fails)."""
    return lambda preds, ds: [replace(p, placements=list(answer), failed=False, diagnostics={}) for p in preds]


def first_answer(preds: list[Prediction]) -> list[Placement]:
    """The method's first non-empty answer (what "constant (first answer)" gives everyone)."""
    return list(next(p.placements for p in preds if not p.failed and p.placements))


def best_constant(ds: Dataset, episodes: list[Episode]) -> list[Placement]:
    """Of the episodes' own ground-truth arrangements, the one that scores the lowest mean set RMSD when given to
    every episode: the best any constant answer drawn from the data can do (it peeks at the test split)."""
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    tables = ds.tables
    best, best_score = None, np.inf
    for cand in gts:
        scores = score_many(ds.catalog, gts, [list(cand.placements)] * len(gts), tables=tables)
        mean = float(np.mean([s.set_rmsd for s in scores]))
        if mean < best_score:
            best, best_score = cand, mean
    return list(best.placements)


def reverse_order() -> Shortcut:
    """The answer's placement order reversed (same objects, same spots)."""
    return lambda preds, ds: _each(preds, lambda p, rng: list(p.placements[::-1]))


def zero_rotations() -> Shortcut:
    """Every object turned to 0 degrees (same objects, same spots, same order)."""
    return lambda preds, ds: _each(preds, lambda p, rng: [replace(q, rotation=0.0) for q in p.placements])


def shift_x(dx: float = 0.1) -> Shortcut:
    """The whole arrangement moved by `dx` along x: what set RMSD (registered) forgives and its unregistered twin
    does not. Not a shortcut: it shows what each set score can see."""
    return lambda preds, ds: _each(preds, lambda p, rng: [replace(q, x=q.x + dx) for q in p.placements])


def shortcuts(ds: Dataset, episodes: list[Episode], preds: list[Prediction],
              best: list[Placement] | None = None) -> dict[str, Shortcut]:
    """Every transformation of the table, by row name (`best`: best_constant's answer, computed if None)."""
    best = best_constant(ds, episodes) if best is None else best
    return {"truncate to 1": truncate(1), "truncate to 2": truncate(2), "truncate to 3": truncate(3),
            "pad +1": pad(1), "pad x2": pad(None), "whole catalog": whole_catalog(),
            "constant (first answer)": constant(first_answer(preds)), "constant (best table)": constant(best),
            "reverse order": reverse_order(), "rotations 0": zero_rotations(), "shift +0.1 x": shift_x(0.1)}


def transformed_rows(ds: Dataset, episodes: list[Episode], preds: list[Prediction], method: str,
                     table: dict[str, Shortcut]) -> list[EpisodeRow]:
    """Rows of the original (named `method`) and of each transformation (named by its key), original first."""
    by_id = {e.id: e for e in episodes}
    rows = score_predictions(ds, [replace(p, method=method) for p in preds], by_id)
    for name, shortcut in table.items():
        rows += score_predictions(ds, [replace(p, method=name) for p in shortcut(preds, ds)], by_id)
    return rows


# (summary key, header, digits, better: +1 higher, -1 lower, 0 nearer 0, marked when it improves: the ranking
# score and the paper's columns)
COLUMNS = (("set_rmsd", "set RMSD", 3, -1, True), ("set_rmsd_unregistered", "set RMSD (unreg.)", 3, -1, False),
           ("object_accuracy", "object acc. (paper)", 3, 1, True), ("object_precision", "precision", 3, 1, False),
           ("object_f1", "F1", 3, 1, False), ("rmsd", "Kabsch RMSD (paper)", 3, -1, True),
           ("acc@0.05 paper", "acc@0.05 (paper)", 3, 1, True), ("acc@0.05", "acc@0.05 (like for like)", 3, 1, True),
           ("count_bias", "count bias", 2, 0, False),
           ("order_tau", "order τ", 3, 1, False), ("rotation_error", "rotation error (°)", 1, -1, False))


def _value(s: dict, key: str) -> float | None:
    if key == "acc@0.05 paper":
        return s["acceptable_at_paper"]["0.05"]
    if key == "acc@0.05":
        return s["acceptable_at"]["0.05"]
    return (s.get(key) or {}).get("mean")


def _delta(orig: float | None, new: float | None, digits: int, better: int, marked: bool) -> str:
    if orig is None or new is None:
        return "-"
    d = new - orig
    cell = f"{d:+.{digits}f}"
    if round(d, digits) == 0:
        return f"{0:.{digits}f}"
    improves = abs(new) < abs(orig) if better == 0 else d * better > 0
    return f"**{cell}**" if improves and marked else cell


def delta_table(summary: dict[str, dict], method: str) -> list[str]:
    """The Markdown table of one method: original values, then transformed minus original per row."""
    order = rank_methods(summary)
    head = "| transformation | " + " | ".join(c[1] for c in COLUMNS) + " | degenerate | rank |"
    lines = [head, "|---|" + "---:|" * len(COLUMNS) + "---|---:|"]
    orig = summary[method]

    def shown(v, digits):
        return "-" if v is None else f"{v:.{digits}f}"

    lines.append(f"| {method} (original) | " + " | ".join(shown(_value(orig, c[0]), c[2]) for c in COLUMNS)
                 + f" | {', '.join(orig['degenerate_reasons']) or '-'} | {order.index(method) + 1} |")
    for name, s in summary.items():
        if name == method:
            continue
        cells = [_delta(_value(orig, key), _value(s, key), digits, better, marked)
                 for key, _, digits, better, marked in COLUMNS]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {', '.join(s['degenerate_reasons']) or '-'} | "
                     f"{order.index(name) + 1} |")
    return lines


def run_method(name: str, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    spec = get_method(name)
    return spec.run(spec.config_cls(method=name, dataset=str(ds.root), out="", seed=0), ds, episodes)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="data/naturalistic")
    parser.add_argument("--context", type=int, default=4)
    parser.add_argument("--methods", nargs="+", default=["consensus", "copy_nearest", "population_mean"])
    parser.add_argument("--bootstrap", type=int, default=200, help="resamples per interval (only means are shown)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    ds = load_dataset(args.dataset)
    episodes = make_episodes(ds, args.context, "test", 0)
    best = best_constant(ds, episodes)
    print(f"{ds.label}, test split, context {args.context}: {len(episodes)} episodes, "
          f"{len({e.participant for e in episodes})} participants. Cells: transformed minus original; bold: set "
          "RMSD (the ranking score) or a paper's column improves. rank: place among the original and its "
          "transformations (summary.rank_methods: degenerate last).\n")
    for method in args.methods:
        preds = run_method(method, ds, episodes)
        rows = transformed_rows(ds, episodes, preds, method, shortcuts(ds, episodes, preds, best))
        summary = summarize(rows, n_bootstrap=args.bootstrap)
        summary = {m: summary[m] for m in dict.fromkeys(r.method for r in rows)}  # rows' order: original first
        print(f"### {method}\n")
        print("\n".join(delta_table(summary, method)), end="\n\n")
    print(f"({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
