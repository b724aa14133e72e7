"""Per-episode scores: object accuracy, Kabsch RMSD, unregistered RMSD, count error and set RMSD.

- object_accuracy: fraction of ground-truth objects whose matched prediction is exactly the same object
  id; unmatched ground-truth objects count as wrong (nan only for an empty ground truth).
- rmsd: Kabsch RMSD over the matched pairs (see kabsch.py). It alone rewards predicting one or two
  objects (N = 1 gives 0), which is why the next three stand beside it.
- rmsd_unregistered: RMSD over the matched pairs without any alignment.
- count_error: |len(pred) - len(gt)|.
- set_rmsd: the set-aware score (set_score.py): an OSPA distance with penalty c = SET_PENALTY per
  unmatched object, on the same matching and Kabsch registration as rmsd; in [0, c].

A failed prediction counts as predicting nothing: accuracy 0, both RMSDs nan, n_pred 0, count_error
len(gt), set_rmsd c (every ground-truth object unmatched). An empty prediction scores the same. An
empty ground truth gives nan accuracy and set_rmsd.

`score_many` is the fast path for whole prediction files: it groups episodes by (len(gt), len(pred)),
builds the cost matrices and RMSDs for each group in one vectorized step, and only loops for the
Hungarian solver. Both paths build the matching costs with the same function (bit for bit the same
matching); `score_prediction` then does the few-point arithmetic in plain Python, so its RMSDs may
differ from `score_many`'s in the last bits (~1e-16).

Usage:
    from degusta_learn.metrics import score_prediction, score_many
    s = score_prediction(ds.catalog, ds.arrangement(p, trial), prediction.placements, prediction.failed)
    scores = score_many(ds.catalog, gts, predictions)   # list[EpisodeScore], same order
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from degusta_learn.errors import DegustaError
from degusta_learn.metrics.kabsch import kabsch_sq_residuals_batch, kabsch_sq_residuals_points
from degusta_learn.metrics.matching import as_complex, feature_table, match_costs
from degusta_learn.metrics.set_score import SET_PENALTY, set_rmsd_batch, set_rmsd_points
from degusta_learn.scene.catalog import Catalog
from degusta_learn.scene.types import Arrangement, Placement

NAN = float("nan")


@dataclass
class EpisodeScore:
    """The scores of one prediction against its ground truth."""

    object_accuracy: float  # fraction of GT objects matched to the same object id
    rmsd: float  # Kabsch RMSD over matched pairs (normalized image units); nan if none matched
    rmsd_unregistered: float  # RMSD over matched pairs without alignment
    count_error: int  # |n_pred - n_gt|
    n_matched: int  # min(n_gt, n_pred)
    n_gt: int
    n_pred: int  # 0 for a failed prediction
    set_rmsd: float  # OSPA-style: matched distances capped at c, c per unmatched object; in [0, c]


def _unpack(pred) -> tuple[Sequence[Placement], bool]:
    """(placements, failed) of a Prediction, a sequence of Placements, or None (failed)."""
    if pred is None:
        return (), True
    return getattr(pred, "placements", pred), bool(getattr(pred, "failed", False))


def _xy(placements: Sequence[Placement]) -> list[float]:
    return [c for p in placements for c in (p.x, p.y)]  # interleaved x0, y0, x1, y1, ...


def _trivial(n_gt: int, n_pred: int, failed: bool) -> EpisodeScore | None:
    """The score when nothing can be matched (failed, empty prediction or empty ground truth), else None."""
    if failed or n_pred == 0:
        return EpisodeScore(0.0, NAN, NAN, n_gt, 0, n_gt, 0, SET_PENALTY if n_gt else NAN)
    if n_gt == 0:
        return EpisodeScore(NAN, NAN, NAN, n_pred, 0, 0, n_pred, NAN)
    return None


def score_prediction(catalog: Catalog, gt: Arrangement, placements: Sequence[Placement],
                     failed: bool = False) -> EpisodeScore:
    """Score one prediction against its ground-truth arrangement.

    Args:
        catalog: the dataset's catalog (object features for matching).
        gt: the target arrangement.
        placements: the predicted placements (object ids may repeat).
        failed: the method failed on this episode (scored as predicting nothing).

    Returns:
        The EpisodeScore (see the module docstring for each field).

    Raises:
        DegustaError: an object id is not in the catalog.
    """
    placements, pred_failed = _unpack(placements)
    table = feature_table(catalog)
    g = table.rows_of([p.object for p in gt.placements], f"ground truth {gt.participant!r} trial {gt.trial}")
    n, m = len(g), len(placements)
    trivial = _trivial(n, m, failed or pred_failed)
    if trivial is not None:
        return trivial
    gi, pi, same, d2, sq = _match_one(table, g, gt, placements)
    k = len(gi)
    return EpisodeScore(sum(same) / n, math.sqrt(sum(sq) / k), math.sqrt(sum(d2) / k), abs(m - n), k, n, m,
                        set_rmsd_points(sq, n, m))


def _match_one(table, g, gt: Arrangement, placements: Sequence[Placement]):
    """(gt_idx, pred_idx, same object?, squared distances, squared residuals after Kabsch) of the matched pairs."""
    p = table.rows_of([q.object for q in placements], "prediction")
    gxy, pxy = _xy(gt.placements), _xy(placements)
    ham = table.hamming_between(np.array([g]), np.array([p]))  # (1, n, m)
    cost = match_costs(ham, np.array(gxy).view(np.complex128)[None], np.array(pxy).view(np.complex128)[None])
    gi, pi = (a.tolist() for a in linear_sum_assignment(cost[0]))
    a = [[gxy[2 * i], gxy[2 * i + 1]] for i in gi]  # matched positions, Python floats
    b = [[pxy[2 * j], pxy[2 * j + 1]] for j in pi]
    same = [bool(g[i] == p[j]) for i, j in zip(gi, pi)]  # same row <=> same object id
    d2 = [(u[0] - v[0]) ** 2 + (u[1] - v[1]) ** 2 for u, v in zip(a, b)]
    return gi, pi, same, d2, kabsch_sq_residuals_points(a, b)


@dataclass(frozen=True)
class MatchedPair:
    """One matched (ground-truth, predicted) object of an episode, as `score_prediction` matched it."""

    gt_index: int
    pred_index: int  # the item's place in the answer: 0 is the first object it names
    same_object: bool  # the predicted id is the ground truth's
    distance: float  # unregistered
    residual: float  # after the Kabsch registration of all the episode's matched pairs


def matched_pairs(catalog: Catalog, gt: Arrangement, placements: Sequence[Placement]) -> list[MatchedPair]:
    """The pairs behind an episode's scores, for per-object analyses (e.g. error by the item's place in the answer;
    benchmarks/by_position.py). An empty or failed prediction has none."""
    placements, failed = _unpack(placements)
    table = feature_table(catalog)
    g = table.rows_of([p.object for p in gt.placements], f"ground truth {gt.participant!r} trial {gt.trial}")
    if failed or not placements or not len(g):
        return []
    gi, pi, same, d2, sq = _match_one(table, g, gt, placements)
    return [MatchedPair(i, j, s, math.sqrt(d), math.sqrt(r)) for i, j, s, d, r in zip(gi, pi, same, d2, sq)]


def _score_group(table, g: np.ndarray, gxy: np.ndarray, p: np.ndarray, pxy: np.ndarray) -> list[EpisodeScore]:
    """Score E episodes sharing n = len(gt) > 0, m = len(pred) > 0: rows g (E, n), p (E, m); xy (E, n, 2)."""
    n_ep, n, m = g.shape[0], g.shape[1], p.shape[1]
    cost = match_costs(table.hamming_between(g, p), as_complex(gxy), as_complex(pxy))  # (E, n, m)
    k = min(n, m)
    gi, pi = np.empty((n_ep, k), dtype=np.int64), np.empty((n_ep, k), dtype=np.int64)
    for e in range(n_ep):
        gi[e], pi[e] = linear_sum_assignment(cost[e])
    rows = np.arange(n_ep)[:, None]  # (E, 1)
    correct = (g[rows, gi] == p[rows, pi]).sum(1)  # (E,)
    a, b = gxy[rows, gi], pxy[rows, pi]  # (E, k, 2) matched positions
    sq = kabsch_sq_residuals_batch(a, b)  # (E, k) registered squared distances
    rmsd = np.sqrt(sq.sum(1) / k).tolist()
    set_rmsd = set_rmsd_batch(sq, n, m).tolist()
    d = a - b
    unreg = np.sqrt((d * d).sum((1, 2)) / k).tolist()
    acc = (correct / n).tolist()
    return [EpisodeScore(acc[e], rmsd[e], unreg[e], abs(m - n), k, n, m, set_rmsd[e]) for e in range(n_ep)]


def score_many(catalog: Catalog, gts: Sequence[Arrangement], preds: Sequence) -> list[EpisodeScore]:
    """Score many predictions at once (vectorized; equal to calling `score_prediction` on each).

    Args:
        catalog: the dataset's catalog.
        gts: the ground-truth arrangements, one per episode.
        preds: one per episode, in the same order: a `Prediction` (its `placements` and `failed` are
            used), a sequence of `Placement`, or None (a failed prediction).

    Returns:
        One EpisodeScore per episode, in order.
    """
    if len(gts) != len(preds):
        raise DegustaError(f"score_many: {len(gts)} ground truths but {len(preds)} predictions")
    table = feature_table(catalog)
    out: list[EpisodeScore | None] = [None] * len(gts)
    groups: dict[tuple[int, int], tuple[list, list, list, list, list]] = {}
    for e, (gt, pred) in enumerate(zip(gts, preds)):
        placements, failed = _unpack(pred)
        g = table.rows_of([q.object for q in gt.placements], f"ground truth {gt.participant!r} trial {gt.trial}")
        out[e] = _trivial(len(g), len(placements), failed)
        if out[e] is None:
            p = table.rows_of([q.object for q in placements], f"prediction {e}")
            group = groups.setdefault((len(g), len(p)), ([], [], [], [], []))
            for lst, v in zip(group, (e, g, _xy(gt.placements), p, _xy(placements))):
                lst.append(v)
    for (n, m), (idx, g, gxy, p, pxy) in groups.items():
        scores = _score_group(table, np.array(g), np.array(gxy).reshape(-1, n, 2),
                              np.array(p), np.array(pxy).reshape(-1, m, 2))
        for e, s in zip(idx, scores):
            out[e] = s
    return out  # type: ignore[return-value]
