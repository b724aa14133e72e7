"""`slot_heuristic`: a hand-made context whose slots, votes, supports and order are known, carrying onto another
table, the context-0 fallback, valid predictions on generated data, and bad config values."""

import functools

import numpy as np
import pytest

from degusta_learn.baselines.slot_heuristic import SlotHeuristicConfig
from degusta_learn.errors import DegustaError
from degusta_learn.methods import get_method, run_predict
from degusta_learn.scene import (
    Arrangement,
    Dataset,
    Episode,
    Placement,
    default_catalog,
    default_tables,
    make_episodes,
    read_predictions,
    save_dataset,
)
from degusta_learn.synth import naturalistic_with_styles

P1, P2, F1, F2, K1, K2, C1, S1 = 75, 76, 25, 26, 50, 51, 0, 100  # plates, forks, knives, a cup, a spoon
PLATE, FORK, KNIFE = (0.5, 0.5), (0.35, 0.5), (0.65, 0.5)
WALNUT, SLATE = 2, 4  # default tables: a square (0.06..0.94) and a wide bench (0.03..0.97 x 0.2..0.8)


def _arr(trial, table, *rows):
    return Arrangement("a", trial, table, tuple(Placement(o, x, y, r) for o, x, y, r in rows))


def hand_made(context_table=WALNUT) -> Dataset:
    """Four context trials on one table (step order as listed), a target trial on the slate bench, and a
    trial 5 with one spoon elsewhere.

    plate slot  (0.5, 0.5):  P1 P1 P1 P2 -> support 1,   voted P1, steps 0 0 0 0
    fork slot   (0.35, 0.5): F1 F1 F2    -> support 3/4, voted F1, steps 1 2 2 (mean 1.67), rotations 350 10 0
    knife slot  (0.65, 0.5): K1 K2       -> support 1/2, a 1-1 tie that K2 wins (held in 2 trials, K1 in 1), steps 2 1
    cup (0.5, 0.2), spoon (0.8, 0.8), a far knife K2 (0.2, 0.8): support 1/4 each
    """
    t = context_table
    arrangements = [
        _arr(0, t, (P1, *PLATE, 0.0), (F1, *FORK, 350.0), (K1, *KNIFE, 90.0), (C1, 0.5, 0.2, 0.0)),
        _arr(1, t, (P1, *PLATE, 0.0), (K2, 0.2, 0.8, 45.0), (F1, *FORK, 10.0)),
        _arr(2, t, (P1, *PLATE, 0.0), (S1, 0.8, 0.8, 0.0), (F2, *FORK, 0.0)),
        _arr(3, t, (P2, *PLATE, 0.0), (K2, *KNIFE, 90.0)),
        _arr(4, SLATE, (P1, 0.5, 0.5, 0.0)),
        _arr(5, t, (S1, 0.8, 0.2, 0.0)),
    ]
    return Dataset(default_catalog(), {x.id: x for x in default_tables()}, arrangements)


def predict(ds, context=(0, 1, 2, 3), target=4, **keys):
    spec = get_method("slot_heuristic")
    episode = Episode("a/t4", "a", tuple(context), target, "generalization")
    return spec.run(spec.config_cls(method="slot_heuristic", dataset="", out="", **keys), ds, [episode])[0]


def _xy(prediction):
    return np.array([[p.x, p.y] for p in prediction.placements])


def test_supported_slots_voted_objects_mean_positions_and_step_order():
    ds = hand_made(context_table=SLATE)  # context and target on the same table: positions come back as they were
    p = predict(ds)
    # order by mean step: plate 0, knife 1.5, fork 1.67 (the slots were found in the order plate, fork, knife)
    assert [q.object for q in p.placements] == [P1, K2, F1]
    np.testing.assert_allclose(_xy(p), [PLATE, KNIFE, FORK], atol=1e-9)
    rot = [q.rotation for q in p.placements]
    assert rot[1] == pytest.approx(90.0)
    assert min(rot[2], 360.0 - rot[2]) == pytest.approx(0.0, abs=1e-6)  # circular mean of 350, 10, 0
    assert p.diagnostics["support"] == [1.0, 0.5, 0.75] and p.diagnostics["slots"] == 6


@pytest.mark.parametrize("min_support, objects", [(0.75, [P1, F1]), (1.0, [P1]), (0.25, [P1, K2, F1, C1, S1])])
def test_min_support_decides_which_slots_are_set(min_support, objects):
    p = predict(hand_made(context_table=SLATE), min_support=min_support)
    # at 0.25 the far knife slot (K2 alone) loses K2 to the better-supported knife slot and stays empty
    assert sorted(q.object for q in p.placements) == sorted(objects)


def test_carrying_onto_another_table_keeps_the_physical_spacing():
    p = predict(hand_made(context_table=WALNUT))  # context on the square, target on the wide bench
    xy = _xy(p)
    np.testing.assert_allclose(xy[1] - xy[0], np.subtract(KNIFE, PLATE), atol=1e-9)  # offsets kept, not rescaled
    np.testing.assert_allclose(xy[2] - xy[0], np.subtract(FORK, PLATE), atol=1e-9)
    slate = ds_table(SLATE)
    assert slate.contains(xy[:, 0], xy[:, 1]).all()


def ds_table(table_id):
    return {x.id: x for x in default_tables()}[table_id]


def test_no_slot_reaching_the_threshold_sets_the_best_supported_one():
    ds = hand_made(context_table=SLATE)
    p = predict(ds, context=(3, 5), min_support=1.0)  # plate, knife and spoon 1/2 each: the first slot found
    assert [q.object for q in p.placements] == [P2]
    p = predict(ds, context=(0, 3), min_support=1.0)  # plate 1, knife 1: the cup and fork (1/2) are not set
    assert [q.object for q in p.placements] == [P1, K1]  # knife tie K1 / K2, each held once: the smaller id


def test_context_zero_falls_back_to_population_mean():
    ds, _ = small()
    episodes = make_episodes(ds, 0, "test")[:5]
    spec, population = get_method("slot_heuristic"), get_method("population_mean")
    ours = spec.run(SlotHeuristicConfig(method="slot_heuristic", dataset="", out="", context=0), ds, episodes)
    theirs = population.run(population.config_cls(method="population_mean", dataset="", out="", context=0), ds,
                            episodes)
    assert [p.placements for p in ours] == [p.placements for p in theirs]
    assert all(p.diagnostics["fallback"] == "population_mean" for p in ours)


@functools.lru_cache(maxsize=1)
def small():
    return naturalistic_with_styles(2, n_participants=40)


def test_predictions_on_generated_data_are_valid_through_the_yaml_config(tmp_path):
    ds, _ = small()
    root = save_dataset(ds, tmp_path / "data")
    out = run_predict("configs/baseline_slot_heuristic.yaml",
                      [f"dataset={root}", f"out={tmp_path / 'p.jsonl'}", "split=val"])
    preds = read_predictions(out, ds.catalog)
    assert len(preds) == len(make_episodes(ds, 4, "val"))
    for p in preds:
        table = ds.tables[ds.arrangement(p.participant, p.target).table]
        xy = _xy(p)
        assert p.method == "slot_heuristic" and len(p.placements) >= 1
        assert len({q.object for q in p.placements}) == len(p.placements)  # an object fills one slot
        assert table.contains(xy[:, 0], xy[:, 1]).all()


@pytest.mark.parametrize("value", [-0.1, 1.5])
def test_a_share_outside_zero_one_is_refused(value):
    with pytest.raises(DegustaError, match=r"min_support: expected a share in \[0, 1\]"):
        SlotHeuristicConfig(method="slot_heuristic", dataset="", out="", min_support=value)
