"""The task-plan metrics on hand-computed arrangements: placement order (Kendall's tau), rotation modulo each
object's symmetry, object precision and F1, the unregistered set RMSD; and their edge cases (0 or 1 matched
objects, empty and failed predictions)."""

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from degusta_learn.metrics import (
    SET_PENALTY,
    SHAPE_SYMMETRY,
    TYPE_SYMMETRY,
    UNKNOWN_SYMMETRY,
    kendall_tau,
    rotation_errors,
    score_many,
    score_prediction,
    symmetry_order,
)
from degusta_learn.metrics.plan import FULL, pair_symmetry
from degusta_learn.scene import TYPES, Arrangement, CatalogObject, Placement, default_catalog, default_tables

CAT = default_catalog()
TABLES = {t.id: t for t in default_tables()}
CUP, FORK, KNIFE, SPOON = 0, 25, 50, 100
SQUARE_PLATE = next(o.id for o in CAT if o.type == "plate" and o.shape == "square")
ROUND_PLATE = next(o.id for o in CAT if o.type == "plate" and o.shape == "round")
OVAL_PLATE = next(o.id for o in CAT if o.type == "plate" and o.shape == "oval")


def gt_of(*placements, table=0) -> Arrangement:
    return Arrangement("p1", 0, table, tuple(placements))


# --- Kendall's tau ------------------------------------------------------------------------------------------


def test_kendall_tau_hand_computed():
    assert kendall_tau([0, 1, 2, 3]) == 1.0
    assert kendall_tau([3, 2, 1, 0]) == -1.0
    # [0, 2, 1]: pairs (0,2) and (0,1) in order, (2,1) out of order -> (2 - 1) / 3
    assert kendall_tau([0, 2, 1]) == pytest.approx(1 / 3)
    # [1, 0, 3, 2]: 4 of 6 pairs in order -> (4 - 2) / 6
    assert kendall_tau([1, 0, 3, 2]) == pytest.approx(1 / 3)
    assert kendall_tau([5, 9]) == 1.0 and kendall_tau([9, 5]) == -1.0  # two pairs: +-1
    assert math.isnan(kendall_tau([4])) and math.isnan(kendall_tau([]))  # nothing to order
    # given ground-truth positions, pairs are first put in ground-truth order
    assert kendall_tau([2, 0, 1], gt_idx=[2, 0, 1]) == 1.0


def test_kendall_tau_matches_scipy():
    rng = np.random.default_rng(0)
    for k in range(2, 9):
        for _ in range(20):
            p = rng.permutation(k + 3)[:k]
            assert kendall_tau(p) == pytest.approx(stats.kendalltau(np.arange(k), p).statistic, abs=1e-12)


def test_order_tau_of_a_prediction():
    # Ground truth: plate, fork, knife, cup (placement order = list order). The prediction lists the same
    # objects in the order knife, plate, cup, fork: in ground-truth order their places are 1, 3, 0, 2.
    gt = gt_of(Placement(SQUARE_PLATE, 0.5, 0.5), Placement(FORK, 0.35, 0.5), Placement(KNIFE, 0.65, 0.5),
               Placement(CUP, 0.7, 0.35))
    pred = [gt.placements[2], gt.placements[0], gt.placements[3], gt.placements[1]]
    # pairs (1,3)+ (1,0)- (1,2)+ (3,0)- (3,2)- (0,2)+: (3 - 3) / 6 = 0
    assert score_prediction(CAT, gt, pred).order_tau == 0.0
    assert score_prediction(CAT, gt, list(gt.placements)).order_tau == 1.0
    assert score_prediction(CAT, gt, list(reversed(gt.placements))).order_tau == -1.0
    # Only matched pairs count: two predicted objects, in ground-truth order -> 1 (not "4 of 4").
    assert score_prediction(CAT, gt, [gt.placements[1], gt.placements[3]]).order_tau == 1.0
    assert score_prediction(CAT, gt, [gt.placements[3], gt.placements[1]]).order_tau == -1.0


# --- symmetry and rotation ------------------------------------------------------------------------------------


def test_every_catalog_type_and_shape_has_a_symmetry():
    assert set(TYPES) <= set(TYPE_SYMMETRY)  # the documented table covers every type of the design
    for obj in CAT:  # and every object of the default catalog resolves through it, not through the fallback
        assert (obj.type, obj.shape) in SHAPE_SYMMETRY or obj.type in TYPE_SYMMETRY, obj
    assert {symmetry_order(o) for o in CAT if o.type in ("cup", "fork", "knife", "spoon")} == {1}
    assert {o.shape: symmetry_order(o) for o in CAT if o.type == "plate"} == {
        "round": FULL, "square": 4, "oval": 2, "octagonal": 8}
    teapot = CatalogObject(999, "teapot", "red", "red", "ceramic", "ceramic")
    assert symmetry_order(teapot) == UNKNOWN_SYMMETRY == 4


def test_rotation_errors_hand_computed():
    assert rotation_errors(10, 350, 1) == pytest.approx(20.0)  # the short way round
    assert rotation_errors(0, 180, 1) == pytest.approx(180.0)  # the largest error without symmetry
    assert rotation_errors(30, 100, 1) == pytest.approx(70.0)
    assert rotation_errors(10, 100, 4) == pytest.approx(0.0)  # a square looks the same every 90 degrees
    assert rotation_errors(10, 55, 4) == pytest.approx(45.0)  # the largest error of a square
    assert rotation_errors(0, 170, 2) == pytest.approx(10.0)  # an oval plate every 180
    assert math.isnan(rotation_errors(0, 123, FULL))  # a round plate: not scored
    rng = np.random.default_rng(1)
    for s in (1, 2, 4, 8):
        err = rotation_errors(rng.uniform(0, 360, 500), rng.uniform(-720, 720, 500), s)
        assert (err >= 0).all() and (err <= 180 / s + 1e-9).all()
    # A pair shares the symmetry both objects keep: lcm of the orders; any fully symmetric object: not scored.
    assert pair_symmetry(4, 2) == 4 and pair_symmetry(1, 4) == 4 and pair_symmetry(1, 1) == 1
    assert pair_symmetry(FULL, 1) == FULL and pair_symmetry(4, FULL) == FULL


def test_rotation_error_of_a_prediction():
    gt = gt_of(Placement(KNIFE, 0.6, 0.5, 10.0), Placement(FORK, 0.4, 0.5, 0.0), Placement(ROUND_PLATE, 0.5, 0.5, 0.0),
               Placement(SQUARE_PLATE, 0.5, 0.3, 0.0))
    pred = [Placement(KNIFE, 0.6, 0.5, 350.0), Placement(FORK, 0.4, 0.5, 90.0),
            Placement(ROUND_PLATE, 0.5, 0.5, 77.0), Placement(SQUARE_PLATE, 0.5, 0.3, 100.0)]
    s = score_prediction(CAT, gt, pred)
    # knife 20, fork 90, square plate 10 (100 mod 90), round plate not scored: (20 + 90 + 10) / 3
    assert s.rotation_error == pytest.approx(40.0) and s.n_rotation_scored == 3
    only_round = score_prediction(CAT, gt_of(Placement(ROUND_PLATE, 0.5, 0.5, 0.0)),
                                  [Placement(ROUND_PLATE, 0.5, 0.5, 45.0)])
    assert math.isnan(only_round.rotation_error) and only_round.n_rotation_scored == 0
    # A square plate matched to an oval one: they share order lcm(4, 2) = 4 -> 100 vs 0 is 10.
    mixed = score_prediction(CAT, gt_of(Placement(SQUARE_PLATE, 0.5, 0.5, 0.0)), [Placement(OVAL_PLATE, 0.5, 0.5, 100.0)])
    assert mixed.rotation_error == pytest.approx(10.0)


# --- precision, F1 and the unregistered set RMSD ---------------------------------------------------------------


def test_precision_f1_and_unregistered_set_rmsd_hand_computed():
    gt = gt_of(Placement(SQUARE_PLATE, 0.5, 0.5), Placement(FORK, 0.35, 0.5), Placement(KNIFE, 0.65, 0.5))
    # plate exact, fork 25 replaced by fork 27 (2 features apart), knife exact, plus an extra cup 4 (7 features
    # from fork 25, so the matching pairs fork with fork and leaves the cup unmatched)
    pred = [Placement(SQUARE_PLATE, 0.5, 0.5), Placement(FORK + 2, 0.35, 0.5), Placement(KNIFE, 0.65, 0.5),
            Placement(4, 0.2, 0.2)]
    s = score_prediction(CAT, gt, pred)
    assert s.object_accuracy == pytest.approx(2 / 3)  # recall
    assert s.object_precision == pytest.approx(2 / 4)
    assert s.object_f1 == pytest.approx(2 * 2 / (3 + 4))  # = 2PR / (P + R) = 4/7
    assert s.object_f1 == pytest.approx(2 * (2 / 3) * (2 / 4) / (2 / 3 + 2 / 4))
    # Every matched object in place, one extra: sqrt(c^2 * 1 / 4) = c / 2, registered or not.
    assert s.set_rmsd_unregistered == pytest.approx(SET_PENALTY / 2) == pytest.approx(s.set_rmsd)
    # A rigid shift by 0.05: registration removes it, the unregistered set RMSD does not (every pair 0.05 off).
    shifted = [Placement(p.object, p.x + 0.05, p.y) for p in gt.placements]
    s = score_prediction(CAT, gt, shifted)
    assert s.set_rmsd < 1e-12 and s.set_rmsd_unregistered == pytest.approx(0.05)
    # ... capped at c per pair like the registered one: a shift of 0.5 costs c per object.
    far = score_prediction(CAT, gt, [Placement(p.object, p.x - 0.3, p.y + 0.4) for p in gt.placements])
    assert far.set_rmsd_unregistered == pytest.approx(SET_PENALTY)


# --- edge cases --------------------------------------------------------------------------------------------------


def test_edge_cases_zero_and_one_match_empty_and_failed():
    gt = gt_of(Placement(KNIFE, 0.6, 0.5, 10.0), Placement(FORK, 0.4, 0.5, 0.0), Placement(CUP, 0.7, 0.3, 0.0))
    one = score_prediction(CAT, gt, [Placement(KNIFE, 0.6, 0.5, 40.0)], table=TABLES[0])
    assert one.n_matched == 1 and math.isnan(one.order_tau)  # no pair to order
    assert one.rotation_error == pytest.approx(30.0) and one.n_rotation_scored == 1
    assert one.object_precision == 1.0 and one.object_f1 == pytest.approx(2 / 4)
    assert one.off_table_rate == 0.0 and math.isnan(one.overlap_rate)  # one object: no pair
    for s in (score_prediction(CAT, gt, [], table=TABLES[0]),  # empty
              score_prediction(CAT, gt, list(gt.placements), failed=True, table=TABLES[0])):  # failed
        assert (s.object_accuracy, s.object_precision, s.object_f1) == (0.0, 0.0, 0.0)
        assert s.set_rmsd_unregistered == SET_PENALTY == s.set_rmsd
        assert math.isnan(s.order_tau) and math.isnan(s.rotation_error) and s.n_rotation_scored == 0
        assert math.isnan(s.off_table_rate) and math.isnan(s.overlap_rate)  # nothing placed
        assert s.gt_off_table_rate == 0.0 and s.gt_overlap_rate == 0.0  # the reference is still there
    # Zero same-id matches: precision and F1 0, but order and rotation still scored over the matched pairs.
    other = [Placement(KNIFE + 1, 0.6, 0.5, 10.0), Placement(FORK + 1, 0.4, 0.5, 180.0)]
    s = score_prediction(CAT, gt, other)
    assert (s.object_precision, s.object_f1) == (0.0, 0.0)
    assert s.order_tau == 1.0 and s.rotation_error == pytest.approx(90.0) and s.n_rotation_scored == 2
    empty_gt = score_prediction(CAT, gt_of(), [Placement(CUP, 0.5, 0.5)])
    assert math.isnan(empty_gt.object_accuracy) and (empty_gt.object_precision, empty_gt.object_f1) == (0.0, 0.0)


def test_score_many_equals_score_prediction_on_every_plan_field():
    rng = np.random.default_rng(7)
    gts, preds, expected = [], [], []
    for e in range(250):
        n, m = int(rng.integers(1, 7)), int(rng.integers(0, 7))
        gt = Arrangement("p", e, int(rng.integers(0, 5)), tuple(
            Placement(int(i), *rng.random(2), float(rng.uniform(0, 360))) for i in rng.choice(125, n, replace=False)))
        pl = [Placement(int(i), *rng.random(2), float(rng.uniform(0, 360))) for i in rng.choice(125, m)]
        failed = bool(rng.random() < 0.1)
        gts.append(gt)
        preds.append(None if failed else pl)
        expected.append(score_prediction(CAT, gt, pl, failed=failed, table=TABLES[gt.table]))
    got = score_many(CAT, gts, preds, tables=TABLES)
    for a, b in zip(got, expected):
        for key, x in vars(b).items():
            y = getattr(a, key)
            assert type(x) is type(y), key
            assert (math.isnan(x) and math.isnan(y)) if isinstance(x, float) and math.isnan(x) else \
                x == pytest.approx(y, rel=1e-12, abs=1e-14), key
    # a varied sample: every field takes many values
    for key in ("order_tau", "rotation_error", "object_precision", "off_table_rate"):
        assert len({round(getattr(s, key), 9) for s in got if math.isfinite(getattr(s, key))}) > 5, key
    assert any(s.overlap_rate > 0 for s in got if math.isfinite(s.overlap_rate))


def test_without_tables_off_table_is_nan_not_zero():
    gt = gt_of(Placement(KNIFE, 0.6, 0.5), Placement(FORK, 0.4, 0.5))
    s = score_many(CAT, [gt], [list(gt.placements)])[0]
    assert math.isnan(s.off_table_rate) and math.isnan(s.gt_off_table_rate) and s.overlap_rate == 0.0


@pytest.mark.parametrize("k", [2, 3, 4])
def test_tau_over_all_orders_averages_to_zero(k):
    # Over every ordering of k matched objects, tau averages 0 (no order preference is built in).
    gt = gt_of(*(Placement(o, 0.2 + 0.15 * i, 0.5) for i, o in enumerate((KNIFE, FORK, CUP, SPOON)[:k])))
    taus = [score_prediction(CAT, gt, list(p)).order_tau for p in itertools.permutations(gt.placements)]
    assert np.mean(taus) == pytest.approx(0.0, abs=1e-12)
