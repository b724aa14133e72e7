"""The naturalistic generator: counts, validity, consistency vs diversity, styles, ratings calibration."""

import functools
import itertools

import numpy as np
import pytest

from degusta_learn.metrics import PAPER_ACCEPTABILITY, acceptability_curve
from degusta_learn.scene import default_catalog, default_tables, object_size
from degusta_learn.synth import Style, naturalistic_with_styles, read_styles, write_styles
from degusta_learn.synth.geometry import max_overlap, sizes_of
from degusta_learn.synth.templates import TEMPLATES


@functools.lru_cache(maxsize=1)
def full():
    return naturalistic_with_styles(0)


def test_participants_trials_tables_and_catalog():
    ds, styles = full()
    assert len(ds.participants) == 199 and len(styles) == 199 and len(ds.arrangements) == 995
    assert ds.synthetic and ds.meta["seed"] == 0 and "SYNTHETIC" in ds.meta["description"]
    assert ds.catalog.to_json() == default_catalog().to_json()
    assert [t.to_json() for t in ds.tables.values()] == [t.to_json() for t in default_tables()]
    for arrs in ds.by_participant().values():
        assert [a.trial for a in arrs] == [0, 1, 2, 3, 4]
        assert sorted(a.table for a in arrs) == [0, 1, 2, 3, 4]  # every trial on a different table


def test_objects_count_inside_surface_and_overlap():
    ds, _ = full()
    overlaps = []
    for a in ds.arrangements:
        assert len(a.placements) >= 3
        assert len(set(a.objects)) == len(a.objects)
        assert ds.tables[a.table].contains(a.positions[:, 0], a.positions[:, 1]).all(), (a.participant, a.trial)
        overlaps.append(max_overlap(a.positions, a.rotations, sizes_of([ds.catalog[o].type for o in a.objects])))
    assert np.mean(np.array(overlaps) > 0.3) < 0.03  # objects essentially never pile up


def test_footprints_inside_surface_where_possible():
    ds, _ = full()
    ends = {t: [] for t in ds.tables}  # independent check: the 4 ends of each footprint's axes
    for a in ds.arrangements:
        for p in a.placements:
            w, length = object_size(ds.catalog[p.object])
            r = np.radians(p.rotation)
            ends[a.table] += [(p.x + s * length / 2 * np.sin(r), p.y - s * length / 2 * np.cos(r)) for s in (-1, 1)]
            ends[a.table] += [(p.x + s * w / 2 * np.cos(r), p.y + s * w / 2 * np.sin(r)) for s in (-1, 1)]
    ok = np.concatenate([ds.tables[t].contains(*np.array(e).T) for t, e in ends.items()])
    assert ok.mean() > 0.99


def _centroid_uv(ds, a):
    x0, y0, x1, y1 = ds.tables[a.table].bounds
    return (a.positions.mean(0) - [x0, y0]) / [x1 - x0, y1 - y0]


def test_participants_consistent_with_themselves_and_different_from_each_other():
    ds, _ = full()
    by_p = ds.by_participant()
    within_j, within_c, within_n = [], [], []
    for arrs in by_p.values():
        for a, b in itertools.combinations(arrs, 2):
            within_j.append(len(set(a.objects) & set(b.objects)) / len(set(a.objects) | set(b.objects)))
            within_c.append(np.linalg.norm(_centroid_uv(ds, a) - _centroid_uv(ds, b)))
            within_n.append(abs(len(a.placements) - len(b.placements)))
    rng = np.random.default_rng(0)
    ids = list(by_p)
    between_j, between_c, between_n = [], [], []
    for _ in range(2000):
        p, q = rng.choice(len(ids), 2, replace=False)
        a, b = by_p[ids[p]][rng.integers(5)], by_p[ids[q]][rng.integers(5)]
        between_j.append(len(set(a.objects) & set(b.objects)) / len(set(a.objects) | set(b.objects)))
        between_c.append(np.linalg.norm(_centroid_uv(ds, a) - _centroid_uv(ds, b)))
        between_n.append(abs(len(a.placements) - len(b.placements)))
    assert np.mean(within_j) > 0.3 > 5 * np.mean(between_j)  # the same favourite objects, not everyone's
    assert np.mean(within_c) < 0.5 * np.mean(between_c)  # the same place on the table
    assert np.mean(within_n) < 0.5 * np.mean(between_n)  # about the same number of objects
    assert np.mean(within_j) < 0.95  # ... but not exactly the same arrangement
    assert all(len({a.positions.round(4).tobytes() for a in arrs}) == 5 for arrs in by_p.values())


def test_styles_are_diverse_and_round_trip(tmp_path):
    _, styles = full()
    assert {s.template for s in styles} == set(TEMPLATES)
    assert len({tuple(s.colors) for s in styles}) > 40
    path = tmp_path / "styles.json"
    write_styles(path, styles)
    back = read_styles(path)
    assert list(back) == [s.participant for s in styles]
    assert all(back[s.participant] == s == Style.from_json(s.to_json()) for s in styles)


def test_deterministic_and_seed_dependent():
    # participants are drawn from their own seed streams: the first 30 of a 30-person run are the same
    a, b, c = naturalistic_with_styles(0, 30)[0], full()[0], naturalistic_with_styles(1, 30)[0]
    assert [x.to_json() for x in a.arrangements] == [x.to_json() for x in b.arrangements[:150]]
    assert [x.to_json() for x in a.ratings] == [x.to_json() for x in b.ratings[:150]]
    assert [x.to_json() for x in a.arrangements] != [x.to_json() for x in c.arrangements]


def test_ratings_one_per_arrangement_and_calibrated():
    ds, _ = full()
    assert [(r.participant, r.trial) for r in ds.ratings] == [(a.participant, a.trial) for a in ds.arrangements]
    assert all(0 <= r.b_initial <= 100 and 0 <= r.b_jitter <= 100 and r.rmsd_jitter >= 0 for r in ds.ratings)
    assert all(r.b_correct is None and r.rmsd_correct is None for r in ds.ratings)
    curve = acceptability_curve(ds.ratings)
    for t, paper in PAPER_ACCEPTABILITY.items():
        assert curve[t] == pytest.approx(paper, abs=0.05), (t, curve[t], paper)
    # the drop grows with RMSD: small jitters are accepted far more often than large ones
    small = [r.drop < 0.2 for r in ds.ratings if r.rmsd_jitter <= 0.02]
    large = [r.drop < 0.2 for r in ds.ratings if r.rmsd_jitter > 0.1]
    assert np.mean(small) > 0.5 > 0.1 > np.mean(large)
