"""`collaborative`: a hand-made dataset whose nearest training participants are known (and a closer validation
participant that must never be used), the consensus of k neighbours, own objects, the distance terms computed by
hand, the context-0 fallback, and bad config values."""

import functools

import numpy as np
import pytest

from degusta_learn.baselines.collaborative import (
    CollaborativeConfig,
    NeighbourModel,
    Profiles,
    distances,
)
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
    split_participants,
)
from degusta_learn.synth import naturalistic_with_styles

P1, P2, P3, P4 = 75, 76, 77, 78
F1, F2, F3 = 25, 26, 27
K2, K3 = 51, 52
C1, C2 = 0, 1
S1 = 100
IDS = [f"p{i:02d}" for i in range(10)]
SPLIT = split_participants(IDS, 0)  # 7 train, 1 val, 2 test
QUERY, OTHER_TEST = SPLIT["test"]
VAL = SPLIT["val"][0]
T1, T2, T3, *OTHERS = SPLIT["train"]


def _arr(participant, table, *rows):
    return Arrangement(participant, table, table, tuple(Placement(o, x, y, r) for o, x, y, r in rows))


def _person(participant, context_rows, target_rows):
    """Trials 0-3 on tables 0-3 with the same rows, trial 4 (the target) on table 4 (the slate bench)."""
    return [_arr(participant, t, *context_rows) for t in range(4)] + [_arr(participant, 4, *target_rows)]


@functools.lru_cache(maxsize=1)
def hand_made() -> Dataset:
    """The query sets a plate with a fork on its left on tables 0-3. T1 sets the same shape with other objects,
    T2 and T3 the same with the fork 0.02 and 0.04 further out; the other training participants a plate and a
    knife elsewhere. The validation participant copies the query exactly but sets only a cup on table 4."""
    people = [
        _person(QUERY, [(P1, 0.5, 0.5, 0.0), (F1, 0.35, 0.5, 0.0)], [(P1, 0.5, 0.5, 0.0)]),
        _person(VAL, [(P1, 0.5, 0.5, 0.0), (F1, 0.35, 0.5, 0.0)], [(C1, 0.2, 0.3, 0.0)]),
        _person(T1, [(P2, 0.5, 0.5, 0.0), (F2, 0.35, 0.5, 0.0)],
                [(P2, 0.50, 0.5, 0.0), (F2, 0.35, 0.5, 10.0), (C2, 0.60, 0.35, 0.0)]),
        _person(T2, [(P2, 0.5, 0.5, 0.0), (F2, 0.33, 0.5, 0.0)],
                [(P2, 0.52, 0.5, 0.0), (F3, 0.33, 0.5, 20.0), (C2, 0.64, 0.35, 0.0)]),
        _person(T3, [(P3, 0.5, 0.5, 0.0), (F3, 0.31, 0.5, 0.0)],
                [(P3, 0.54, 0.5, 0.0), (F3, 0.36, 0.5, 30.0), (S1, 0.70, 0.40, 0.0)]),
        _person(OTHER_TEST, [(P4, 0.4, 0.4, 0.0)], [(P4, 0.4, 0.4, 0.0)]),
    ]
    for j, other in enumerate(OTHERS):
        people.append(_person(other, [(P4, 0.3, 0.3, 0.0), (K3, 0.7, 0.7 - 0.05 * j, 90.0)],
                              [(P4, 0.3, 0.3, 0.0), (K3, 0.7, 0.7, 90.0)]))
    return Dataset(default_catalog(), {t.id: t for t in default_tables()}, [a for p in people for a in p])


def predict(ds=None, participant=QUERY, **keys):
    ds = ds or hand_made()
    spec = get_method("collaborative")
    episode = Episode(f"{participant}/t4", participant, (0, 1, 2, 3), 4, "generalization")
    return spec.run(spec.config_cls(method="collaborative", dataset="", out="", **keys), ds, [episode])[0]


# features: without the taste term (the query's red plastic has no twin in the catalog; T3's yellow happens to be
# nearer to it than T1's blue), the layout decides: T1's plate and fork sit where the query's do
@pytest.mark.parametrize("keys", [{"similarity": "tables"}, {"similarity": "features", "w_taste": 0.0}])
def test_the_nearest_training_participant_is_found_and_the_closer_validation_one_never_is(keys):
    p = predict(k=1, own_objects=False, **keys)
    assert p.diagnostics["neighbours"] == [T1]  # VAL is identical to the query, but not a training participant
    assert [q.object for q in p.placements] == [P2, F2, C2]  # T1's own arrangement on the target table
    np.testing.assert_allclose([[q.x, q.y] for q in p.placements], [[0.5, 0.5], [0.35, 0.5], [0.6, 0.35]], atol=1e-9)


def test_the_neighbours_are_ranked_by_similarity():
    p = predict(k=3, own_objects=False)
    assert p.diagnostics["neighbours"] == [T1, T2, T3]


def test_k_neighbours_are_combined_as_consensus_combines():
    p = predict(k=3, own_objects=False)
    # reference T1: plate and fork matched in all three (support 1), the cup in T1 and T2 (2/3 >= 0.5); T3's spoon
    # has no cup to match and is left out; majority ids, median positions (the cup's: of two), circular-mean rotations
    assert [q.object for q in p.placements] == [P2, F3, C2]
    np.testing.assert_allclose([[q.x, q.y] for q in p.placements], [[0.52, 0.5], [0.35, 0.5], [0.62, 0.35]], atol=1e-9)
    assert p.placements[1].rotation == pytest.approx(20.0)
    assert p.diagnostics["support"] == [1.0, 1.0, pytest.approx(2 / 3, abs=1e-3)]


def test_own_objects_replace_the_neighbours_by_type():
    p = predict(k=1, own_objects=True)
    # the query's plate and fork take the places of T1's; it has no cup, so T1's cup stays
    assert [q.object for q in p.placements] == [P1, F1, C2]


def test_a_training_participant_is_never_its_own_neighbour():
    ds = hand_made()
    model = NeighbourModel(ds, 0)
    context = [ds.arrangement(T1, t) for t in range(4)]
    near = [model.train[i] for i in model.nearest(context, CollaborativeConfig(method="collaborative", dataset="",
                                                                                out="", k=2, split="train"))]
    assert near == [T2, T3]


def test_the_features_distance_terms_by_hand():
    def profile(objects, types, colors, materials, layout):
        return Profiles(*(np.array([x], dtype=float) for x in (objects, types, colors, materials, layout)))

    query = profile([1.0, 0.5, 0.0], [2.0, 0.0], [1.0, 0.0], [0.5, 0.5], [[0.0, 0.0], [0.0, 0.0]])
    other = profile([0.5, 0.5, 0.5], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5], [[0.3, 0.4], [0.9, 0.9]])
    # objects: 1 - (0.5 + 0.5 + 0) / (1 + 0.5 + 0.5) = 0.5; types: 1 - 1 / 3; taste: (|1-0|+|0-1| + 0) / 4 = 0.5;
    # layout: type 0 set by both, 0.5 apart; type 1 only by the other: 1 -> 0.75
    for weights, expected in [((1, 0, 0, 0), 0.5), ((0, 1, 0, 0), 2 / 3), ((0, 0, 1, 0), 0.5), ((0, 0, 0, 1), 0.75),
                              ((1, 2, 3, 4), 0.5 + 4 / 3 + 1.5 + 3.0)]:
        assert distances(query, other, weights)[0] == pytest.approx(expected)
    assert distances(query, query, (1, 1, 1, 1))[0] == pytest.approx(0.0)


@functools.lru_cache(maxsize=1)
def small():
    return naturalistic_with_styles(2, n_participants=40)


def test_context_zero_falls_back_to_population_mean():
    ds, _ = small()
    episodes = make_episodes(ds, 0, "test")[:5]
    spec, population = get_method("collaborative"), get_method("population_mean")
    ours = spec.run(CollaborativeConfig(method="collaborative", dataset="", out="", context=0), ds, episodes)
    theirs = population.run(population.config_cls(method="population_mean", dataset="", out="", context=0), ds,
                            episodes)
    assert [p.placements for p in ours] == [p.placements for p in theirs]
    assert all(p.diagnostics["fallback"] == "population_mean" for p in ours)


def test_predictions_on_generated_data_are_valid_through_the_yaml_config(tmp_path):
    ds, _ = small()
    root = save_dataset(ds, tmp_path / "data")
    out = run_predict("configs/baseline_collaborative.yaml", [f"dataset={root}", f"out={tmp_path / 'p.jsonl'}",
                                                              "split=val", "k=3"])
    preds = read_predictions(out, ds.catalog)
    train = set(split_participants(ds.participants, 0)["train"])
    assert len(preds) == len(make_episodes(ds, 4, "val"))
    for p in preds:
        table = ds.tables[ds.arrangement(p.participant, p.target).table]
        xy = np.array([[q.x, q.y] for q in p.placements])
        assert p.method == "collaborative" and len(p.placements) >= 1
        assert len({q.object for q in p.placements}) == len(p.placements)
        assert table.contains(xy[:, 0], xy[:, 1]).all()
        assert len(p.diagnostics["neighbours"]) == 3 and set(p.diagnostics["neighbours"]) <= train


@pytest.mark.parametrize("keys, message", [
    ({"k": 0}, r"k: expected a number of neighbours >= 1"),
    ({"min_support": 2.0}, r"min_support: expected a share in \[0, 1\]"),
    ({"w_layout": -1.0}, r"w_layout: expected a weight >= 0"),
    ({"w_objects": 0.0, "w_types": 0.0, "w_taste": 0.0, "w_layout": 0.0}, r"at least one weight must be > 0"),
    ({"similarity": "cosine"}, r"similarity"),
])
def test_bad_values_are_refused_naming_the_key(keys, message):
    with pytest.raises(DegustaError, match=message):
        CollaborativeConfig(method="collaborative", dataset="", out="", **keys)
