"""Matching: Hungarian on Hamming distance, ties toward nearer positions, min(len) pairs; checked against
a brute-force lexicographic search (min total Hamming, then min total distance) over all assignments."""

import itertools

import numpy as np
import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import match
from degusta_learn.metrics.matching import hamming
from degusta_learn.scene import Catalog, CatalogObject, default_catalog

CAT = default_catalog()


def small_catalog():
    base = dict(type="cup", color1="red", color2="red", material1="glass", material2="glass")
    return Catalog((
        CatalogObject(0, **base),
        CatalogObject(1, **{**base, "color1": "blue"}),  # Hamming 1 from 0
        CatalogObject(2, **{**base, "material1": "metal"}),  # Hamming 1 from 0
        CatalogObject(3, **base),  # same features as 0
        CatalogObject(4, **{**base, "type": "plate", "shape": "square"}),
    ))


def brute_force(catalog, gid, pid, gxy, pxy):
    """(min total Hamming, min total distance among those) over all injective assignments."""
    h = hamming(catalog.features(gid), catalog.features(pid))  # the distance itself: tests/test_metrics_pairs.py
    d = np.linalg.norm(gxy[:, None] - pxy[None], axis=-1)
    n, m = h.shape
    best = None
    if n <= m:
        cands = ((range(n), cols) for cols in itertools.permutations(range(m), n))
    else:
        cands = ((rows, range(m)) for rows in itertools.permutations(range(n), m))
    for rows, cols in cands:
        rows, cols = list(rows), list(cols)
        key = (int(h[rows, cols].sum()), float(d[rows, cols].sum()))
        if best is None or key[0] < best[0] or (key[0] == best[0] and key[1] < best[1]):
            best = key
    return best


def test_shuffled_identical_arrangement_matches_perfectly():
    rng = np.random.default_rng(0)
    gid = list(rng.choice(CAT.ids, 6, replace=False))
    gxy = rng.random((6, 2))
    perm = rng.permutation(6)
    gi, pi = match(CAT, gid, [gid[k] for k in perm], gxy, gxy[perm])
    assert list(gi) == list(range(6))
    assert [perm[k] for k in pi] == list(range(6))


def test_hamming_tie_breaks_toward_nearer_position():
    cat = small_catalog()
    gxy = np.array([[0.2, 0.2]])
    # Objects 1 and 2 are both at Hamming 1 from object 0: the nearer one wins, whichever index it has.
    assert match(cat, [0], [1, 2], gxy, np.array([[0.9, 0.9], [0.21, 0.2]]))[1].tolist() == [1]
    assert match(cat, [0], [1, 2], gxy, np.array([[0.21, 0.2], [0.9, 0.9]]))[1].tolist() == [0]
    # Same features, different ids: matched by position even though the ids then differ.
    gi, pi = match(cat, [0, 3], [3, 0], np.array([[0.1, 0.1], [0.9, 0.9]]), np.array([[0.1, 0.1], [0.9, 0.9]]))
    assert pi.tolist() == [0, 1]


def test_distance_never_overrides_hamming():
    cat = small_catalog()
    # The exact object far away beats a Hamming-1 object right on top of the ground truth.
    _, pi = match(cat, [0], [1, 0], np.array([[0.0, 0.0]]), np.array([[0.0, 0.0], [50.0, 50.0]]))
    assert pi.tolist() == [1]


def test_random_cases_against_brute_force():
    rng = np.random.default_rng(1)
    pool = list(rng.choice(CAT.ids, 8, replace=False))  # few ids: many repeats and ties
    for _ in range(150):
        n, m = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        gid = list(rng.choice(pool, n, replace=False))
        pid = list(rng.choice(pool, m))
        scale = rng.choice([1.0, 30.0])
        gxy, pxy = rng.random((n, 2)) * scale, rng.random((m, 2)) * scale
        gi, pi = match(CAT, gid, pid, gxy, pxy)
        assert len(gi) == len(pi) == min(n, m)
        assert len(set(gi.tolist())) == len(gi) and len(set(pi.tolist())) == len(pi)
        h = int(hamming(CAT.features(gid), CAT.features(pid))[gi, pi].sum())
        d = float(np.linalg.norm(gxy[gi] - pxy[pi], axis=1).sum())
        ref_h, ref_d = brute_force(CAT, gid, pid, gxy, pxy)
        assert h == ref_h
        assert d == pytest.approx(ref_d, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("n,m", [(5, 2), (2, 5), (3, 3), (4, 0), (0, 3)])
def test_unequal_lengths_give_min_pairs(n, m):
    rng = np.random.default_rng(n * 10 + m)
    gid, pid = CAT.ids[:n], CAT.ids[50:50 + m]
    gi, pi = match(CAT, gid, pid, rng.random((n, 2)), rng.random((m, 2)))
    assert len(gi) == len(pi) == min(n, m)
    assert np.all(np.diff(gi) > 0)


def test_bad_input_is_a_degusta_error():
    with pytest.raises(DegustaError, match="unknown object id 999"):
        match(CAT, [0], [999], [[0, 0]], [[0, 0]])
    with pytest.raises(DegustaError, match="positions"):
        match(CAT, [0, 1], [2], [[0, 0]], [[0, 0]])


def test_feature_table_with_sparse_huge_ids_allocates_nothing_by_id():
    """An id of 1e11 once sized a dense id -> row array (745 GiB); sparse ids use a sorted lookup."""
    from degusta_learn.metrics.matching import FeatureTable

    class Sparse:
        ids = [7, 10**11, 3]

        def features(self, ids):
            return np.arange(len(ids) * 7).reshape(len(ids), 7)  # one code per MATCH_FEATURES entry

    table = FeatureTable(Sparse())
    assert table.row is None
    assert table.rows([10**11, 3, 7], "ids").tolist() == [1, 2, 0]
    with pytest.raises(DegustaError, match="unknown object id 8"):
        table.rows([7, 8], "ids")
