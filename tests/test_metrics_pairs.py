"""Colours and materials compare as unordered pairs (the paper's multi-label features): a red/blue object
and a blue/red one have the same colours, in the feature distance and so in matching and scoring."""

from __future__ import annotations

import itertools

import numpy as np

from degusta_learn.metrics import match, score_prediction
from degusta_learn.metrics.matching import hamming
from degusta_learn.scene import Arrangement, Catalog, CatalogObject, Placement, default_catalog

BASE = dict(type="cup", color1="red", color2="blue", material1="glass", material2="metal")


def reference_distance(o: CatalogObject, q: CatalogObject) -> int:
    """Object-level reference: differing single features + per pair the fewer differences of its two alignments."""
    d = sum(getattr(o, f) != getattr(q, f) for f in ("type", "shape", "pattern"))
    for x, y in (("color1", "color2"), ("material1", "material2")):
        a, b = (getattr(o, x), getattr(o, y)), (getattr(q, x), getattr(q, y))
        d += min((a[0] != b[0]) + (a[1] != b[1]), (a[0] != b[1]) + (a[1] != b[0]))
    return d


def test_swapped_colours_and_materials_are_the_same_pair():
    cat = Catalog((
        CatalogObject(0, **BASE),
        CatalogObject(1, **{**BASE, "color1": "blue", "color2": "red"}),            # colours swapped
        CatalogObject(2, **{**BASE, "material1": "metal", "material2": "glass"}),   # materials swapped
        CatalogObject(3, **{**BASE, "color1": "blue", "color2": "green"}),          # shares blue only
        CatalogObject(4, **{**BASE, "color1": "green", "color2": "green"}),         # no colour in common
    ))
    d = hamming(cat.features([0]), cat.features([1, 2, 3, 4]))[0].tolist()
    assert d == [0, 0, 1, 2]  # positionally: 2, 2, 2, 2


def test_a_swapped_pair_is_matched_before_a_positional_one():
    """GT red/blue cup; predictions: a blue/red cup far away and a red/green cup on top of it. As a pair the
    blue/red cup is the same colours (distance 0) and wins; compared by position it lost (2 vs 1)."""
    cat = Catalog((CatalogObject(0, **BASE), CatalogObject(1, **{**BASE, "color1": "blue", "color2": "red"}),
                   CatalogObject(2, **{**BASE, "color2": "green"})))
    _, pi = match(cat, [0], [2, 1], [[0.5, 0.5]], [[0.5, 0.5], [0.9, 0.1]])
    assert pi.tolist() == [1]
    gt = Arrangement("p000", 0, 0, (Placement(0, 0.5, 0.5, 0.0), Placement(2, 0.2, 0.2, 0.0)))
    s = score_prediction(cat, gt, [Placement(1, 0.5, 0.5, 0.0), Placement(2, 0.2, 0.2, 0.0)])
    assert s.rmsd == 0.0  # the swapped cup pairs with the red/blue one, the red/green with itself


def test_distance_equals_the_object_level_rule_on_the_default_catalog():
    cat = default_catalog()
    objs = list(cat)
    rng = np.random.default_rng(0)
    ids = sorted(rng.choice(cat.ids, 60, replace=False).tolist()) + [25, 112, 36, 38, 45, 48, 110, 121]
    h = hamming(cat.features(ids), cat.features(ids))
    by_id = {o.id: o for o in objs}
    for (i, a), (j, b) in itertools.product(enumerate(ids), repeat=2):
        assert h[i, j] == reference_distance(by_id[a], by_id[b]), (a, b)
    assert (h == h.T).all() and (np.diag(h) == 0).all()
