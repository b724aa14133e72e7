"""The learned arrangement model: shapes, gradients to every parameter, decoding rules, overfitting."""

import numpy as np
import pytest
import torch

from degusta_learn.baselines.learned.data import (
    DataConfig, TrainEpisodes, ValEpisodes, mirror, relabel, shuffle_mapping, swap_table,
)
from degusta_learn.baselines.learned.decode import greedy_decode
from degusta_learn.baselines.learned.features import (
    Vocab, collate, onto_surface, position_features, table_geometry,
)
from degusta_learn.baselines.learned.model import ArrangementModel, ModelConfig
from degusta_learn.scene import make_episodes


@pytest.fixture(autouse=True)
def one_thread():
    """Two threads on a shared 2-core machine oversubscribe badly; tiny models run best on one."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def tiny(vocab, **kw) -> ArrangementModel:
    torch.manual_seed(0)
    cfg = dict(d_model=32, n_layers=1, n_heads=2, d_ff=64, dropout=0.0, max_objects=8)
    return ArrangementModel(ModelConfig(**{**cfg, **kw}), vocab)


@pytest.fixture
def setup(small_dataset):
    np.random.seed(0)
    vocab = Vocab.from_dataset(small_dataset)
    eps = [e for k in (0, 2, 4) for e in make_episodes(small_dataset, k, "train")]
    val = ValEpisodes(small_dataset, eps, vocab, max_objects=8)
    return small_dataset, vocab, val


def test_forward_backward_shapes(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    batch = collate([val[i] for i in (0, 40, 80)])  # context 0, 2 and 4 in one batch
    B, T = batch["y_obj"].shape
    out = model(batch)
    assert out["type_logits"].shape == (B, T + 1, len(vocab.types) + 1)
    assert out["obj_logits"].shape == (B, T, vocab.n_objects)
    assert out["place"]["xy"].shape == (B, T, 2) and out["place"]["mu"].shape == (B, T, 4, 2)
    losses = model.loss(batch, out)
    assert set(losses) == {"loss", "type", "object", "position", "rotation", "pointer"}
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("head", ["mixture", "mse"])
def test_a_few_steps_change_every_parameter(setup, head):
    ds, vocab, val = setup
    model = tiny(vocab, position_head=head)
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.0)  # no decay: only gradients move them
    for i in range(3):
        batch = collate([val[j] for j in range(i, len(val), 7)])
        loss = model.loss(batch, model(batch))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    unchanged = [n for n, p in model.named_parameters() if torch.equal(p, before[n])]
    assert not unchanged, f"parameters without gradient: {unchanged}"


def test_torch_position_features_match_numpy(small_dataset):
    table = small_dataset.tables[3]
    xy, rot = np.array([[0.3, 0.4], [0.7, 0.2]]), np.array([0.0, 135.0])
    geom = torch.tensor(table_geometry(table)[None])
    ours = ArrangementModel.position_features(torch.tensor(xy[None], dtype=torch.float32),
                                              torch.tensor(np.deg2rad(rot)[None], dtype=torch.float32), geom)
    np.testing.assert_allclose(ours[0].numpy(), position_features(table, xy, rot), atol=1e-6)


def test_decoding_respects_the_rules(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    batch = collate([val[i] for i in range(0, len(val), 5)])
    objs, xys, rots = greedy_decode(model, batch, min_objects=3)
    types = vocab.type_of_row
    for rows, xy, rot, geom in zip(objs, xys, rots, batch["tgt_geom"].numpy()):
        assert 3 <= len(rows) <= 8 and len(set(rows)) == len(rows)  # min count, no object twice
        assert xy.shape == (len(rows), 2) and (rot >= 0).all() and (rot < 360).all()
        assert (xy >= geom[0:2] - 1e-6).all() and (xy <= geom[2:4] + 1e-6).all()
        assert set(types[rows]) <= set(range(len(vocab.types)))


def test_overfits_a_handful_of_episodes(setup):
    ds, vocab, val = setup
    model = tiny(vocab, position_head="mse")
    batch = collate([val[i] for i in (40, 41, 42, 43)])  # four context-2 episodes
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    first = None
    for _ in range(150):
        loss = model.loss(batch, model(batch))["loss"]
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.1 * first
    objs, xys, _ = greedy_decode(model, batch, min_objects=1)
    for b, (rows, xy) in enumerate(zip(objs, xys)):
        n = int(batch["y_mask"][b].sum())
        assert rows == batch["y_obj"][b, :n].tolist()
        assert np.abs(xy - batch["y_xy"][b, :n].numpy()).max() < 0.03


def test_augmentations_keep_the_task(small_dataset):
    ds = small_dataset
    arr = ds.arrangements[0]
    back = mirror(mirror(arr, ds), ds)
    np.testing.assert_allclose(back.positions, arr.positions, atol=1e-9)
    np.testing.assert_allclose(back.rotations % 360, arr.rotations % 360, atol=1e-9)
    other = next(t for t in ds.tables if t != arr.table)
    moved = swap_table(arr, ds, other)
    assert moved.table == other and moved.objects == arr.objects
    table = ds.tables[other]
    assert table.contains(moved.positions[:, 0], moved.positions[:, 1]).all()
    d = lambda a: np.linalg.norm(a.positions[:, None] - a.positions[None], axis=-1)  # noqa: E731
    np.testing.assert_allclose(d(moved), d(arr), atol=0.02)  # physical spacing kept (small layouts)
    mapping = shuffle_mapping(ds, np.random.default_rng(0))
    assert sorted(mapping.values()) == sorted(mapping) and mapping != {k: k for k in mapping}
    assert all(ds.catalog[a].type == ds.catalog[b].type for a, b in mapping.items())  # a permutation within types
    assert relabel(arr, mapping).objects == [mapping[o] for o in arr.objects]
    cfg = DataConfig(table_swap=1.0, mirror=1.0, object_shuffle=1.0)
    ts = TrainEpisodes(ds, ds.participants, Vocab.from_dataset(ds), cfg, 8)
    s = ts[0]
    assert len(s["y_obj"]) == len(s["y_xy"]) and np.isfinite(s["y_feat"]).all()


def test_onto_surface_pulls_points_inside(small_dataset):
    table = small_dataset.tables[1]  # round
    pts = onto_surface(table, np.array([[0.0, 0.0], [0.5, 0.5], [1.0, 0.5]]))
    assert table.contains(pts[:, 0], pts[:, 1]).all()
    np.testing.assert_allclose(pts[1], [0.5, 0.5])
