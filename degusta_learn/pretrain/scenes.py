"""Random, style-free table scenes: what the base VLM learns to *see* before it sees anyone's taste.

A scene is an `Arrangement` of random catalog objects at random positions and rotations on a random
table: no layout template, no favourite colours, no participant. Objects are placed one by one by
rejection sampling so that every footprint lies on the table surface and no object covers more than
`MAX_OVERLAP` of another (an object hidden under a plate cannot be perceived, so it may not be asked
about). Rotations mix the common cases (pointing north, south, one of the eight directions) with
uniformly random angles; round-ish plates keep to north mostly, because their direction cannot be seen.

Everything is a pure function of the numpy Generator passed in, so example i of a seeded stream is the
same on every machine and in every DataLoader worker.

Example:
    rng = np.random.default_rng(0)
    scene = random_scene(rng, default_catalog(), {t.id: t for t in default_tables()})
"""

from __future__ import annotations

import numpy as np

from degusta_learn.scene import Arrangement, Catalog, Placement, Table
from degusta_learn.synth.geometry import bounds, footprint_points, inside, max_overlap, sizes_of

MAX_OVERLAP = 0.05  # largest fraction of one footprint another may cover
_TRIES = 40  # positions tried per object before it is left out
# How many objects a scene has: mostly 3-6 like people's tables, sometimes 1-2 or up to 14.
_COUNTS = np.arange(1, 15)
_COUNT_P = np.array([4, 6, 12, 13, 12, 11, 9, 8, 7, 6, 4, 3, 3, 2], dtype=float)
_COUNT_P /= _COUNT_P.sum()


def random_rotation(rng: np.random.Generator, type_: str) -> float:
    """Degrees clockwise from north: mostly N (plates even more so), S, one of 8 directions, or any."""
    u = rng.random()
    north, south, eight = (0.85, 0.93, 0.97) if type_ == "plate" else (0.45, 0.6, 0.85)
    if u < north:
        base = 0.0
    elif u < south:
        base = 180.0
    elif u < eight:
        base = 45.0 * int(rng.integers(8))
    else:
        return float(rng.uniform(0.0, 360.0))
    return float((base + rng.normal(0.0, 7.0)) % 360.0)


def random_scene(rng: np.random.Generator, catalog: Catalog, tables: dict[int, Table], n_objects: int | None = None,
                 participant: str = "random", trial: int = 0) -> Arrangement:
    """A random arrangement on a random table (see the module docstring); at least one object.

    Args:
        rng: the source of randomness (the scene is a pure function of its state).
        catalog: objects to draw from (each at most once).
        tables: table id -> Table; one is drawn uniformly.
        n_objects: how many objects to try to place (default: drawn from a people-like distribution).
        participant, trial: labels of the returned Arrangement.
    """
    table = tables[sorted(tables)[int(rng.integers(len(tables)))]]
    n = int(n_objects if n_objects is not None else rng.choice(_COUNTS, p=_COUNT_P))
    ids = rng.choice(catalog.ids, size=min(n, len(catalog.ids)), replace=False).tolist()
    x0, y0, x1, y1 = bounds(table)
    placed: list[Placement] = []
    xy = np.zeros((0, 2))
    rot = np.zeros(0)
    types: list[str] = []
    for oid in ids:
        t = catalog[oid].type
        size = sizes_of([t])
        for _ in range(_TRIES):
            r = random_rotation(rng, t)
            p = np.array([[rng.uniform(x0, x1), rng.uniform(y0, y1)]])
            if not inside(table, footprint_points(p, np.array([r]), size)).all():
                continue
            cand_xy, cand_rot = np.vstack([xy, p]), np.append(rot, r)
            if max_overlap(cand_xy, cand_rot, sizes_of(types + [t])) > MAX_OVERLAP:
                continue
            xy, rot, types = cand_xy, cand_rot, types + [t]
            placed.append(Placement(int(oid), round(float(p[0, 0]), 6), round(float(p[0, 1]), 6), round(r, 4)))
            break
    if not placed:  # a crowded draw: one object in the middle of the surface always fits
        oid = int(ids[0])
        placed.append(Placement(oid, round((x0 + x1) / 2, 6), round((y0 + y1) / 2, 6), 0.0))
    return Arrangement(participant=participant, trial=trial, table=table.id, placements=tuple(placed))

