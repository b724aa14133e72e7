"""metrics.degenerate: the answer fingerprint and the three reasons, on hand-counted cases."""

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import answer_key, constant_fraction, degenerate_answers


def test_answer_key_ignores_order_and_rounding_below_a_hundredth():
    objects, xy = [3, 7, 1], [(0.101, 0.2), (0.5, 0.5), (0.9, 0.333)]
    key = answer_key(objects, xy)
    assert isinstance(key, str) and len(key) == 12
    assert answer_key(objects[::-1], xy[::-1]) == key  # order is not part of the answer's identity
    assert answer_key(objects, [(0.099, 0.2), (0.5, 0.502), (0.9, 0.334)]) == key  # same at 0.01
    assert answer_key(objects, [(0.12, 0.2), (0.5, 0.5), (0.9, 0.333)]) != key  # 0.02 away: another answer
    assert answer_key([3, 7, 2], xy) != key  # another object
    assert answer_key([1], [(-0.001, 0.0)]) == answer_key([1], [(0.0, 0.0)])  # -0.00 is 0.00
    assert answer_key([], []) is None
    with pytest.raises(DegustaError, match="2 objects but 1 positions"):
        answer_key([1, 2], [(0.1, 0.1)])


def test_too_few_by_half_or_by_the_few_matched_rule():
    # 4 scored episodes (the failed one is left out): 3 have <= half the truth's objects -> 3/4.
    v = degenerate_answers([4, 6, 4, 5, 4], [2, 3, 4, 2, 0], [False, False, False, False, True])
    assert v.n_scored == 4 and v.short_fraction == 0.75 and v.reasons == ("too few",) and v.degenerate
    # 3 of 5 is more than half, but 2 matched of 3 or more in 2 of 3 episodes: the older rule fires.
    v = degenerate_answers([3, 3, 8], [2, 2, 8], [False] * 3)
    assert v.short_fraction == 0.0 and v.few_matched_fraction == pytest.approx(2 / 3) and v.reasons == ("too few",)
    # Exactly half is not "more than half".
    assert degenerate_answers([4, 4], [2, 4], [False, False]).reasons == ()


def test_padding_by_ratio_or_margin():
    assert degenerate_answers([3, 3, 3], [6, 6, 3], [False] * 3).reasons == ("padding",)  # 2 x the truth
    v = degenerate_answers([10, 10, 10], [14, 14, 10], [False] * 3)  # 4 more (PAD_MARGIN), not 2x
    assert v.padded_fraction == pytest.approx(2 / 3) and v.reasons == ("padding",)
    assert degenerate_answers([10, 10, 10], [13, 13, 13], [False] * 3).reasons == ()  # 3 more: an honest answer
    assert degenerate_answers([3, 3, 3], [5, 5, 5], [False] * 3).reasons == ()


def test_constant_needs_most_episodes_and_two_participants():
    n = [4] * 4
    assert constant_fraction(["a", "a", "a", "b"], ["p", "q", "r", "s"]) == 0.75
    assert constant_fraction(["a", "a", "a", "b"], ["p", "p", "p", "s"]) == 0.0  # one person's repeated table
    assert constant_fraction([None, "a", "a"], ["p", "q", "r"]) == pytest.approx(2 / 3)  # None: no answer to share
    assert constant_fraction([]) is None
    v = degenerate_answers(n, n, [False] * 4, answer_keys=["a", "a", "a", "b"], participants=["p", "q", "r", "s"])
    assert v.constant_fraction == 0.75 and v.reasons == ("constant",)
    # Failed episodes are not counted: 2 of the 3 scored answers are "a".
    v = degenerate_answers(n, n, [True, False, False, False], answer_keys=[None, "a", "a", "b"],
                           participants=["p", "q", "r", "s"])
    assert v.constant_fraction == pytest.approx(2 / 3) and v.degenerate
    assert degenerate_answers(n, n, [False] * 4, answer_keys=["a", "b", "a", "b"],
                              participants=["p", "q", "r", "s"]).reasons == ()  # half each: not more than half
    assert degenerate_answers(n, n, [False] * 4).constant_fraction is None  # no keys: not tested


def test_reasons_combine_in_fixed_order_and_fractions_are_reported():
    v = degenerate_answers([6, 6, 6], [1, 1, 6], [False] * 3, answer_keys=["k", "k", "m"], participants=["p", "q", "r"])
    assert v.reasons == ("too few", "constant")
    assert v.fractions() == {"too few": pytest.approx(2 / 3, abs=1e-6), "few matched": pytest.approx(2 / 3, abs=1e-6),
                             "padding": 0.0, "constant": pytest.approx(2 / 3, abs=1e-6)}


def test_nothing_scored_is_not_degenerate_and_bad_lengths_are_refused():
    v = degenerate_answers([3, 0], [0, 2], [True, False])  # a failure and an empty ground truth
    assert v.n_scored == 0 and v.reasons == () and v.short_fraction is None and v.padded_fraction is None
    with pytest.raises(DegustaError, match="differ in length"):
        degenerate_answers([3, 3], [3], [False, False])
    with pytest.raises(DegustaError, match="1 answer keys for 2 episodes"):
        degenerate_answers([3, 3], [3, 3], [False, False], answer_keys=["a"])
