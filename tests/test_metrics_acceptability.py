"""Acceptability curve from ratings (hand-computed) and the fraction of acceptable predictions."""

import math

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import PAPER_ACCEPTABILITY, THRESHOLDS, acceptability_curve, fraction_acceptable
from degusta_learn.scene import Rating


def r(rmsd, b_initial, b_jitter):
    return Rating("p", 0, b_initial, b_jitter, rmsd)


def test_defaults_to_the_papers_points():
    assert acceptability_curve(None) == {0.01: 0.727, 0.05: 0.333, 0.10: 0.199}
    assert acceptability_curve([]) == PAPER_ACCEPTABILITY
    assert THRESHOLDS == (0.01, 0.05, 0.10)
    with pytest.raises(DegustaError, match="0.2"):
        acceptability_curve(None, thresholds=(0.2,))


def test_hand_computed_curve():
    ratings = [
        r(0.005, 80, 75),  # drop 0.05: acceptable
        r(0.008, 80, 50),  # drop 0.30: not
        r(0.03, 90, 71),  # drop 0.19: acceptable
        r(0.04, 90, 70),  # drop exactly 0.20: not (strictly below)
        r(0.09, 50, 60),  # rating went up: acceptable
        r(0.50, 100, 0),  # beyond every threshold
    ]
    # t = 0.01: 1 of 2; t = 0.05: 2 of 4; t = 0.10: 3 of 5.
    assert acceptability_curve(ratings) == pytest.approx({0.01: 0.5, 0.05: 0.5, 0.10: 0.6})
    assert acceptability_curve(ratings, thresholds=(0.01,), drop_threshold=0.4) == {0.01: 1.0}
    assert math.isnan(acceptability_curve(ratings, thresholds=(0.001,))[0.001])


def test_fraction_acceptable_counts_nan_as_not_acceptable():
    got = fraction_acceptable([0.005, 0.03, 0.2, float("nan")])
    assert got == pytest.approx({0.01: 0.25, 0.05: 0.5, 0.10: 0.5})
    assert fraction_acceptable([0.01], thresholds=(0.01,)) == {0.01: 1.0}  # <= t
    assert all(math.isnan(v) for v in fraction_acceptable([]).values())
