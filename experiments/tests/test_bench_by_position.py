"""benchmarks/by_position.py and `metrics.matched_pairs`: error by the item's place in the answer."""

import dataclasses
import math

import pytest
from benchmark_support import load_benchmark

from degusta_learn.metrics import matched_pairs, score_prediction
from degusta_learn.scene import Prediction


def predictions(ds, moved_item: int | None = None, dx: float = 0.0):
    """The ground truth itself as every episode's answer; item `moved_item` (0-based) shifted by dx."""
    out = []
    for pid in ds.participants[:4]:
        for trial in range(3):
            gt = ds.arrangement(pid, trial)
            placements = [dataclasses.replace(p, x=p.x + dx) if k == moved_item else p
                          for k, p in enumerate(gt.placements)]
            out.append(Prediction(f"{pid}/t{trial}", pid, trial, "test", placements))
    return out


def test_the_ground_truth_is_right_and_exact_at_every_place(small_dataset):
    rows = load_benchmark("by_position").by_position(small_dataset, predictions(small_dataset), last=3)
    assert [r["item"] for r in rows] == [1, 2, 3] and rows[-1]["pooled"]
    for r in rows:
        assert r["right_id"] == 1.0 and r["distance"] == pytest.approx(0, abs=1e-12)
        assert r["distance_right"] == pytest.approx(0, abs=1e-12) and math.isnan(r["distance_wrong"])
        assert r["residual"] == pytest.approx(0, abs=1e-9)


def test_an_item_moved_in_every_answer_shows_in_its_row_only(small_dataset):
    rows = load_benchmark("by_position").by_position(small_dataset, predictions(small_dataset, 1, 0.05), last=9)
    assert rows[1]["distance"] == pytest.approx(0.05)  # the moved item, unregistered
    assert all(r["distance"] == pytest.approx(0, abs=1e-12) for r in rows if r["item"] != 2)
    assert rows[1]["residual"] > max(r["residual"] for r in rows if r["item"] != 2)  # registration spreads it


def test_matched_pairs_are_the_scores_pairs(small_dataset):
    pred = predictions(small_dataset, 0, 0.1)[0]
    gt = small_dataset.arrangement(pred.participant, pred.target)
    pairs = matched_pairs(small_dataset.catalog, gt, pred)
    score = score_prediction(small_dataset.catalog, gt, pred.placements)
    assert len(pairs) == score.n_matched
    assert math.sqrt(sum(p.residual ** 2 for p in pairs) / len(pairs)) == pytest.approx(score.rmsd)
    assert math.sqrt(sum(p.distance ** 2 for p in pairs) / len(pairs)) == pytest.approx(score.rmsd_unregistered)
    assert sum(p.same_object for p in pairs) / score.n_gt == score.object_accuracy
    assert matched_pairs(small_dataset.catalog, gt, dataclasses.replace(pred, failed=True)) == []
    assert matched_pairs(small_dataset.catalog, gt, []) == []


def test_teacher_forced_items_assigns_each_value_token_to_its_item_and_field():
    fields = load_benchmark("teacher_forced_items").token_fields
    pieces = ["[{'", "type", "': '", "plate", "', '", "id", "': ", "75", ", '", "position", "': ['", "G5", "', '",
              "E6", "'], '", "cardinal_direction", "': '", "N", "'}, {'", "type", "': '", "knife", "', '", "id", "': ",
              "56", ", '", "position", "': ['", "D2", "'], '", "cardinal_direction", "': '", "SW", "'}]"]
    got = [(p, f) for p, f in zip(pieces, fields(pieces)) if f is not None]
    assert got == [("plate", (0, "'type'")), ("75", (0, "'id'")), ("G5", (0, "'position'")), ("E6", (0, "'position'")),
                   ("N", (0, "'cardinal_direction'")), ("knife", (1, "'type'")), ("56", (1, "'id'")),
                   ("D2", (1, "'position'")), ("SW", (1, "'cardinal_direction'"))]
