"""No score that a shortcut can win: the shortcut transformations of benchmarks/bench_shortcuts.py (truncate, pad,
whole catalog, one answer for everyone, reversed order, rotations 0) against the metrics and `compare`'s ranking,
on hand-made cases (hand-computed values) and on the naturalistic test split with baselines computed in-process."""

import math
from dataclasses import replace

import numpy as np
import pytest

from benchmark_support import load_benchmark
from degusta_learn.evaluate.scoring import score_predictions
from degusta_learn.evaluate.summary import rank_methods, summarize
from degusta_learn.metrics import SET_PENALTY as C
from degusta_learn.metrics import score_many
from degusta_learn.scene import Arrangement, Placement, Prediction, load_dataset, make_episodes
from degusta_learn.synth import generate_dataset

bench = load_benchmark("bench_shortcuts")
SHORTCUTS = ("truncate to 1", "truncate to 2", "truncate to 3", "pad +1", "pad x2", "whole catalog",
             "constant (first answer)", "constant (best table)", "reverse order", "rotations 0")
UNCHANGED = ("reverse order", "rotations 0")
"""Shortcuts that leave the objects and their spots as they are: set RMSD must not move at all."""


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    """The embedded naturalistic default, generated here (a fresh clone has no data/ folder; 1-2 s)."""
    return load_dataset(generate_dataset("naturalistic", tmp_path_factory.mktemp("data") / "naturalistic"))


# -- hand-made: one ground truth of 4 objects, hand-computed scores -------------------------------------------------

# A cup, a fork, a knife and a spoon (symmetry order 1: every turn counts) on table 0, turned 30, 60, 90, 120.
GT = Arrangement("p", 1, 0, (Placement(0, 0.3, 0.3, 30.0), Placement(25, 0.5, 0.3, 60.0),
                             Placement(50, 0.5, 0.6, 90.0), Placement(100, 0.3, 0.6, 120.0)))


def _perfect(method="m", gt=GT):
    return Prediction(f"{gt.participant}/t{gt.trial}/k0", gt.participant, gt.trial, method, list(gt.placements))


class _OneEpisode:
    """The smallest stand-in for a Dataset the transformations need: the catalog, the tables, one ground truth."""

    def __init__(self, ds, gts):
        self.catalog, self.tables, self._gts = ds.catalog, ds.tables, {(g.participant, g.trial): g for g in gts}

    def arrangement(self, participant, trial):
        return self._gts[participant, trial]


def _score(ds, preds, gts=(GT,)):
    return score_many(ds.catalog, list(gts), preds, tables=ds.tables)


def test_hand_made_truncation_padding_and_catalog_cost_what_the_formula_says(ds):
    fake = _OneEpisode(ds, [GT])
    pred = [_perfect()]
    (orig,) = _score(ds, pred)
    assert orig.set_rmsd == pytest.approx(0.0, abs=1e-9) and orig.rmsd == pytest.approx(0.0, abs=1e-12) and orig.object_accuracy == 1.0
    # Truncation: the k kept objects are perfect (Kabsch RMSD 0 always), the 4 - k missing cost c^2 each.
    for k in (1, 2, 3):
        (s,) = _score(ds, bench.truncate(k)(pred, fake))
        assert s.set_rmsd == pytest.approx(C * math.sqrt((4 - k) / 4), abs=1e-12)
        assert s.rmsd == pytest.approx(0.0, abs=1e-9) and s.object_accuracy == k / 4 and s.n_pred == k
    # Padding with 4 others: every true object still matched by its own id (accuracy 1), 4 extra cost c^2 over 8.
    (s,) = _score(ds, bench.pad(None)(pred, fake))
    assert (s.n_pred, s.object_accuracy, s.object_precision) == (8, 1.0, 0.5)
    assert s.set_rmsd == pytest.approx(C / math.sqrt(2), abs=1e-12)
    # The whole catalog: object accuracy 1.0, the best the paper's column can be, and set RMSD near c.
    (s,) = _score(ds, bench.whole_catalog()(pred, fake))
    assert (s.n_pred, s.object_accuracy) == (len(ds.catalog), 1.0)
    assert s.set_rmsd == pytest.approx(C * math.sqrt((len(ds.catalog) - 4) / len(ds.catalog)), abs=1e-12)


def test_hand_made_order_and_rotation_move_only_the_task_plan_metrics(ds):
    fake = _OneEpisode(ds, [GT])
    pred = [_perfect()]
    (orig,) = _score(ds, pred)
    (rev,) = _score(ds, bench.reverse_order()(pred, fake))
    (flat,) = _score(ds, bench.zero_rotations()(pred, fake))
    assert (orig.order_tau, orig.rotation_error) == (1.0, 0.0)
    assert rev.order_tau == -1.0 and rev.rotation_error == 0.0  # fully reversed: tau -1
    assert flat.order_tau == 1.0 and flat.rotation_error == pytest.approx((30 + 60 + 90 + 120) / 4)
    for s in (rev, flat):
        assert s.object_accuracy == 1.0
        assert (s.set_rmsd, s.set_rmsd_unregistered) == pytest.approx((0.0, 0.0), abs=1e-9)
    # A shift of the whole arrangement: set RMSD registers it away, its unregistered twin sees all of it.
    (moved,) = _score(ds, bench.shift_x(0.1)(pred, fake))
    assert moved.set_rmsd == pytest.approx(0.0, abs=1e-9) and moved.set_rmsd_unregistered == pytest.approx(0.1)


def test_hand_made_constant_answer_and_the_one_truncation_that_may_gain(ds):
    other = Arrangement("q", 1, 0, (Placement(1, 0.7, 0.7, 0.0), Placement(26, 0.8, 0.7, 0.0),
                                    Placement(51, 0.8, 0.8, 0.0)))
    gts = [GT, other]
    fake = _OneEpisode(ds, gts)
    preds = [_perfect("m", GT), _perfect("m", other)]
    # Everyone gets GT's table: perfect for p; for q three wrong objects (different ids), 4 vs 3 objects.
    s_p, s_q = _score(ds, bench.constant(list(GT.placements))(preds, fake), gts)
    assert s_p.set_rmsd == pytest.approx(0.0, abs=1e-9) and s_q.object_accuracy == 0.0 and s_q.count_error == 1
    assert (s_p.set_rmsd + s_q.set_rmsd) / 2 > 0.0  # the perfect answers' mean
    # Cutting a *surplus* object is a real improvement, and set RMSD says so: one wrong extra costs
    # sqrt(c^2 / 4) = c / 2, truncating back to the 3 true objects scores 0.
    extra = [replace(preds[1], placements=[*other.placements, Placement(100, 0.2, 0.2, 0.0)])]
    (before,) = _score(ds, extra, [other])
    (after,) = _score(ds, bench.truncate(3)(extra, _OneEpisode(ds, [other])), [other])
    assert before.set_rmsd == pytest.approx(C / 2) and after.set_rmsd == pytest.approx(0.0, abs=1e-9)


# -- the naturalistic test split, context 4 -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def split(ds):
    episodes = make_episodes(ds, 4, "test", 0)
    best = bench.best_constant(ds, episodes[::4])  # the best of 50 of the split's own tables, as a constant answer
    return episodes, best


def _transformed(ds, episodes, method, best):
    preds = bench.run_method(method, ds, episodes)
    return preds, {name: fn(preds, ds) for name, fn in bench.shortcuts(ds, episodes, preds, best).items()}


def _mean(scores, field):
    return float(np.nanmean([getattr(s, field) for s in scores]))


@pytest.mark.parametrize("method", ["consensus", "copy_nearest", "oracle"])
def test_no_shortcut_lowers_mean_set_rmsd(ds, split, method):
    episodes, best = split
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    preds, variants = _transformed(ds, episodes, method, best)
    orig = _score(ds, preds, gts)
    for name in SHORTCUTS:
        scores = _score(ds, variants[name], gts)
        if name in UNCHANGED:  # the same objects at the same spots: every set score is the same, episode by episode
            assert [s.set_rmsd for s in scores] == pytest.approx([s.set_rmsd for s in orig], abs=1e-12), name
            assert _mean(scores, "object_accuracy") == _mean(orig, "object_accuracy"), name
        else:
            assert _mean(scores, "set_rmsd") > _mean(orig, "set_rmsd") + 0.01, name
    # ... while the task-plan metrics see order and rotation: tau turns over, the rotation error grows.
    rev, flat = _score(ds, variants["reverse order"], gts), _score(ds, variants["rotations 0"], gts)
    assert _mean(rev, "order_tau") == pytest.approx(-_mean(orig, "order_tau"), abs=1e-9)
    assert _mean(orig, "order_tau") > 0.4
    assert _mean(flat, "rotation_error") > _mean(orig, "rotation_error") + 10.0
    # The paper's columns are what the shortcuts move: truncation flatters Kabsch RMSD, the catalog accuracy.
    assert _mean(_score(ds, variants["truncate to 1"], gts), "rmsd") == pytest.approx(0.0, abs=1e-9)
    assert _mean(_score(ds, variants["whole catalog"], gts), "object_accuracy") == 1.0


def test_truncation_gains_only_where_the_answer_was_too_long(ds, split):
    """population_mean gives 4-5 objects to tables of 3: cutting it to 3 lowers its mean set RMSD a little, all of
    it on those over-long answers (a surplus wrong object removed); where its answer was not longer than the truth,
    truncation costs on average."""
    episodes, best = split
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    preds, variants = _transformed(ds, episodes, "population_mean", best)
    orig = _score(ds, preds, gts)
    long = np.array([s.n_pred > s.n_gt for s in orig])
    for k in (1, 2, 3):
        delta = np.array([t.set_rmsd - o.set_rmsd for o, t in zip(orig, _score(ds, variants[f"truncate to {k}"], gts))])
        assert delta[~long].mean() > 0.002, k  # 0.040, 0.024, 0.004 on the default (k = 1, 2, 3)


@pytest.mark.parametrize("method", ["consensus", "copy_nearest"])
def test_compare_ranks_the_original_above_every_shortcut(ds, split, method):
    episodes, best = split
    preds = bench.run_method(method, ds, episodes)
    table = {name: fn for name, fn in bench.shortcuts(ds, episodes, preds, best).items() if name in SHORTCUTS}
    rows = bench.transformed_rows(ds, episodes, preds, method, table)
    summary = summarize(rows, n_bootstrap=20)
    assert rank_methods(summary)[0] == method
    reasons = {m: s["degenerate_reasons"] for m, s in summary.items()}
    assert reasons[method] == []
    assert "too few" in reasons["truncate to 1"] and "too few" in reasons["truncate to 2"]
    assert reasons["whole catalog"] == ["padding"]
    assert "constant" in reasons["constant (first answer)"] and "constant" in reasons["constant (best table)"]
    for name in ("truncate to 3", "pad +1", "reverse order", "rotations 0"):
        assert reasons[name] == [], name  # not degenerate: ranked by set RMSD, and still below the original
    # Count bias says which way the count went: the original about right, truncation below, padding above.
    bias = {m: s["count_bias"]["mean"] for m, s in summary.items()}
    assert abs(bias[method]) < 0.5 and bias["truncate to 1"] < -2.5 and bias["pad +1"] == pytest.approx(bias[method] + 1)
    assert bias["whole catalog"] > 100


def test_answer_keys_of_a_constant_answer_agree(ds, split):
    episodes, best = split
    preds = bench.constant(best)(bench.run_method("consensus", ds, episodes[:10]), ds)
    rows = score_predictions(ds, preds, {e.id: e for e in episodes})
    assert len({r.answer_key for r in rows}) == 1 and rows[0].answer_key is not None
    own = score_predictions(ds, bench.run_method("consensus", ds, episodes[:10]), {e.id: e for e in episodes})
    assert len({r.answer_key for r in own}) == 10  # a real method's answers differ from episode to episode
