"""Where do a VLM's answers go wrong? Ids, types and counts of its predictions, constrained and free.

For each predictions file (`degusta predict` / `benchmarks/bench_vlm.py` output of the `hf` backend) on its
episodes, beside the paper's object accuracy and the set-aware score:

- **ids seen in context**: the share of predicted objects that appear in one of the episode's context tables
  (a model that copies what it sees names ids from there), next to the same share of the ground truth's objects;
- **type recall**: the share of ground-truth objects whose type the answer has (types as multisets), so an
  answer can be right about *what kind* of objects a person sets while naming the wrong ones;
- **repeat stops**: answers the constrained decoder ended where the model named an object again
  (`vlm/constrain.py`, decoding `on_repeat: stop`; with skip, the default, none);
- the same scores for the **free** answers (the unconstrained decoding the backend records where the grammar
  changed an answer; elsewhere the two are the same), read by the toolkit's parser, which drops an item that
  names an object again: do the constrained answers lose objects the model would have placed?

Usage:
    python benchmarks/analyze_answers.py --dataset data/naturalistic --episodes RUN/episodes.jsonl \\
        RUN/predictions/tiny_vlm_lora.jsonl RUN/predictions/tiny_vlm_full.jsonl
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np


def free_placements(prediction, kind: str, catalog, grid):
    """The placements of the free answer (the kept one where the grammar changed nothing, so none was recorded);
    None if unreadable."""
    from degusta_learn.prompting.aggregate import aggregate
    from degusta_learn.prompting.answers import AnswerParseError, read_answer

    d = prediction.diagnostics or {}
    kept = d.get("responses") or []
    free = (d.get("decoding") or {}).get("free_responses") or []
    # a null free answer: the grammar changed nothing, the free answer is the kept one
    texts = [f if f is not None else k for f, k in zip(free, kept)] if free else kept
    if not texts:
        return None if prediction.failed else list(prediction.placements)
    try:
        placements, _ = aggregate([read_answer(texts[0], kind, catalog, grid).items], kind, grid)
    except AnswerParseError:
        return None
    return placements


def analyze(ds, episodes: dict, predictions, grid) -> dict:
    """Mean scores of the kept and the free answers, and the id / type / repeat diagnostics."""
    from degusta_learn.metrics.scores import score_prediction
    from degusta_learn.prompting.answers import answer_kind

    catalog = ds.catalog
    types = lambda ids: Counter(catalog[i].type for i in ids)  # noqa: E731
    kept, free = [], []
    pred_in_ctx = gt_in_ctx = n_pred = n_gt = type_hits = repeats = 0
    for p in predictions:
        ep = episodes[p.episode]
        gt = ds.arrangement(p.participant, p.target)
        context = {q.object for t in ep.context for q in ds.arrangement(p.participant, t).placements}
        ids = [q.object for q in p.placements]
        gt_ids = [q.object for q in gt.placements]
        pred_in_ctx += sum(i in context for i in ids)
        gt_in_ctx += sum(i in context for i in gt_ids)
        n_pred, n_gt = n_pred + len(ids), n_gt + len(gt_ids)
        type_hits += sum((types(ids) & types(gt_ids)).values())
        repeats += bool(((p.diagnostics or {}).get("decoding") or {}).get("repeat_stops"))
        kept.append(score_prediction(catalog, gt, p.placements, p.failed))
        fp = free_placements(p, answer_kind(p.method), catalog, grid)
        free.append(score_prediction(catalog, gt, fp or [], fp is None))

    def means(scores) -> dict:
        m = lambda key: float(np.nanmean([getattr(s, key) for s in scores]))  # noqa: E731
        return {k: m(k) for k in ("object_accuracy", "set_rmsd", "count_error", "n_pred")}

    return {"episodes": len(predictions), "kept": means(kept), "free": means(free),
            "pred_ids_in_context": pred_in_ctx / max(n_pred, 1), "gt_ids_in_context": gt_in_ctx / max(n_gt, 1),
            "type_recall": type_hits / max(n_gt, 1), "repeat_stops": repeats}


def _name(path: Path) -> str:
    """A predictions file's row name: RUN/predictions/METHOD.jsonl -> RUN/METHOD (bench_vlm's layout)."""
    return f"{path.parent.parent.name}/{path.stem}" if path.parent.name == "predictions" else path.stem


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("predictions", type=Path, nargs="+", help="predictions.jsonl files of one episode set")
    ap.add_argument("--dataset", required=True, type=Path)
    ap.add_argument("--episodes", required=True, type=Path, help="the episodes.jsonl the predictions answer")
    ap.add_argument("--grid", type=int, default=8, help="cells per side of the grid answers")
    args = ap.parse_args(argv)

    from degusta_learn.errors import DegustaError
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene.dataset import load_dataset
    from degusta_learn.scene.episodes import read_episodes
    from degusta_learn.scene.predictions import read_predictions

    try:
        ds = load_dataset(args.dataset)
        episodes = {e.id: e for e in read_episodes(args.episodes, ds)}
        grid = Grid(args.grid, args.grid)
        rows = [(_name(path), analyze(ds, episodes, read_predictions(path, ds.catalog, episodes), grid))
                for path in args.predictions]
    except DegustaError as e:
        raise SystemExit(f"analyze_answers: {e}") from None
    print("| predictions | episodes | object accuracy (kept / free) | set RMSD (kept / free) | objects / answer "
          "(kept / free) | count error (kept) | ids seen in context (pred / truth) | type recall | repeat stops |")
    print("|---|---:|---|---|---|---:|---|---:|---:|")
    for name, r in rows:
        k, f = r["kept"], r["free"]
        print(f"| {name} | {r['episodes']} | {k['object_accuracy']:.3f} / {f['object_accuracy']:.3f} | "
              f"{k['set_rmsd']:.3f} / {f['set_rmsd']:.3f} | {k['n_pred']:.1f} / {f['n_pred']:.1f} | "
              f"{k['count_error']:.2f} | {r['pred_ids_in_context']:.2f} / {r['gt_ids_in_context']:.2f} | "
              f"{r['type_recall']:.2f} | {r['repeat_stops']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
