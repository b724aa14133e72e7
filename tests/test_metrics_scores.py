"""Per-episode scores (accuracy, Kabsch and unregistered RMSD, count error, set RMSD) and the fast path."""

import itertools
import math

import numpy as np
import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import (
    SET_PENALTY,
    EpisodeScore,
    few_matched_fraction,
    kabsch_rmsd,
    score_many,
    score_prediction,
)
from degusta_learn.metrics.matching import hamming
from degusta_learn.scene import Arrangement, Placement, Prediction, default_catalog

CAT = default_catalog()
# cup 0, fork 25, knife 50, plate 75, spoon 100 at distinct positions.
GT = Arrangement("p1", 0, 0, (Placement(75, 0.5, 0.6), Placement(0, 0.7, 0.4), Placement(25, 0.3, 0.6),
                              Placement(50, 0.65, 0.62), Placement(100, 0.72, 0.6)))


def moved(placements, theta, shift):
    c, s = math.cos(theta), math.sin(theta)
    return [Placement(p.object, c * p.x - s * p.y + shift[0], s * p.x + c * p.y + shift[1], p.rotation)
            for p in placements]


def same(a: EpisodeScore, b: EpisodeScore) -> bool:
    """Integers equal; floats equal up to the last bits (the two paths sum in different orders)."""
    for x, y in zip(vars(a).values(), vars(b).values()):
        if isinstance(x, float) and math.isnan(x):
            if not (isinstance(y, float) and math.isnan(y)):
                return False
        elif not math.isclose(x, y, rel_tol=1e-12, abs_tol=1e-14) or type(x) is not type(y):
            return False
    return True


def test_perfect_and_rigidly_moved_predictions():
    s = score_prediction(CAT, GT, list(GT.placements))
    assert (s.object_accuracy, s.rmsd, s.rmsd_unregistered, s.count_error, s.set_rmsd) == (1.0, 0.0, 0.0, 0, 0.0)
    shuffled = moved(list(reversed(GT.placements)), 0.4, (0.1, -0.2))
    s = score_prediction(CAT, GT, shuffled)
    assert s.object_accuracy == 1.0 and s.rmsd < 1e-12 and s.set_rmsd < 1e-12 and s.rmsd_unregistered > 0.05
    assert (s.n_matched, s.n_gt, s.n_pred) == (5, 5, 5)


def test_failed_and_empty_predictions():
    for s in (score_prediction(CAT, GT, [], failed=False), score_prediction(CAT, GT, list(GT.placements), failed=True)):
        assert s.object_accuracy == 0.0 and math.isnan(s.rmsd) and math.isnan(s.rmsd_unregistered)
        assert (s.count_error, s.n_matched, s.n_gt, s.n_pred) == (5, 0, 5, 0)
        assert s.set_rmsd == SET_PENALTY  # every ground-truth object unmatched
    empty_gt = Arrangement("p1", 1, 0, ())
    assert math.isnan(score_prediction(CAT, empty_gt, [Placement(0, 0.1, 0.1)]).set_rmsd)
    assert math.isnan(score_prediction(CAT, empty_gt, [], failed=True).set_rmsd)


def test_one_object_gets_zero_kabsch_rmsd():
    # The bias the docs warn about: a single predicted object always aligns perfectly.
    s = score_prediction(CAT, GT, [Placement(0, 0.1, 0.1)])
    assert s.rmsd == 0.0 and s.count_error == 4 and s.object_accuracy == pytest.approx(0.2)
    assert s.rmsd_unregistered == pytest.approx(math.hypot(0.6, 0.3))
    # ... which the set RMSD does not give: four missing objects cost c each.
    assert s.set_rmsd == pytest.approx(math.sqrt(4 / 5) * SET_PENALTY) == pytest.approx(0.178885, abs=1e-6)


def test_accuracy_needs_the_exact_id_and_counts_unmatched_as_wrong():
    # Plate 75 exact; cup 1 stands in for cup 0 (same type, other object); the rest unmatched.
    pred = [Placement(75, 0.5, 0.6), Placement(1, 0.7, 0.4)]
    s = score_prediction(CAT, GT, pred)
    assert s.object_accuracy == pytest.approx(1 / 5)
    assert s.count_error == 3 and s.n_matched == 2
    # Extra predicted objects do not hurt accuracy, only the count error.
    extra = list(GT.placements) + [Placement(2, 0.1, 0.1), Placement(3, 0.9, 0.9)]
    s = score_prediction(CAT, GT, extra)
    assert s.object_accuracy == 1.0 and s.count_error == 2 and s.rmsd < 1e-12


def test_rmsd_uses_matched_pairs():
    pred = [Placement(p.object, p.x + (0.05 if i % 2 else -0.03), p.y, 0.0) for i, p in enumerate(GT.placements)]
    s = score_prediction(CAT, GT, pred[::-1])
    assert s.rmsd == pytest.approx(kabsch_rmsd(GT.positions, [[p.x, p.y] for p in pred]), abs=1e-12)


def test_score_many_equals_score_prediction():
    rng = np.random.default_rng(0)
    gts, preds, expected = [], [], []
    for e in range(300):
        n, m = int(rng.integers(1, 7)), int(rng.integers(0, 7))
        gt = Arrangement("p", e, 0, tuple(Placement(int(i), *rng.random(2)) for i in rng.choice(125, n, replace=False)))
        pl = [Placement(int(i), *rng.random(2)) for i in rng.choice(125, m)]
        failed = bool(rng.random() < 0.1)
        kind = e % 3
        pred = Prediction(f"e{e}", "p", e, "m", pl, failed=failed) if kind == 0 else (None if failed else pl)
        gts.append(gt)
        preds.append(pred)
        expected.append(score_prediction(CAT, gt, pl, failed=failed))
    empty = Arrangement("p", 999, 0, ())  # an empty ground truth, predicted and failed
    for pl, failed in (([Placement(0, 0.5, 0.5)], False), ([], True)):
        gts.append(empty)
        preds.append(None if failed else pl)
        expected.append(score_prediction(CAT, empty, pl, failed=failed))
    got = score_many(CAT, gts, preds)
    assert len(got) == len(expected)
    assert all(same(a, b) for a, b in zip(got, expected))  # every field, set_rmsd included
    assert {"set_rmsd", "rmsd", "object_accuracy"} <= set(vars(got[0]))
    assert len({round(s.set_rmsd, 9) for s in got if not math.isnan(s.set_rmsd)}) > 100  # a varied sample


def test_bad_input():
    with pytest.raises(DegustaError, match="unknown object id 500"):
        score_prediction(CAT, GT, [Placement(500, 0.1, 0.1)])
    with pytest.raises(DegustaError, match="unknown object id 500"):
        score_many(CAT, [GT], [[Placement(500, 0.1, 0.1)]])
    with pytest.raises(DegustaError, match="2 ground truths but 1"):
        score_many(CAT, [GT, GT], [[]])


# --- set RMSD against an independent reference -------------------------------------------------------


def reference_set_rmsd(gt: Arrangement, placements, c=SET_PENALTY):
    """Brute force: the matching by exhaustive lexicographic search (min total Hamming, then min total
    distance) over all injective assignments, the registration by a grid + bounded search over the
    rotation angle (translation: centroid onto centroid), then the OSPA formula of the docs."""
    from scipy.optimize import minimize_scalar

    gid, pid = [p.object for p in gt.placements], [p.object for p in placements]
    n, m = len(gid), len(pid)
    if n == 0:
        return math.nan
    if m == 0:
        return c
    gxy, pxy = np.array(gt.positions, dtype=float), np.array([[p.x, p.y] for p in placements])
    h = hamming(CAT.features(gid), CAT.features(pid))  # the distance itself: tests/test_metrics_pairs.py
    dist = np.linalg.norm(gxy[:, None] - pxy[None], axis=-1)
    pairs = ([(list(range(n)), list(cols)) for cols in itertools.permutations(range(m), n)] if n <= m else
             [(list(rows), list(range(m))) for rows in itertools.permutations(range(n), m)])
    rows, cols = min(pairs, key=lambda rc: (int(h[rc].sum()), float(dist[rc].sum())))
    a, b = gxy[rows] - gxy[rows].mean(0), pxy[cols] - pxy[cols].mean(0)

    def sq(theta):  # squared registered distances, per pair
        r = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
        return ((b @ r.T - a) ** 2).sum(1)

    grid = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    best = grid[np.argmin([sq(t).sum() for t in grid])]
    step = 2 * np.pi / len(grid)
    theta = minimize_scalar(lambda t: sq(t).sum(), bounds=(best - step, best + step), method="bounded",
                            options={"xatol": 1e-12}).x
    d = np.sqrt(sq(theta))
    return math.sqrt(((np.minimum(d, c) ** 2).sum() + c * c * abs(n - m)) / max(n, m))


def test_set_rmsd_matches_brute_force_reference():
    rng = np.random.default_rng(3)
    for e in range(80):
        n, m = int(rng.integers(1, 6)), int(rng.integers(0, 6))
        gt = Arrangement("p", e, 0, tuple(Placement(int(i), *rng.random(2)) for i in rng.choice(125, n, replace=False)))
        # Near-copies (some objects swapped for a same-type neighbour id) or unrelated random sets.
        if e % 2:
            pl = [Placement(p.object + int(rng.integers(0, 2)), *(np.array([p.x, p.y]) + rng.normal(0, 0.08, 2)))
                  for p in gt.placements[:m]]
        else:
            pl = [Placement(int(i), *rng.random(2)) for i in rng.choice(125, m)]
        pl = [Placement(min(p.object, 124), p.x, p.y) for p in pl]
        assert score_prediction(CAT, gt, pl).set_rmsd == pytest.approx(reference_set_rmsd(gt, pl), abs=1e-8)


def test_set_rmsd_hand_computed_cap_and_extras():
    # Four objects in place and one 0.5 from home: after registration its distance is still above c and
    # counts as c, so the set RMSD drops below the Kabsch RMSD (same pairs, same registration).
    pred = list(GT.placements[:4]) + [Placement(100, 0.72 + 0.5, 0.6)]
    s = score_prediction(CAT, GT, pred)
    assert 0 < s.set_rmsd < s.rmsd < SET_PENALTY
    assert s.set_rmsd == pytest.approx(reference_set_rmsd(GT, pred), abs=1e-8)
    # Extra predictions cost c each, like missing ones: 5 perfect + 3 extras -> sqrt(3 / 8) * c.
    extra = list(GT.placements) + [Placement(i, 0.1, 0.1) for i in (1, 2, 3)]
    assert score_prediction(CAT, GT, extra).set_rmsd == pytest.approx(math.sqrt(3 / 8) * SET_PENALTY)


def test_set_rmsd_missing_objects_never_score_better_and_bounded():
    # Dropping objects from a perfect prediction: strictly worse with each one, c when nothing is left.
    scores = [score_prediction(CAT, GT, list(GT.placements[:k])).set_rmsd for k in range(5, -1, -1)]
    assert scores == sorted(scores) and len(set(scores)) == 6 and scores[-1] == SET_PENALTY
    assert scores == pytest.approx([math.sqrt(j / 5) * SET_PENALTY for j in range(6)])
    # Whatever the positions: 0 <= set RMSD <= c, and never below the cost of the missing objects.
    rng = np.random.default_rng(5)
    for _ in range(200):
        k = int(rng.integers(1, 6))
        pl = [Placement(p.object, *(rng.random(2) * 3 - 1)) for p in GT.placements[:k]]
        s = score_prediction(CAT, GT, pl)
        assert math.sqrt((5 - k) / 5) * SET_PENALTY - 1e-15 <= s.set_rmsd <= SET_PENALTY + 1e-15


def test_few_matched_fraction():
    n_gt, n_matched = [5, 5, 5, 2, 4], [1, 2, 5, 2, 0]
    failed = [False, False, False, False, True]
    # Counted: the three non-failed episodes with >= 3 ground-truth objects; two of them match <= 2.
    frac, degenerate = few_matched_fraction(n_gt, n_matched, failed)
    assert frac == pytest.approx(2 / 3) and degenerate
    assert few_matched_fraction([5, 5], [2, 3], [False, False]) == (0.5, False)  # exactly half: not degenerate
    assert few_matched_fraction([2, 5], [1, 0], [False, True]) == (None, False)  # nothing counted
