"""Per-field scores of one generated answer: which part of an answer is wrong, beside the set score.

The answer's objects are matched to the ground truth's with the paper's matching (`metrics.match`: object
features first, then position), the very pairs `score_prediction` scores. Over the matched pairs:

- id: the pair names the same object id (per pair, so a one-object answer with the right id scores 1;
  `object_accuracy`, per ground-truth object, and the count error show what it left out);
- cell IoU (grid answers): |cells_pred & cells_true| / |cells_pred | cells_true| of the pair's cell sets,
  the true cells being the footprint the fine-tuning target lists (`answer_items`);
- direction (grid answers): the same one of the eight cardinal directions.

Unmatched objects are what the count error and the set score (`val/set_rmsd`) charge, not these.

Usage:
    counts = field_counts(items, placements, gt, catalog, grid, "grid")   # sums over the episode's pairs
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FieldCounts:
    """Sums over one episode's matched pairs (divide by `pairs`, pooled over episodes)."""

    pairs: int = 0
    id_correct: int = 0
    cell_iou: float = 0.0
    direction_correct: int = 0


def field_counts(items, placements, gt, catalog, grid, kind: str) -> FieldCounts:
    """Compare a parsed answer (`items`; None if it failed) and its placements with the ground truth `gt`.

    Args:
        items: the parsed AnswerItems (ids are unique within an answer) or None.
        placements: what `aggregate` made of them (the positions `score_prediction` matched).
        gt: the target Arrangement.
        catalog, grid: the dataset's catalog and the answers' grid.
        kind: "grid" (cells and direction compared) or "unmarked" (ids only).
    """
    from degusta_learn.metrics import match
    from degusta_learn.task.answer_format import answer_items

    if not items or not placements or not gt.placements:
        return FieldCounts()
    gi, pi = match(catalog, [p.object for p in gt.placements], [p.object for p in placements],
                   [(p.x, p.y) for p in gt.placements], [(p.x, p.y) for p in placements])
    said = {it.id: it for it in items}
    truth = answer_items(gt.placements, catalog, kind, grid) if kind == "grid" else None
    out = FieldCounts(pairs=len(gi))
    for g, p in zip(gi.tolist(), pi.tolist()):
        pred_id = placements[p].object
        out.id_correct += pred_id == gt.placements[g].object
        if truth is None:
            continue
        item = said.get(pred_id)
        cells = set(item.cells or []) if item is not None else set()
        true = set(truth[g].cells or [])
        out.cell_iou += len(cells & true) / len(cells | true) if cells | true else 1.0
        out.direction_correct += item is not None and item.direction == truth[g].direction
    return out
