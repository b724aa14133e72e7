"""Acceptability like for like: a prediction is judged by the kind of error the ratings were collected with.

The ratings judged complete scenes moved rigidly (unregistered RMSD of the move), so "acceptable at t" reads the
unregistered set RMSD; the paper's variant (Kabsch RMSD <= t) stays beside it as `acceptable_at_paper`.
"""

from __future__ import annotations

import math

import pytest

from degusta_learn.evaluate.scoring import EpisodeRow
from degusta_learn.evaluate.summary import summarize
from degusta_learn.metrics import ACCEPTABILITY_ERROR, PAPER_ACCEPTABILITY_ERROR, score_prediction
from degusta_learn.scene.types import Placement


def _row(participant: str, score) -> EpisodeRow:
    return EpisodeRow("m", f"{participant}/t1/k1", participant, 1, 1, "reconstruction", False, score.n_gt,
                      score.n_pred, score.n_matched, score.object_accuracy, score.rmsd, score.rmsd_unregistered,
                      score.count_error, score.set_rmsd, set_rmsd_unregistered=score.set_rmsd_unregistered)


def test_the_default_error_is_the_ratings_kind_and_the_papers_is_kabsch():
    assert ACCEPTABILITY_ERROR == "set_rmsd_unregistered" and PAPER_ACCEPTABILITY_ERROR == "rmsd"


def test_a_rigidly_shifted_copy_is_acceptable_to_the_paper_at_any_t_but_like_for_like_only_beyond_the_shift(
        small_dataset):
    ds = small_dataset
    gt = ds.arrangements[0]
    assert len(gt.placements) >= 3
    # the whole ground truth moved by (0.03, 0.04): every object 0.05 away, the shape unchanged
    moved = [Placement(p.object, p.x + 0.03, p.y + 0.04, p.rotation) for p in gt.placements]
    score = score_prediction(ds.catalog, gt, moved)
    assert score.rmsd == pytest.approx(0.0, abs=1e-9)  # Kabsch removes the move
    assert score.set_rmsd_unregistered == pytest.approx(0.05)  # sqrt(0.03^2 + 0.04^2) per object
    s = summarize([_row("p", score), _row("q", score)], n_bootstrap=20)["m"]
    assert s["acceptable_at_paper"] == {"0.01": 1.0, "0.05": 1.0, "0.10": 1.0}
    assert s["acceptable_at"]["0.01"] == 0.0 and s["acceptable_at"]["0.10"] == 1.0


def test_a_perfect_but_incomplete_answer_is_not_a_scene_the_raters_saw(small_dataset):
    ds = small_dataset
    gt = next(a for a in ds.arrangements if len(a.placements) >= 4)
    n = len(gt.placements)
    one = list(gt.placements[:1])  # one object, exactly where it belongs
    score = score_prediction(ds.catalog, gt, one)
    # the paper's variant: Kabsch RMSD of one pair is 0 -> acceptable everywhere
    assert score.rmsd == 0.0
    # like for like: c = 0.2 for each of the n - 1 missing objects, sqrt((n - 1) / n) * 0.2 >= 0.17 > 0.10
    assert score.set_rmsd_unregistered == pytest.approx(0.2 * math.sqrt((n - 1) / n))
    s = summarize([_row("p", score), _row("q", score)], n_bootstrap=20)["m"]
    assert s["acceptable_at_paper"]["0.01"] == 1.0 and s["acceptable_at"]["0.10"] == 0.0
