"""Context alignment (align.py): corresponding objects share a group, types never mix, support counts."""

from dataclasses import replace

import numpy as np

from degusta_learn.baselines.learned.align import align_context
from degusta_learn.baselines.learned.features import Vocab
from degusta_learn.scene import Placement


def test_same_layout_on_other_tables_and_orders_aligns(small_dataset):
    ds = small_dataset
    types = Vocab.from_dataset(ds).type_of_id
    a, b = ds.trials_of("p000")[:2]  # one person's fixed layout, two tables
    b = replace(b, placements=tuple(reversed(b.placements)))  # another placement order
    group, support = align_context([a, b], ds.tables, types)
    n = len(a.placements)
    first = dict(zip(a.objects, group[:n]))
    second = dict(zip(b.objects, group[n:]))
    assert first == second and len(set(group[:n])) == n  # same object -> same group, one group per object
    np.testing.assert_allclose(support, 1.0)


def test_unmatched_and_other_types_start_new_groups(small_dataset):
    ds = small_dataset
    types = Vocab.from_dataset(ds).type_of_id
    a = ds.trials_of("p001")[0]
    extra = next(o.id for o in ds.catalog if o.id not in a.objects)
    b = replace(a, trial=99, placements=a.placements + (Placement(extra, 0.5, 0.5, 0.0),))
    group, support = align_context([a, b], ds.tables, types)
    n = len(a.placements)
    assert group[-1] == n and support[-1] == 0.5  # only in one of the two arrangements
    for g in set(group):  # a group never mixes types
        assert len({types[o] for o, gg in zip(a.objects + b.objects, group) if gg == g}) == 1
    assert align_context([], ds.tables, types)[0].shape == (0,)
