"""Physical plausibility: centroids off the table surface and overlapping footprint ellipses, on hand-computed
layouts (the exact lens area of two discs, a knife across a plate, a rectangular table's edge)."""

import math

import numpy as np
import pytest

from degusta_learn.metrics import OVERLAP_FRACTION, footprint_overlap, off_table_rates, overlap_rates, score_prediction
from degusta_learn.scene import TYPE_SIZE, Arrangement, Placement, default_catalog, default_tables

CAT = default_catalog()
TABLES = {t.id: t for t in default_tables()}
CUP, KNIFE, SPOON = 0, 50, 100
PLATE = 75
R = TYPE_SIZE["cup"][0] / 2  # a cup's footprint is a disc of radius 0.04


def lens_fraction(d: float, r: float = R) -> float:
    """Exact area of two discs of radius r at distance d, over one disc's area."""
    return (2 * r * r * math.acos(d / (2 * r)) - d / 2 * math.sqrt(4 * r * r - d * d)) / (math.pi * r * r)


def cups_at(d: float, turn: float = 0.0) -> float:
    return float(footprint_overlap([[0.5, 0.5]], [0.0], [TYPE_SIZE["cup"]], [[0.5 + d, 0.5]], [turn],
                                   [TYPE_SIZE["cup"]])[0])


def test_overlap_of_two_discs_is_the_lens_area():
    for f in (0.2, 0.5, 1.0, 1.2, 1.5, 1.9):
        assert cups_at(f * R, turn=37.0) == pytest.approx(lens_fraction(f * R), abs=0.01)
    assert cups_at(0.0) == 1.0 and cups_at(2.01 * R) == 0.0
    # the threshold sits between d = r (39% of a cup covered) and d = 1.2 r (28%)
    assert lens_fraction(R) > OVERLAP_FRACTION > lens_fraction(1.2 * R)


def test_overlap_is_over_the_smaller_footprint_and_respects_rotation():
    # A knife (0.03 x 0.18 ellipse) lying across a plate (disc of radius 0.085) at its centre: the knife's
    # ellipse pokes out 0.005 at each end, so nearly all of the smaller footprint (the knife) is covered.
    across = footprint_overlap([[0.5, 0.5]], [90.0], [TYPE_SIZE["knife"]], [[0.5, 0.5]], [0.0], [TYPE_SIZE["plate"]])
    assert across[0] > 0.95
    # Two knives side by side 0.05 apart, parallel: no overlap; crossed at right angles at their centres: they
    # share a patch about 0.03 x 0.03 near the centres, ~0.19 of a knife's ellipse (pi * 0.015 * 0.09): below 0.3.
    k = TYPE_SIZE["knife"]
    assert footprint_overlap([[0.5, 0.5]], [0.0], [k], [[0.55, 0.5]], [0.0], [k])[0] == 0.0
    crossed = footprint_overlap([[0.5, 0.5]], [0.0], [k], [[0.5, 0.5]], [90.0], [k])[0]
    assert 0.1 < crossed < OVERLAP_FRACTION
    assert footprint_overlap([[0.5, 0.5]], [0.0], [k], [[0.5, 0.52]], [0.0], [k])[0] > 0.8  # stacked lengthwise


def test_overlap_rates_count_pairs():
    # Three cups: two at distance r (overlap 39%), the third far away -> 1 of 3 pairs.
    xy = [[0.5, 0.5], [0.5 + R, 0.5], [0.1, 0.1]]
    sizes = [TYPE_SIZE["cup"]] * 3
    assert overlap_rates([xy], [[0, 0, 0]], [sizes])[0] == pytest.approx(1 / 3)
    # at distance 1.2 r (28%) they do not count
    assert overlap_rates([[[0.5, 0.5], [0.5 + 1.2 * R, 0.5], [0.1, 0.1]]], [[0, 0, 0]], [sizes])[0] == 0.0
    out = overlap_rates([[[0.5, 0.5]], [], xy], [[0], [], [0, 0, 0]], [[TYPE_SIZE["cup"]], np.zeros((0, 2)), sizes])
    assert math.isnan(out[0]) and math.isnan(out[1]) and out[2] == pytest.approx(1 / 3)  # < 2 objects: nan


def test_off_table_rates_on_a_rectangle_and_an_ellipse():
    oak, marble = TABLES[0], TABLES[1]  # oak: rectangle x 0.04..0.96, y 0.12..0.88; marble: disc r 0.46 at centre
    assert off_table_rates([oak], [[[0.5, 0.5], [0.5, 0.05], [0.97, 0.5], [0.05, 0.13]]])[0] == pytest.approx(2 / 4)
    assert off_table_rates([marble], [[[0.5, 0.5], [0.05, 0.05], [0.9, 0.5]]])[0] == pytest.approx(1 / 3)
    out = off_table_rates([oak, None, oak], [[], [[0.5, 0.5]], [[0.5, 0.5]]])
    assert math.isnan(out[0]) and math.isnan(out[1]) and out[2] == 0.0  # nothing placed / no table: nan


def test_plausibility_of_a_prediction():
    gt = Arrangement("p1", 0, 0, (Placement(PLATE, 0.5, 0.5), Placement(KNIFE, 0.65, 0.5), Placement(CUP, 0.7, 0.3)))
    # a cup at the plate's centre (the smaller footprint fully covered), a knife off the table's top edge
    pred = [Placement(PLATE, 0.5, 0.5), Placement(CUP, 0.5, 0.5), Placement(KNIFE, 0.65, 0.05)]
    s = score_prediction(CAT, gt, pred, table=TABLES[0])
    assert s.off_table_rate == pytest.approx(1 / 3) and s.overlap_rate == pytest.approx(1 / 3)
    assert s.gt_off_table_rate == 0.0 and s.gt_overlap_rate == 0.0
