"""Slot encoding (slots.py): one slot per recurring object, registration, carrying, labels, context 0."""

from dataclasses import replace

import numpy as np

from degusta_learn.baselines.learned.features import Vocab
from degusta_learn.baselines.learned.slots import SLOT_DIM, SlotEncoder, collate_slots, population_rows
from degusta_learn.scene import Placement


def shifted(arr, dx, dy):
    return replace(arr, placements=tuple(Placement(p.object, p.x + dx, p.y + dy, p.rotation) for p in arr.placements))


def encoder(ds):
    vocab = Vocab.from_dataset(ds)
    return vocab, SlotEncoder(vocab, ds.tables, population_rows(ds), 20)


def test_one_slot_per_recurring_object_and_labels_from_the_target(small_dataset):
    ds = small_dataset
    vocab, encode = encoder(ds)
    a, b, c = ds.trials_of("p000")[:3]  # one person's fixed layout on three tables
    s = encode([a, b], c.table, c)
    n = len(a.placements)
    assert s["slot_feat"].shape == (n, SLOT_DIM) and s["slot_votes"].shape == (n, vocab.n_objects)
    np.testing.assert_allclose(s["slot_votes"].sum(1), 2)  # every slot holds one object of each context arrangement
    np.testing.assert_allclose(s["slot_feat"][:, 0], 1.0)  # support: in both context arrangements
    assert s["y_set"].tolist() == [1.0] * n and int(s["y_missed"]) == 0
    assert sorted(s["y_obj"].tolist()) == sorted(vocab.rows(c.objects).tolist())
    assert (vocab.type_of_row[s["y_obj"]] == s["slot_type"]).all()


def test_registration_removes_a_whole_layout_shift(small_dataset):
    ds = small_dataset
    _, encode = encoder(ds)
    a, b, c = ds.trials_of("p000")[:3]
    base = encode([a, b], c.table)
    moved = encode([a, shifted(b, 0.03, -0.02)], c.table)
    rel = lambda s: s["slot_xy"] - s["slot_xy"].mean(0)  # noqa: E731 - the layout, whatever its anchor
    np.testing.assert_allclose(rel(moved), rel(base), atol=1e-6)  # the relative layout is untouched
    spread = base["slot_feat"][:, 8]
    np.testing.assert_allclose(moved["slot_feat"][:, 8], spread, atol=1e-6)


def test_carried_layout_keeps_physical_spacing_on_another_table(small_dataset):
    ds = small_dataset
    _, encode = encoder(ds)
    a = ds.trials_of("p001")[0]
    other = next(t for t in sorted(ds.tables) if t != a.table)
    s = encode([a], other)
    d = lambda xy: np.linalg.norm(xy[:, None] - xy[None], axis=-1)  # noqa: E731
    np.testing.assert_allclose(d(s["slot_xy"]), d(a.positions), atol=1e-6)


def test_context_zero_uses_the_population_rows_and_flags_them(small_dataset):
    ds = small_dataset
    vocab, encode = encoder(ds)
    target = ds.trials_of("p002")[0]
    rows = population_rows(ds)[target.table]
    s = encode([], target.table, target)
    assert len(s["slot_feat"]) == len(rows)
    np.testing.assert_allclose(s["slot_feat"][:, 1], 1.0)  # population flag
    np.testing.assert_allclose(s["slot_feat"][:, 0], 0.0)  # no personal support
    assert sorted(np.nonzero(s["slot_votes"])[1].tolist()) == sorted(vocab.rows([r[0] for r in rows]).tolist())
    assert int(s["y_set"].sum()) + int(s["y_missed"]) == len(target.placements)


def test_collate_pads_slots(small_dataset):
    ds = small_dataset
    _, encode = encoder(ds)
    a, b, c = ds.trials_of("p000")[:3]
    batch = collate_slots([encode([a], c.table, c), encode([a, b], c.table, c), encode([], c.table, c)])
    B, S = batch["slot_mask"].shape
    assert B == 3 and batch["slot_votes"].shape[:2] == (B, S) and batch["taste"].shape == (B, batch["share"].shape[1], 2)
    assert (batch["y_obj"][~batch["slot_mask"]] == -1).all()


def test_a_table_unseen_in_training_gets_the_all_tables_population(small_dataset):
    ds = small_dataset
    vocab, encode = encoder(ds)
    new = replace(ds.tables[0], id=99, surface=((0.1, 0.2), (0.9, 0.2), (0.9, 0.8), (0.1, 0.8)))
    encode.tables = {**ds.tables, 99: new}
    s = encode([], 99)
    rows = population_rows(ds)[-1]
    assert len(s["slot_feat"]) == len(rows) and int(s["tgt_table"]) == len(vocab.tables)  # the "unknown table" row
    assert new.contains(s["slot_xy"][:, 0], s["slot_xy"][:, 1]).all()
