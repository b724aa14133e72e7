"""Aggregation of n answers, checked on hand-built responses with hand-computed results."""

from __future__ import annotations

import math

import pytest

from degusta_learn.prompting.aggregate import aggregate
from degusta_learn.prompting.answers import AnswerItem
from degusta_learn.render.grid import Grid

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
