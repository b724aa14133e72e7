"""Aggregation of n answers, checked on hand-built responses with hand-computed results."""

from __future__ import annotations

import math

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.render.grid import Grid
from degusta_learn.task.aggregate import aggregate, aggregate_votes, combine
from degusta_learn.task.answers import AnswerItem

G = Grid(8, 8)


def centre(cell):  # hand formula: column letter from the left, row number from the top, 1/8 each
    return ((ord(cell[0]) - 65 + 0.5) / 8, (int(cell[1:]) - 0.5) / 8)


def U(type_, id_, x, y, rot):
    return AnswerItem(type_, id_, position=(x, y), rotation=rot)


def Gi(type_, id_, cells, d):
    return AnswerItem(type_, id_, cells=cells, direction=d)


def test_unmarked_modes_means_and_circular_mean():
    responses = [
        [U("plate", 80, 0.5, 0.5, 350), U("fork", 30, 0.3, 0.5, 0), U("cup", 1, 0.7, 0.3, 0)],
        [U("plate", 81, 0.6, 0.5, 10), U("fork", 30, 0.2, 0.5, 0), U("cup", 1, 0.8, 0.3, 0)],
        None,  # unparseable
        [U("plate", 81, 0.4, 0.5, 0), U("knife", 60, 0.9, 0.9, 90)],  # shorter: length 2
        [U("plate", 80, 0.5, 0.6, 0), U("fork", 31, 0.25, 0.5, 0), U("cup", 2, 0.75, 0.3, 0)],
    ]
    placements, diag = aggregate(responses, "unmarked")
    assert diag["n_responses"] == 5 and diag["n_parsed"] == 4 and not diag["failed"]
    assert diag["length"] == 3 and diag["length_agreement"] == 0.75
    assert [p.object for p in placements] == [80, 30, 1]  # 80 vs 81 tie -> first seen
    plate = placements[0]
    assert plate.x == pytest.approx(0.5) and plate.y == pytest.approx(0.525)  # mean of all four plates
    assert min(plate.rotation, 360 - plate.rotation) < 1e-6                 # circular mean of 350,10,0,0 = 0
    fork = placements[1]                                                     # knife (1 of 4) outvoted
    assert fork.x == pytest.approx((0.3 + 0.2 + 0.25) / 3) and diag["steps"][1]["type_agreement"] == 0.75
    assert diag["steps"][1]["id_agreement"] == pytest.approx(2 / 3, abs=1e-4)
    cup = placements[2]                                                      # only 3 responses have step 2
    assert cup.x == pytest.approx(0.75) and diag["steps"][2]["n"] == 3


def test_grid_weighted_cell_centres_and_directions():
    responses = [[Gi("plate", 80, ["D4", "D5"], "N")], [Gi("plate", 80, ["D4"], "E")]]
    placements, diag = aggregate(responses, "grid", G)
    # each response weighs the same: the mean of the responses' centroids (D4-D5's midpoint and D4)
    x = ((centre("D4")[0] + centre("D5")[0]) / 2 + centre("D4")[0]) / 2
    y = ((centre("D4")[1] + centre("D5")[1]) / 2 + centre("D4")[1]) / 2
    assert G.cell_center("D5") == pytest.approx(centre("D5"))
    assert (placements[0].x, placements[0].y) == pytest.approx((x, y))
    assert placements[0].rotation == pytest.approx(45.0)  # circular mean of N (0) and E (90)
    assert diag["steps"][0]["id"] == 80


def test_all_unparseable_is_a_failed_prediction_not_a_crash():
    placements, diag = aggregate([None, None, None], "grid", G)
    assert placements == [] and diag["failed"] and diag["n_parsed"] == 0
    assert aggregate([], "unmarked")[1]["failed"]


def test_duplicate_ids_across_steps_take_the_next_id_or_drop_the_step():
    responses = [
        [U("cup", 1, 0.1, 0.1, 0), U("cup", 1, 0.2, 0.2, 0), U("cup", 1, 0.3, 0.3, 0)],
        [U("cup", 1, 0.1, 0.1, 0), U("cup", 2, 0.2, 0.2, 0), U("cup", 1, 0.3, 0.3, 0)],
        [U("cup", 1, 0.1, 0.1, 0), U("cup", 1, 0.2, 0.2, 0), U("cup", 2, 0.3, 0.3, 0)],
    ]
    placements, diag = aggregate(responses, "unmarked")
    # step 0: cup 1; step 1: mode is 1 (used) -> 2; step 2: candidates 1, 2 both used -> dropped
    assert [p.object for p in placements] == [1, 2]
    assert diag["dropped_steps"] == [2] and diag["steps"][1]["id_mode"] == 1
    assert placements[1].x == pytest.approx(0.2)


def test_zero_length_mode_gives_an_empty_unfailed_prediction():
    placements, diag = aggregate([[], [], [U("cup", 1, 0.5, 0.5, 0)]], "unmarked")
    assert placements == [] and not diag["failed"] and diag["length"] == 0


def test_rotation_is_normalized_and_finite():
    placements, _ = aggregate([[U("cup", 1, 0.5, 0.5, 300)], [U("cup", 1, 0.5, 0.5, 320)]], "unmarked")
    assert placements[0].rotation == pytest.approx(310.0) and math.isfinite(placements[0].rotation)


# ------------------------------------------ object votes (greedy_votes_pooled's fallback without a greedy answer)


def test_votes_take_the_most_named_objects_in_their_mean_order():
    """Three answers naming the same objects in different orders: the paper's per-step modes mix them up, the
    votes keep each object whole (hand-computed)."""
    responses = [
        [Gi("cup", 1, ["A1"], "N"), Gi("plate", 2, ["B2"], "N"), Gi("fork", 3, ["C3"], "E")],
        [Gi("plate", 2, ["B3"], "N"), Gi("cup", 1, ["A1"], "S"), Gi("fork", 3, ["C3"], "E")],
        None,  # unparseable: no vote, no length
        [Gi("plate", 2, ["B2"], "N"), Gi("fork", 3, ["C4"], "E"), Gi("cup", 1, ["A2"], "N"),
         Gi("knife", 4, ["D1"], "W")],
    ]
    placements, diag = aggregate_votes(responses, "grid", G)
    assert diag["n_parsed"] == 3 and diag["length"] == 3  # median of 3, 3, 4
    assert diag["length_agreement"] == pytest.approx(2 / 3, abs=1e-4)
    # votes 3, 3, 3, 1 (knife out); mean steps: plate (1+0+0)/3, cup (0+1+2)/3, fork (2+2+1)/3
    assert [p.object for p in placements] == [2, 1, 3]
    assert [o["votes"] for o in diag["objects"]] == [3, 3, 3]
    plate = placements[0]  # each answer's centroid weighs the same: B2, B3, B2
    assert plate.x == pytest.approx(centre("B2")[0])
    assert plate.y == pytest.approx((2 * centre("B2")[1] + centre("B3")[1]) / 3)
    cup = placements[1]    # N, S, N: the circular mean of 0, 180, 0 is 0
    assert min(cup.rotation, 360 - cup.rotation) < 1e-6
    # the paper's aggregation of the same answers: step 0's mode is the plate; step 1's types tie (plate, cup,
    # fork) and the first seen, the plate, is placed already: the step is dropped and the cup lost; step 2: fork
    steps, sdiag = combine(responses, "grid", G)
    assert sdiag["aggregation"] == "steps" and [p.object for p in steps] == [2, 3] and sdiag["dropped_steps"] == [1]


def test_votes_break_ties_by_mean_step_then_first_seen_and_stop_at_the_median_length():
    responses = [
        [U("cup", 1, 0.1, 0.1, 0), U("fork", 5, 0.5, 0.5, 0)],
        [U("spoon", 7, 0.7, 0.7, 0), U("cup", 1, 0.1, 0.2, 0)],
        [U("knife", 9, 0.9, 0.9, 0)],
    ]
    placements, diag = aggregate_votes(responses, "unmarked")
    # median length 2; cup has 2 votes, then spoon (mean step 0) and knife (0) tie before fork (1): spoon seen first
    assert diag["length"] == 2 and [p.object for p in placements] == [7, 1]  # ordered by mean step: 0 vs 0.5
    assert placements[1].y == pytest.approx(0.15)


def test_votes_where_every_answer_fails_or_most_are_empty():
    placements, diag = aggregate_votes([None, None], "grid", G)
    assert placements == [] and diag["failed"]
    placements, diag = aggregate_votes([[], [], [U("cup", 1, 0.5, 0.5, 0)]], "unmarked")
    assert placements == [] and not diag["failed"] and diag["length"] == 0  # as the paper's: most answers empty


def test_one_answer_is_its_own_vote():
    answer = [U("plate", 80, 0.5, 0.5, 10), U("cup", 1, 0.7, 0.3, 200), U("fork", 30, 0.2, 0.5, 90)]
    placements, _ = aggregate_votes([answer], "unmarked")
    assert [(p.object, p.x, p.y) for p in placements] == [(it.id, *it.position) for it in answer]


def test_the_removed_aggregations_are_refused():
    """votes, greedy_votes and greedy_votes_context were removed (no shipped config used them); object votes remain
    greedy_votes_pooled's fallback when its greedy answer does not parse."""
    for removed in ("votes", "greedy_votes", "greedy_votes_context"):
        with pytest.raises(DegustaError, match=r"aggregation: expected one of \['steps', 'greedy_votes_pooled'\]"):
            combine([[U("cup", 1, 0.5, 0.5, 0)]], "unmarked", how=removed)


def test_unknown_aggregation_is_refused_in_python_configs_too():
    """The loader checks YAML and --set; a config built in Python is checked when made, not after the answers."""
    from degusta_learn.prompting.runner import ZeroShotConfig
    from degusta_learn.vlm.settings import DecodingSettings

    with pytest.raises(DegustaError, match="aggregation: expected one of"):
        combine([], "grid", G, how="vote")
    with pytest.raises(DegustaError, match="^decoding.aggregation: expected one of"):
        ZeroShotConfig(method="mogma", dataset="d", out="o", decoding=DecodingSettings(aggregation="vote"))
    with pytest.raises(DegustaError, match="^decoding.aggregation: expected one of"):
        DecodingSettings(aggregation="vote")


def test_greedy_votes_pooled_keeps_the_greedy_answers_objects_and_adds_the_most_voted_ones_it_lacks():
    """`greedy_votes_pooled` by hand: the greedy answer's 2 objects are kept; the samples' median length is 4, so the
    2 best-voted objects it lacks are added (votes 3 and 2, ties to the lower mean step); every object is placed at
    the mean of the answers naming it (the greedy one and the samples); never shortened; an unparseable greedy
    answer falls back to object votes."""
    greedy = [U("plate", 80, 0.5, 0.5, 0), U("fork", 30, 0.3, 0.5, 0)]
    samples = [
        [U("plate", 81, 0.4, 0.4, 0), U("cup", 1, 0.8, 0.3, 0), U("knife", 60, 0.7, 0.5, 0), U("fork", 30, 0.2, 0.5, 0)],
        [U("cup", 1, 0.6, 0.3, 0), U("knife", 60, 0.9, 0.5, 0), U("spoon", 50, 0.1, 0.1, 0), U("plate", 80, 0.5, 0.6, 0)],
        [U("cup", 1, 0.7, 0.3, 0), U("spoon", 50, 0.3, 0.1, 0), U("fork", 31, 0.1, 0.1, 0), U("knife", 61, 0.1, 0.9, 0)],
        None,
    ]
    placements, diag = combine(samples, "unmarked", how="greedy_votes_pooled", anchor=greedy)
    # votes: cup 3 (mean step 1/3), knife 60 2 (1.5), spoon 50 2 (1.5; knife 60 first seen), plate 80 (held), ...
    assert [p.object for p in placements] == [80, 30, 1, 60]
    # plate 80: (0.5, 0.5) greedy and (0.5, 0.6) sampled; fork 30: (0.3, 0.5) and (0.2, 0.5)
    assert (placements[0].x, placements[0].y) == pytest.approx((0.5, 0.55)) and placements[1].x == pytest.approx(0.25)
    assert placements[2].x == pytest.approx(0.7) and placements[3].x == pytest.approx(0.8)  # the voters' means
    assert diag["aggregation"] == "greedy_votes_pooled" and diag["anchor"] == 2 and diag["length"] == 4
    assert [a["id"] for a in diag["added"]] == [1, 60] and diag["added"][0]["votes"] == 3 and not diag["failed"]
    longer = greedy + [U("cup", 2, 0.1, 0.2, 0), U("cup", 3, 0.2, 0.2, 0), U("cup", 4, 0.3, 0.2, 0)]
    assert [p.object for p in combine(samples, "unmarked", how="greedy_votes_pooled", anchor=longer)[0]] == [
        80, 30, 2, 3, 4]
    alone, d = combine([None, None], "unmarked", how="greedy_votes_pooled", anchor=greedy)  # no sample parsed
    assert alone == [combine([greedy], "unmarked")[0][i] for i in range(2)] and d["failed"] is False
    fallback, d = combine(samples, "unmarked", how="greedy_votes_pooled", anchor=None)
    assert d["anchor"] == "unparsed" and fallback == aggregate_votes(samples, "unmarked")[0]
