"""Per-episode scores: object accuracy, Kabsch RMSD, unregistered RMSD, count error and set RMSD.

- object_accuracy: fraction of ground-truth objects whose matched prediction is exactly the same object
  id; unmatched ground-truth objects count as wrong (nan only for an empty ground truth).
- rmsd: Kabsch RMSD over the matched pairs (see kabsch.py). It alone rewards predicting one or two
  objects (N = 1 gives 0), which is why the next three stand beside it.
- rmsd_unregistered: RMSD over the matched pairs without any alignment.
- count_error: |len(pred) - len(gt)|.
- set_rmsd: the set-aware score (set_score.py): an OSPA distance with penalty c = SET_PENALTY per
  unmatched object, on the same matching and Kabsch registration as rmsd; in [0, c].

The whole task plan (docs/metrics.md, "Task plan"):

- object_precision: same-id matches / predicted objects (object_accuracy is the recall); object_f1 =
  2 * same-id matches / (n_gt + n_pred), their harmonic mean.
- set_rmsd_unregistered: set_rmsd on the unregistered distances (where the objects are, not only the
  shape they make).
- order_tau: Kendall's tau between the true and predicted placement order of the matched pairs
  (plan.py); nan for fewer than two matched pairs.
- rotation_error, n_rotation_scored: mean rotation error (degrees) over the matched pairs whose shared
  symmetry leaves a rotation to score, modulo that symmetry (plan.py); nan when no pair is scored.
- off_table_rate, overlap_rate (with the episode's table: `tables` / `table`): the share of predicted
  centroids off the table surface and of pairs of predicted footprints that overlap
  (plausibility.py); gt_off_table_rate, gt_overlap_rate: the same for the ground truth (a reference).

A failed prediction counts as predicting nothing: accuracy, precision and F1 0 (a failure scores the
worst, so failing on hard episodes never raises a mean), both RMSDs nan, n_pred 0, count_error len(gt),
set_rmsd and set_rmsd_unregistered c (every ground-truth object unmatched), order_tau, rotation_error,
off_table_rate and overlap_rate nan (nothing placed to judge; the failure rate stands beside them). An
empty prediction scores the same. An empty ground truth gives nan accuracy and set RMSDs, precision and
F1 0 for a non-empty prediction.

Matching (`matching=`, matching.py `MATCHINGS`): "hungarian" (the default: minimum total Hamming distance,
ties to nearer positions) or "paper" (the paper's greedy rule: each ground-truth object in placement order takes
the least-Hamming prediction not yet taken). Every score above is taken on the pairs of the chosen rule;
`matched_pairs` lists them.

`score_many` is the fast path for whole prediction files: it groups episodes by (len(gt), len(pred)),
builds the cost matrices and RMSDs for each group in one vectorized step, and only loops for the
Hungarian solver (the greedy rule loops over ground-truth objects, vectorized over episodes). Both paths
match with the same function (`matching.assign`: bit for bit the same matching under either rule); `score_prediction` then does the few-point arithmetic in plain Python, so its RMSDs may
differ from `score_many`'s in the last bits (~1e-16).

Usage:
    from degusta_learn.metrics import score_prediction, score_many
    gt = ds.arrangement(p, trial)
    s = score_prediction(ds.catalog, gt, prediction.placements, prediction.failed, table=ds.tables[gt.table])
    scores = score_many(ds.catalog, gts, predictions, tables=ds.tables)   # list[EpisodeScore], same order
    paper = score_many(ds.catalog, gts, predictions, tables=ds.tables, matching="paper")
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from degusta_learn.errors import DegustaError
from degusta_learn.metrics.kabsch import kabsch_sq_residuals_batch, kabsch_sq_residuals_points
from degusta_learn.metrics.matching import as_complex, assign, check_matching, feature_table
from degusta_learn.metrics.plan import kendall_tau_batch, mean_rotation_error, pair_symmetry
from degusta_learn.metrics.plausibility import off_table_rates, overlap_rates
from degusta_learn.metrics.set_score import SET_PENALTY, set_rmsd_batch, set_rmsd_points
from degusta_learn.scene.catalog import Catalog
from degusta_learn.scene.tables import Table
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
    object_precision: float = NAN  # same-id matches / n_pred (0 for a failed or empty prediction)
    object_f1: float = NAN  # 2 * same-id matches / (n_gt + n_pred)
    set_rmsd_unregistered: float = NAN  # set_rmsd on unregistered distances (translation-sensitive)
    order_tau: float = NAN  # Kendall's tau of the matched pairs' placement orders; nan for < 2 pairs
    rotation_error: float = NAN  # degrees, modulo symmetry, mean over scored matched pairs; nan if none scored
    n_rotation_scored: int = 0  # matched pairs whose rotation is scored (not fully symmetric)
    off_table_rate: float = NAN  # predicted centroids off the table surface / n_pred (needs the table)
    overlap_rate: float = NAN  # overlapping pairs of predicted footprints / pairs; nan for n_pred < 2
    gt_off_table_rate: float = NAN  # the same two for the ground truth (reference)
    gt_overlap_rate: float = NAN


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
        c = SET_PENALTY if n_gt else NAN
        return EpisodeScore(0.0, NAN, NAN, n_gt, 0, n_gt, 0, c, object_precision=0.0, object_f1=0.0 if n_gt else NAN,
                            set_rmsd_unregistered=c)
    if n_gt == 0:
        return EpisodeScore(NAN, NAN, NAN, n_pred, 0, 0, n_pred, NAN, object_precision=0.0, object_f1=0.0)
    return None


def score_prediction(catalog: Catalog, gt: Arrangement, placements: Sequence[Placement],
                     failed: bool = False, table: Table | None = None, matching: str = "hungarian") -> EpisodeScore:
    """Score one prediction against its ground-truth arrangement.

    Args:
        catalog: the dataset's catalog (object features for matching, symmetry and footprints).
        gt: the target arrangement.
        placements: the predicted placements (object ids may repeat).
        failed: the method failed on this episode (scored as predicting nothing).
        table: the table `gt` is set on (`ds.tables[gt.table]`); without it the off-table rates are nan.
        matching: the matching rule, "hungarian" (default) or "paper" (matching.py `MATCHINGS`).

    Returns:
        The EpisodeScore (see the module docstring for each field).

    Raises:
        DegustaError: an object id is not in the catalog, or `matching` is not a known rule.
    """
    check_matching(matching)
    placements, pred_failed = _unpack(placements)
    ftable = feature_table(catalog)
    g = ftable.rows_of([p.object for p in gt.placements], f"ground truth {gt.participant!r} trial {gt.trial}")
    n, m = len(g), len(placements)
    failed = failed or pred_failed
    score = _trivial(n, m, failed)
    if score is None:
        gi, pi, same, d2, sq = _match_one(ftable, g, gt, placements, matching)
        p = ftable.rows_of([q.object for q in placements], "prediction")
        k, correct = len(gi), sum(same)
        order = pair_symmetry(ftable.symmetry[[g[i] for i in gi]], ftable.symmetry[[p[j] for j in pi]])
        rot_err, n_rot = mean_rotation_error([gt.placements[i].rotation for i in gi],
                                             [placements[j].rotation for j in pi], order)
        score = EpisodeScore(correct / n, math.sqrt(sum(sq) / k), math.sqrt(sum(d2) / k), abs(m - n), k, n, m,
                             set_rmsd_points(sq, n, m), object_precision=correct / m,
                             object_f1=2 * correct / (n + m), set_rmsd_unregistered=set_rmsd_points(d2, n, m),
                             order_tau=float(kendall_tau_batch(np.array([pi]))[0]), rotation_error=float(rot_err),
                             n_rotation_scored=int(n_rot))
    _add_plausibility(ftable, [score], [gt], [() if failed else placements], [table])
    return score


def _add_plausibility(ftable, scores: list[EpisodeScore], gts: Sequence[Arrangement], placements: Sequence,
                      tables: Sequence[Table | None]) -> None:
    """Fill the off-table and overlap rates of `scores` (predicted and ground truth; plausibility.py) in place."""
    for which, sets in (("", placements), ("gt_", [gt.placements for gt in gts])):
        xys = [[(q.x, q.y) for q in ps] for ps in sets]
        sizes = [ftable.sizes[ftable.rows_of([q.object for q in ps], "placements")] for ps in sets]
        overlap = overlap_rates(xys, [[q.rotation for q in ps] for ps in sets], sizes)
        off = off_table_rates(tables, xys)
        for s, o, v in zip(scores, off.tolist(), overlap.tolist()):
            setattr(s, f"{which}off_table_rate", o)
            setattr(s, f"{which}overlap_rate", v)


def _match_one(table, g, gt: Arrangement, placements: Sequence[Placement], matching: str = "hungarian"):
    """(gt_idx, pred_idx, same object?, squared distances, squared residuals after Kabsch) of the matched pairs."""
    p = table.rows_of([q.object for q in placements], "prediction")
    gxy, pxy = _xy(gt.placements), _xy(placements)
    ham = table.hamming_between(np.array([g]), np.array([p]))  # (1, n, m)
    gi, pi = (a[0].tolist() for a in assign(ham, np.array(gxy).view(np.complex128)[None],
                                            np.array(pxy).view(np.complex128)[None], matching))
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


def matched_pairs(catalog: Catalog, gt: Arrangement, placements: Sequence[Placement],
                  matching: str = "hungarian") -> list[MatchedPair]:
    """The pairs behind an episode's scores under rule `matching` (as `score_prediction` with the same rule
    matched them), in ground-truth order, for per-object analyses (e.g. error by the item's place in the answer;
    benchmarks/by_position.py) and the qualitative figures. An empty or failed prediction has none."""
    check_matching(matching)
    placements, failed = _unpack(placements)
    table = feature_table(catalog)
    g = table.rows_of([p.object for p in gt.placements], f"ground truth {gt.participant!r} trial {gt.trial}")
    if failed or not placements or not len(g):
        return []
    gi, pi, same, d2, sq = _match_one(table, g, gt, placements, matching)
    return [MatchedPair(i, j, s, math.sqrt(d), math.sqrt(r)) for i, j, s, d, r in zip(gi, pi, same, d2, sq)]


def _score_group(table, g: np.ndarray, gxy: np.ndarray, grot: np.ndarray, p: np.ndarray, pxy: np.ndarray,
                 prot: np.ndarray, matching: str = "hungarian") -> list[EpisodeScore]:
    """Score E episodes sharing n = len(gt) > 0, m = len(pred) > 0: rows g (E, n), p (E, m); xy (E, n, 2);
    rotations (E, n), (E, m); matched under rule `matching`."""
    n_ep, n, m = g.shape[0], g.shape[1], p.shape[1]
    k = min(n, m)
    # (E, k) each, gi ascending: pairs listed in ground-truth order
    gi, pi = assign(table.hamming_between(g, p), as_complex(gxy), as_complex(pxy), matching)
    rows = np.arange(n_ep)[:, None]  # (E, 1)
    g_m, p_m = g[rows, gi], p[rows, pi]  # (E, k) catalog rows of the matched objects
    correct = (g_m == p_m).sum(1)  # (E,)
    a, b = gxy[rows, gi], pxy[rows, pi]  # (E, k, 2) matched positions
    sq = kabsch_sq_residuals_batch(a, b)  # (E, k) registered squared distances
    rmsd = np.sqrt(sq.sum(1) / k).tolist()
    set_rmsd = set_rmsd_batch(sq, n, m).tolist()
    d = a - b
    d2 = (d * d).sum(2)  # (E, k) unregistered squared distances
    unreg = np.sqrt(d2.sum(1) / k).tolist()
    set_unreg = set_rmsd_batch(d2, n, m).tolist()
    acc, prec, f1 = (correct / n).tolist(), (correct / m).tolist(), (2 * correct / (n + m)).tolist()
    tau = kendall_tau_batch(pi).tolist()
    rot_err, n_rot = mean_rotation_error(grot[rows, gi], prot[rows, pi],
                                         pair_symmetry(table.symmetry[g_m], table.symmetry[p_m]))
    rot_err, n_rot = rot_err.tolist(), n_rot.tolist()
    return [EpisodeScore(acc[e], rmsd[e], unreg[e], abs(m - n), k, n, m, set_rmsd[e], object_precision=prec[e],
                         object_f1=f1[e], set_rmsd_unregistered=set_unreg[e], order_tau=tau[e],
                         rotation_error=rot_err[e], n_rotation_scored=n_rot[e]) for e in range(n_ep)]


def score_many(catalog: Catalog, gts: Sequence[Arrangement], preds: Sequence,
               tables: Mapping[int, Table] | None = None, matching: str = "hungarian") -> list[EpisodeScore]:
    """Score many predictions at once (vectorized; equal to calling `score_prediction` on each).

    Args:
        catalog: the dataset's catalog.
        gts: the ground-truth arrangements, one per episode.
        preds: one per episode, in the same order: a `Prediction` (its `placements` and `failed` are
            used), a sequence of `Placement`, or None (a failed prediction).
        tables: the dataset's tables by id (`ds.tables`): each prediction is judged on its ground truth's
            table (`gt.table`). Without them (or for a table id they lack) the off-table rates are nan.
        matching: the matching rule, "hungarian" (default) or "paper" (matching.py `MATCHINGS`).

    Returns:
        One EpisodeScore per episode, in order.
    """
    check_matching(matching)
    if len(gts) != len(preds):
        raise DegustaError(f"score_many: {len(gts)} ground truths but {len(preds)} predictions")
    table = feature_table(catalog)
    out: list[EpisodeScore | None] = [None] * len(gts)
    placed: list = [()] * len(gts)
    groups: dict[tuple[int, int], tuple[list, ...]] = {}
    for e, (gt, pred) in enumerate(zip(gts, preds)):
        placements, failed = _unpack(pred)
        g = table.rows_of([q.object for q in gt.placements], f"ground truth {gt.participant!r} trial {gt.trial}")
        out[e] = _trivial(len(g), len(placements), failed)
        if not failed:
            placed[e] = placements
        if out[e] is None:
            p = table.rows_of([q.object for q in placements], f"prediction {e}")
            group = groups.setdefault((len(g), len(p)), ([], [], [], [], [], [], []))
            for lst, v in zip(group, (e, g, _xy(gt.placements), [q.rotation for q in gt.placements], p,
                                      _xy(placements), [q.rotation for q in placements])):
                lst.append(v)
    for (n, m), (idx, g, gxy, grot, p, pxy, prot) in groups.items():
        scores = _score_group(table, np.array(g), np.array(gxy).reshape(-1, n, 2), np.array(grot, dtype=float),
                              np.array(p), np.array(pxy).reshape(-1, m, 2), np.array(prot, dtype=float), matching)
        for e, s in zip(idx, scores):
            out[e] = s
    _add_plausibility(table, out, gts, placed, [None if tables is None else tables.get(gt.table) for gt in gts])
    return out  # type: ignore[return-value]
