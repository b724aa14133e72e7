"""Per-episode scores (accuracy, Kabsch and unregistered RMSD, count error) and the fast path."""

import math

import numpy as np
import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import EpisodeScore, kabsch_rmsd, score_many, score_prediction
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
    assert (s.object_accuracy, s.rmsd, s.rmsd_unregistered, s.count_error) == (1.0, 0.0, 0.0, 0)
    shuffled = moved(list(reversed(GT.placements)), 0.4, (0.1, -0.2))
    s = score_prediction(CAT, GT, shuffled)
    assert s.object_accuracy == 1.0 and s.rmsd < 1e-12 and s.rmsd_unregistered > 0.05
    assert (s.n_matched, s.n_gt, s.n_pred) == (5, 5, 5)


def test_failed_and_empty_predictions():
    for s in (score_prediction(CAT, GT, [], failed=False), score_prediction(CAT, GT, list(GT.placements), failed=True)):
        assert s.object_accuracy == 0.0 and math.isnan(s.rmsd) and math.isnan(s.rmsd_unregistered)
        assert (s.count_error, s.n_matched, s.n_gt, s.n_pred) == (5, 0, 5, 0)


def test_one_object_gets_zero_kabsch_rmsd():
    # The bias the docs warn about: a single predicted object always aligns perfectly.
    s = score_prediction(CAT, GT, [Placement(0, 0.1, 0.1)])
    assert s.rmsd == 0.0 and s.count_error == 4 and s.object_accuracy == pytest.approx(0.2)
    assert s.rmsd_unregistered == pytest.approx(math.hypot(0.6, 0.3))


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
    got = score_many(CAT, gts, preds)
    assert len(got) == len(expected)
    assert all(same(a, b) for a, b in zip(got, expected))


def test_bad_input():
    with pytest.raises(DegustaError, match="unknown object id 500"):
        score_prediction(CAT, GT, [Placement(500, 0.1, 0.1)])
    with pytest.raises(DegustaError, match="unknown object id 500"):
        score_many(CAT, [GT], [[Placement(500, 0.1, 0.1)]])
    with pytest.raises(DegustaError, match="2 ground truths but 1"):
        score_many(CAT, [GT, GT], [[]])
