"""The learned slot model: shapes, gradients to every parameter, decoding rules, overfitting, augmentations."""

from collections import Counter

import numpy as np
import pytest
import torch

from degusta_learn.baselines.learned.data import (
    DataConfig,
    TrainEpisodes,
    ValEpisodes,
    mirror,
    relabel,
    shuffle_mapping,
    swap_table,
)
from degusta_learn.baselines.learned.features import Vocab, onto_surface
from degusta_learn.baselines.learned.slot_model import ModelConfig, SlotModel
from degusta_learn.baselines.learned.slots import SlotEncoder, collate_slots, population_rows
from degusta_learn.errors import DegustaError
from degusta_learn.scene import make_episodes

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


def tiny(vocab, **kw) -> SlotModel:
    torch.manual_seed(0)
    cfg = dict(d_model=32, n_layers=1, n_heads=2, d_ff=64, dropout=0.0, max_objects=8)
    return SlotModel(ModelConfig(**{**cfg, **kw}), vocab)


@pytest.fixture
def setup(small_dataset):
    np.random.seed(0)
    vocab = Vocab.from_dataset(small_dataset)
    encode = SlotEncoder(vocab, small_dataset.tables, population_rows(small_dataset), 8)
    eps = [e for k in (0, 2, 4) for e in make_episodes(small_dataset, k, "train")]
    val = ValEpisodes(small_dataset, eps, encode)
    return small_dataset, vocab, val


def test_forward_backward_shapes(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    batch = collate_slots([val[i] for i in (0, 40, 80)])  # context 0, 2 and 4 in one batch
    B, S = batch["slot_mask"].shape
    out = model(batch)
    assert out["set"].shape == (B, S) and out["step"].shape == (B, S)
    assert out["obj"].shape == (B, S, vocab.n_objects)
    assert out["xy"].shape == (B, S, 2) and out["rot"].shape == (B, S, 2)
    # object log-probabilities: a distribution over the slot's own type only
    probs = out["obj"].exp()
    np.testing.assert_allclose(probs.sum(-1)[batch["slot_mask"]].detach().numpy(), 1.0, atol=1e-5)
    off_type = vocab.type_of_row[None, None] != batch["slot_type"].numpy()[..., None]
    assert (probs.detach().numpy()[off_type] == 0).all()
    losses = model.loss(batch, out)
    assert set(losses) == {"loss", "set", "object", "position", "rotation", "step"}
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_rotation_and_order_start_from_what_the_context_shows(setup):
    """With the heads' corrections at zero, every slot's rotation is its members' mean and its step their mean
    context step (the slot heuristic's answer): decoding then orders the slots and turns them as the context did."""
    from degusta_learn.baselines.learned.slot_model import MEAN_STEP

    ds, vocab, val = setup
    model = tiny(vocab)
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.zero_()
    batch = collate_slots([val[i] for i in (40, 80)])  # contexts 2 and 4
    out = model(batch)
    mask = batch["slot_mask"]
    mean_rot = torch.nn.functional.normalize(batch["slot_rot"], dim=-1)
    torch.testing.assert_close(out["rot"][mask], mean_rot[mask])
    torch.testing.assert_close(out["step"][mask], batch["slot_feat"][..., MEAN_STEP][mask])
    angle = torch.rad2deg(torch.atan2(out["rot"][..., 0], out["rot"][..., 1])) % 360.0
    assert angle[mask].std() > 1.0  # the context's rotations differ between slots: not one learned constant


def test_a_few_steps_change_every_parameter(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.0)  # no decay: only gradients move them
    for i in range(3):
        batch = collate_slots([val[j] for j in range(i, len(val), 7)])
        loss = model.loss(batch, model(batch))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    unchanged = [n for n, p in model.named_parameters() if torch.equal(p, before[n])]
    assert not unchanged, f"parameters without gradient: {unchanged}"


def test_decoding_respects_the_rules(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    batch = collate_slots([val[i] for i in range(0, len(val), 5)])
    objs, xys, rots = model.decode(batch, min_objects=3)
    types = vocab.type_of_row
    for b, (rows, xy, rot) in enumerate(zip(objs, xys, rots)):
        n_slots = int(batch["slot_mask"][b].sum())
        assert min(3, n_slots) <= len(rows) <= min(8, n_slots) and len(set(rows)) == len(rows)  # no object twice
        assert xy.shape == (len(rows), 2) and (rot >= 0).all() and (rot < 360).all()
        slot_types = batch["slot_type"][b, :n_slots].tolist()
        assert not Counter(types[rows].tolist()) - Counter(slot_types)  # each object fills a slot of its type


def test_overfits_a_handful_of_episodes(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    batch = collate_slots([val[i] for i in (40, 41, 42, 43)])  # four context-2 episodes
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    first = None
    for _ in range(150):
        loss = model.loss(batch, model(batch))["loss"]
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.1 * first
    objs, xys, _ = model.decode(batch, min_objects=1)
    for b, (rows, xy) in enumerate(zip(objs, xys)):
        set_slots = (batch["y_set"][b] > 0) & batch["slot_mask"][b]
        want = batch["y_obj"][b][set_slots].tolist()
        assert sorted(rows) == sorted(want)  # the target's objects (in the slots the context showed)
        true_xy = {o: xy_ for o, xy_ in zip(want, batch["y_xy"][b][set_slots].numpy())}
        err = xy - np.array([true_xy[o] for o in rows])
        assert np.abs(err - err.mean(0)).max() < 0.03  # right layout (a common shift is free for the metric)


def test_min_objects_and_bad_model_config(setup):
    ds, vocab, val = setup
    model = tiny(vocab)
    with torch.no_grad():
        model.head.bias[0] = -20.0  # "set nothing"
    objs, _, _ = model.decode(collate_slots([val[80]]), min_objects=3)
    assert len(objs[0]) == 3
    with pytest.raises(DegustaError, match="model.n_heads: 3 does not divide"):
        ModelConfig(d_model=32, n_heads=3)


def test_augmentations_keep_the_task(setup):
    ds, vocab, _ = setup
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
    encode = SlotEncoder(vocab, ds.tables, population_rows(ds), 8)
    ts = TrainEpisodes(ds, ds.participants, cfg, encode)
    s = ts[len(ts) - 1]
    assert len(s["y_obj"]) == len(s["slot_feat"]) and np.isfinite(s["slot_feat"]).all()


def test_onto_surface_pulls_points_inside(small_dataset):
    table = small_dataset.tables[1]  # round
    pts = onto_surface(table, np.array([[0.0, 0.0], [0.5, 0.5], [1.0, 0.5]]))
    assert table.contains(pts[:, 0], pts[:, 1]).all()
    np.testing.assert_allclose(pts[1], [0.5, 0.5])
