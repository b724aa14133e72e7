"""Heuristic baselines: valid predictions, no test-participant leakage, fallbacks, and the expected ordering."""

import dataclasses
import functools

import numpy as np
import pytest

from degusta_learn.baselines import heuristic as H
from degusta_learn.baselines.transfer import table_distance
from degusta_learn.errors import DegustaError
from degusta_learn.methods import get_method, run_predict
from degusta_learn.metrics import score_many
from degusta_learn.scene import (
    Dataset,
    Episode,
    Placement,
    make_episodes,
    read_predictions,
    split_participants,
)
from degusta_learn.synth import generate_dataset, naturalistic_with_styles, simulated_with_styles
from degusta_learn.synth.oracle import predict_oracle

NAMES = ("random", "population_mean", "copy_nearest", "consensus")


@functools.lru_cache(maxsize=1)
def small():
    return naturalistic_with_styles(2, n_participants=60)


def predict(name, ds, episodes, **keys):
    spec = get_method(name)
    return spec.run(spec.config_cls(method=name, dataset="", out="", **keys), ds, episodes)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("context", [0, 4])
def test_predictions_are_valid(name, context):
    ds, _ = small()
    episodes = make_episodes(ds, context, "test")
    preds = predict(name, ds, episodes)
    assert [p.episode for p in preds] == [e.id for e in episodes]
    for p, e in zip(preds, episodes):
        table = ds.tables[ds.arrangement(e.participant, e.target).table]
        assert p.method == name and not p.failed and len(p.placements) >= 1
        assert len({q.object for q in p.placements}) == len(p.placements)
        xy = np.array([[q.x, q.y] for q in p.placements])
        assert table.contains(xy[:, 0], xy[:, 1]).all()


def test_predictions_file_round_trip(tmp_path):
    folder = generate_dataset("simulated", tmp_path / "simulated")
    out = run_predict(None, ["method=consensus", f"dataset={folder}", f"out={tmp_path / 'p.jsonl'}", "context=2"])
    ds = simulated_with_styles(0)[0]
    preds = read_predictions(out, ds.catalog)
    assert len(preds) == 4 * 12 and all(p.method == "consensus" for p in preds)  # 4 test participants


def test_random_counts_and_determinism():
    ds, _ = small()
    episodes = make_episodes(ds, 4, "test")
    a = predict("random", ds, episodes, min_objects=4, max_objects=5)
    b = predict("random", ds, episodes, min_objects=4, max_objects=5)
    assert [p.to_json() for p in a] == [p.to_json() for p in b]
    assert {len(p.placements) for p in a} == {4, 5}
    with pytest.raises(DegustaError, match="min_objects"):
        H.RandomConfig(method="random", dataset="", out="", min_objects=6, max_objects=5)


def test_population_mean_never_reads_test_participants():
    ds, _ = small()
    split = split_participants(ds.participants, 0)
    episodes = make_episodes(ds, 4, "test")
    before = predict("population_mean", ds, episodes)
    # the test participants now all set one absurd arrangement: nothing the population sees may change
    test = set(split["test"])
    weird = [a if a.participant not in test else dataclasses.replace(a, placements=tuple(
        Placement(o, 0.5 + 0.01 * i, 0.5, 123.0) for i, o in enumerate((124, 123, 122, 121, 120, 119, 118))))
        for a in ds.arrangements]
    after = predict("population_mean", Dataset(ds.catalog, ds.tables, weird), episodes)
    assert [p.placements for p in after] == [p.placements for p in before]
    model = H.PopulationModel(ds, seed=0)
    assert {a.participant for a in model.arrangements} == set(split["train"])


@pytest.mark.parametrize("name", ["copy_nearest", "consensus"])
def test_context_zero_falls_back_to_population_mean(name):
    ds, _ = small()
    episodes = make_episodes(ds, 0, "test")
    preds, pop = predict(name, ds, episodes), predict("population_mean", ds, episodes)
    assert [p.placements for p in preds] == [p.placements for p in pop]
    assert all(p.diagnostics["fallback"] == "population_mean" for p in preds)


def test_copy_nearest_prefers_the_same_then_the_most_similar_table():
    ds, _, episodes = simulated_with_styles(0)
    preds = predict("copy_nearest", ds, episodes)
    for p, e in zip(preds, episodes):
        target_table = ds.arrangement(e.participant, e.target).table
        source = ds.arrangement(e.participant, p.diagnostics["source_trial"])
        if e.task == "reconstruction":
            assert source.table == target_table and source.trial == max(e.context)
            assert [q.object for q in p.placements] == list(source.objects)
            assert np.allclose([[q.x, q.y] for q in p.placements], source.positions)  # same table: a copy
    tables = {t.name: t for t in naturalistic_with_styles(0, 1)[0].tables.values()}
    assert table_distance(tables["oak"], tables["oak"]) == 0.0
    assert table_distance(tables["marble"], tables["white"]) < table_distance(tables["marble"], tables["oak"])
    assert table_distance(tables["oak"], tables["slate"]) < table_distance(tables["oak"], tables["marble"])


def test_consensus_of_identical_contexts_is_that_arrangement_and_outvotes_an_odd_one():
    ds, _ = small()
    base = ds.arrangements[0]
    odd = dataclasses.replace(base, trial=3, placements=base.placements[:-1] + (
        dataclasses.replace(base.placements[-1], x=base.placements[-1].x + 0.05),))
    arrs = [dataclasses.replace(base, trial=t) for t in range(3)] + [odd, dataclasses.replace(base, trial=4)]
    toy = Dataset(ds.catalog, ds.tables, arrs)
    preds = predict("consensus", toy, [Episode("e", base.participant, (0, 1, 2, 3), 4, "reconstruction")])
    assert [q.object for q in preds[0].placements] == list(base.objects)
    assert np.allclose([[q.x, q.y] for q in preds[0].placements], base.positions)


def test_oracle_beats_copy_nearest_beats_population_mean():
    ds, styles = small()
    episodes = make_episodes(ds, 4, "test")
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    scores = {name: score_many(ds.catalog, gts, preds) for name, preds in [
        ("oracle", predict_oracle(ds, {s.participant: s for s in styles}, episodes)),
        ("copy_nearest", predict("copy_nearest", ds, episodes)),
        ("population_mean", predict("population_mean", ds, episodes))]}
    rmsd = {k: np.nanmean([s.rmsd for s in v]) for k, v in scores.items()}
    acc = {k: np.mean([s.object_accuracy for s in v]) for k, v in scores.items()}
    assert rmsd["oracle"] * 1.5 < rmsd["copy_nearest"] < rmsd["population_mean"]
    assert acc["oracle"] > acc["copy_nearest"] + 0.1 > acc["population_mean"] + 0.2
