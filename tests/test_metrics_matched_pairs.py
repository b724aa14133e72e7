"""`metrics.matched_pairs`: the pairs behind an episode's scores, the same ones `score_prediction` matched."""

import dataclasses
import math

import pytest

from degusta_learn.metrics import matched_pairs, score_prediction
from degusta_learn.scene import Prediction


def shifted_prediction(ds, dx: float) -> Prediction:
    """The first participant's first table as its own answer, the first object shifted by dx."""
    pid = ds.participants[0]
    gt = ds.arrangement(pid, 0)
    placements = [dataclasses.replace(p, x=p.x + dx) if k == 0 else p for k, p in enumerate(gt.placements)]
    return Prediction(f"{pid}/t0", pid, 0, "test", placements)


def test_matched_pairs_are_the_scores_pairs(small_dataset):
    pred = shifted_prediction(small_dataset, 0.1)
    gt = small_dataset.arrangement(pred.participant, pred.target)
    pairs = matched_pairs(small_dataset.catalog, gt, pred)
    score = score_prediction(small_dataset.catalog, gt, pred.placements)
    assert len(pairs) == score.n_matched
    assert math.sqrt(sum(p.residual ** 2 for p in pairs) / len(pairs)) == pytest.approx(score.rmsd)
    assert math.sqrt(sum(p.distance ** 2 for p in pairs) / len(pairs)) == pytest.approx(score.rmsd_unregistered)
    assert sum(p.same_object for p in pairs) / score.n_gt == score.object_accuracy
    assert [p.pred_index for p in sorted(pairs, key=lambda p: p.pred_index)] == list(range(len(pairs)))
    assert matched_pairs(small_dataset.catalog, gt, dataclasses.replace(pred, failed=True)) == []
    assert matched_pairs(small_dataset.catalog, gt, []) == []
