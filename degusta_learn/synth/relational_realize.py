"""Turn a relational style into arrangements on a table: noisy trials (the data) and the expected one (the oracle).

A trial of a relational style (relational_style.py) on a table is made in this order (SYNTHETIC data;
docs/generators.md):

1. **count**: each rule is set with probability `p_include` (plates always); at least `MIN_OBJECTS`: the most
   likely rules are added;
2. **references**: a rule whose reference is not set this trial is placed against the reference's own reference:
   in a row (both `beside`/`stack` within 45 degrees of each other) it takes the missing object's place, so the
   spoon right of a missing knife sits where the knife would; otherwise it keeps its own direction and gap (a
   cup at a missing knife's tip goes above-right of the plate);
3. **order**: the rule order (a topological order of the rule graph, the seat's plate first) with adjacent
   swaps, each with probability `noise.order`, never moving an object before its reference or the first plate;
4. **objects**: each rule gets its favourite object with probability `loyalty`, otherwise another unused object
   of its type drawn with weight `exp(strictness * taste)` (synth/taste.py), as the naturalistic generator does;
5. **where**: each seat's edge point is found on the surface boundary at its place along the edge (+ N(0,
   noise.seat)); the diner's facing turns by N(0, noise.turn); then, rule by rule in rule order, each object is
   put against its reference's *realized* position and rotation, its direction moved by N(0, noise.direction),
   its gap by N(0, noise.gap), its rotation by N(0, noise.rotation), its position by N(0, noise.position): so
   errors travel down the rule chain;
6. **fit**: `geometry.fit_into` keeps footprints on the surface; a trial is kept when every footprint is on the
   surface and no two objects overlap by more than `MAX_OVERLAP` unless one lies `on` or is `stack`ed against the
   other (the same cluster). Otherwise it is redrawn (`RETRIES` times), then laid out without noise, then as the
   oracle's rules without noise, which the style sampler made sure fit on every table.

`expected_relational` is steps 1-6 without noise: the rules with `p_include` >= 0.5, favourite objects, rule
order. It is the relational oracle's prediction.
"""

from __future__ import annotations

import math

import numpy as np

from degusta_learn.scene import TYPE_SIZE, Catalog, Placement, Table
from degusta_learn.synth.geometry import bounds, fit_into, footprint_points, inside, sizes_of
from degusta_learn.synth.realize import MAX_OVERLAP, MIN_OBJECTS
from degusta_learn.synth.relational_style import ROOTS, SIDES, RelationalStyle
from degusta_learn.synth.taste import catalog_features

# MAX_OVERLAP (the naturalistic generator's, 0.3): the largest share of one footprint another may cover, unless they
# are one cluster (`on` or `stack`); MIN_OBJECTS (3): the fewest objects of a trial.
RETRIES = 6
ROW = ("beside", "stack")
_DISC = np.concatenate([[[0.0, 0.0]], *(s * np.c_[np.cos(a), np.sin(a)] for s, a in
                                        ((0.55, np.linspace(0, 2 * np.pi, 8, endpoint=False)),
                                         (0.9, np.linspace(0, 2 * np.pi, 8, endpoint=False) + np.pi / 8)))])
"""(17, 2) sample points of a unit disc: a footprint's share inside another is the share of these inside it."""


def frame(facing: float) -> tuple[np.ndarray, np.ndarray]:
    """(right, far) unit vectors in image coordinates of a diner facing `facing` degrees (0: at the bottom edge)."""
    f = math.radians(facing)
    return np.array([math.cos(f), math.sin(f)]), np.array([math.sin(f), -math.cos(f)])


def heading(direction: float, right: np.ndarray, far: np.ndarray) -> np.ndarray:
    """Unit vector of `direction` (degrees clockwise from far) in a seat frame."""
    t = math.radians(direction)
    return math.sin(t) * right + math.cos(t) * far


def axes(rot: float) -> tuple[np.ndarray, np.ndarray]:
    """(width axis, long axis) of an object rotated `rot` degrees (0: long axis to image north)."""
    r = math.radians(rot)
    return np.array([math.cos(r), math.sin(r)]), np.array([math.sin(r), -math.cos(r)])


def support(type_: str, rot: float, d: np.ndarray) -> float:
    """How far the footprint ellipse of a `type_` rotated `rot` reaches from its centre along unit vector `d`."""
    w, length = TYPE_SIZE[type_]
    w_ax, l_ax = axes(rot)
    return math.hypot(w / 2 * float(d @ w_ax), length / 2 * float(d @ l_ax))


def edge_point(table: Table, facing: float, along: float) -> np.ndarray:
    """The point of the surface boundary a diner facing `facing` sits at, `along` (a fraction of the surface's
    half extent along the edge, + = their right) from the middle of the edge."""
    x0, y0, x1, y1 = bounds(table)
    right, far = frame(facing)
    half = abs(right[0]) * (x1 - x0) / 2 + abs(right[1]) * (y1 - y0) / 2
    origin = np.array([(x0 + x1) / 2, (y0 + y1) / 2]) + along * half * right
    u = -far  # from inside toward the diner: the farthest boundary crossing is their edge
    p = np.asarray(table.surface, dtype=float)
    e = np.roll(p, -1, axis=0) - p
    w = p - origin
    den = u[0] * e[:, 1] - u[1] * e[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / den
        s = (w[:, 0] * u[1] - w[:, 1] * u[0]) / den
    ok = np.isfinite(t) & (t >= 0) & (s >= -1e-9) & (s <= 1 + 1e-9)
    reach = float(t[ok].max()) if ok.any() else abs(far[0]) * (x1 - x0) / 2 + abs(far[1]) * (y1 - y0) / 2
    return origin + reach * u


def with_least(style: RelationalStyle, chosen: list[int]) -> list[int]:
    """Top a rule selection up to MIN_OBJECTS with the most likely other rules; sorted (rule order)."""
    if len(chosen) < MIN_OBJECTS:
        rest = sorted((i for i in range(len(style.rules)) if i not in chosen),
                      key=lambda i: (-style.rules[i].p_include, i))
        chosen = chosen + rest[:MIN_OBJECTS - len(chosen)]
    return sorted(chosen)


def oracle_rules(style: RelationalStyle) -> list[int]:
    """The rules the person sets at least half the time (topped up to MIN_OBJECTS), in rule order."""
    return with_least(style, [i for i, r in enumerate(style.rules) if r.p_include >= 0.5])


def resolve(style: RelationalStyle, i: int, present: set[int]) -> tuple[str, int, float, float, float]:
    """(relation, reference, direction, gap, shift) of rule `i` when only rules `present` are set (step 2)."""
    r = style.rules[i]
    rel, ref, d, g, s = r.relation, r.ref, r.direction, r.gap, r.shift
    while rel not in ROOTS and ref not in present:
        parent = style.rules[ref]
        if rel in ROW and parent.relation in ROW and abs((d - parent.direction + 180) % 360 - 180) <= 45:
            rel, ref, d, g, s = parent.relation, parent.ref, parent.direction, parent.gap, parent.shift
        else:
            rel, ref = ("beside" if rel == "tip" else rel), parent.ref
    return rel, ref, d, g, s


def clusters(style: RelationalStyle, idx: list[int]) -> dict[int, int]:
    """Rule -> cluster label: objects joined by `on` / `stack` (after step 2) may overlap each other."""
    label = {i: i for i in idx}

    def root(i: int) -> int:
        while label[i] != i:
            i = label[i]
        return i

    present = set(idx)
    for i in idx:
        rel, ref, *_ = resolve(style, i, present)
        if rel in ("on", "stack"):
            label[root(i)] = root(ref)
    return {i: root(i) for i in idx}


def draw_noise(style: RelationalStyle, rng: np.random.Generator | None) -> dict | None:
    """One trial's noise draws (None: no noise), for every seat and rule whether set or not."""
    if rng is None:
        return None
    n, k, z = style.noise, len(style.seats), len(style.rules)
    return {"along": rng.normal(0, n.seat, k), "inset": rng.normal(0, n.seat * 0.5, k), "turn": rng.normal(0, n.turn, k),
            "direction": rng.normal(0, n.direction, z), "gap": rng.normal(0, n.gap, z),
            "position": rng.normal(0, n.position, (z, 2)), "rotation": rng.normal(0, n.rotation, z)}


def layout(style: RelationalStyle, table: Table, idx: list[int], noise: dict | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) and rotations (N,) of rules `idx` (rule order) on `table`, before fitting (step 5)."""
    seats = []
    for k, seat in enumerate(style.seats):
        facing = SIDES[seat.side]
        along, inset, turn = (seat.along, seat.inset, 0.0) if noise is None else \
            (seat.along + noise["along"][k], seat.inset + noise["inset"][k], noise["turn"][k])
        seats.append((edge_point(table, facing, along), max(inset, 0.0), facing + turn, *frame(facing + turn)))
    x0, y0, x1, y1 = bounds(table)
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    present = set(idx)
    pos: dict[int, np.ndarray] = {}
    rot: dict[int, float] = {}
    for i in idx:
        r = style.rules[i]
        rel, ref, d, g, s = resolve(style, i, present)
        edge, inset, facing, right, far = seats[r.seat]
        if noise is not None:
            d, g = d + noise["direction"][i], g + noise["gap"][i]
        u, p = heading(d, right, far), heading(d + 90.0, right, far)
        rot[i] = r.rotation + facing + (0.0 if noise is None else noise["rotation"][i])
        if rel == "edge":
            c = edge + far * (inset + support(r.type, rot[i], far))
        elif rel == "centre":
            c = centre + u * g + p * s
        elif rel == "on":
            c = pos[ref] + u * g + p * s
        elif rel == "tip":
            ref_type = style.rules[ref].type
            tip = pos[ref] + axes(rot[ref])[1] * TYPE_SIZE[ref_type][1] / 2
            c = tip + u * (g + support(r.type, rot[i], u)) + p * s
        else:  # beside, stack
            c = pos[ref] + u * (support(style.rules[ref].type, rot[ref], u) + g + support(r.type, rot[i], u)) + p * s
        pos[i] = c if noise is None else c + noise["position"][i]
    xy = np.array([pos[i] for i in idx], dtype=float).reshape(-1, 2)
    return xy, np.array([rot[i] for i in idx], dtype=float) % 360.0


def overlap_fractions(xy: np.ndarray, rot: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(N, N): the share of object i's footprint samples inside object j's footprint ellipse (0 on the diagonal)."""
    r = np.radians(rot)
    w_ax, l_ax = np.stack([np.cos(r), np.sin(r)], -1), np.stack([np.sin(r), -np.cos(r)], -1)  # (N, 2) each
    half = sizes / 2
    pts = xy[:, None] + _DISC[None, :, :1] * half[:, None, :1] * w_ax[:, None] \
        + _DISC[None, :, 1:] * half[:, None, 1:] * l_ax[:, None]  # (N, 17, 2)
    d = pts[:, :, None, :] - xy[None, None]  # (N, 17, N, 2)
    a = (d * w_ax[None, None]).sum(-1) / half[None, None, :, 0]
    b = (d * l_ax[None, None]).sum(-1) / half[None, None, :, 1]
    frac = ((a ** 2 + b ** 2) <= 1.0).mean(1)
    np.fill_diagonal(frac, 0.0)
    return frac


def fits(table: Table, xy: np.ndarray, rot: np.ndarray, types: list[str], groups: list[int]) -> bool:
    """Every footprint on the surface, and no overlap above MAX_OVERLAP between objects of different clusters."""
    sizes = sizes_of(types)
    if not inside(table, footprint_points(xy, rot, sizes)).all():
        return False
    g = np.asarray(groups)
    return not (overlap_fractions(xy, rot, sizes)[g[:, None] != g[None]] > MAX_OVERLAP).any()


def place(style: RelationalStyle, table: Table, idx: list[int], noise: dict | None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Laid out (step 5), fitted onto the surface and checked (step 6): (xy, rot, whether it fits)."""
    xy, rot = layout(style, table, idx, noise)
    types = [style.rules[i].type for i in idx]
    xy = fit_into(table, xy, rot, sizes_of(types))
    label = clusters(style, idx)
    return xy, rot, fits(table, xy, rot, types, [label[i] for i in idx])


def expected_relational(style: RelationalStyle, table: Table) -> list[Placement]:
    """The style on `table` without noise: the relational oracle's prediction."""
    idx = oracle_rules(style)
    xy, rot, _ = place(style, table, idx, None)
    return [Placement(int(style.rules[i].object), float(x), float(y), float(r)) for i, (x, y), r in zip(idx, xy, rot)]


def taste_weights(style: RelationalStyle, catalog: Catalog) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per type: (object ids, unnormalized weights exp(strictness * taste)) of non-favourite picks."""
    feats = catalog_features(catalog)
    return {t: (feats[t].ids, np.exp(style.strictness * feats[t].taste(style.colors, style.materials)))
            for t in {r.type for r in style.rules}}


def _objects(style: RelationalStyle, order: list[int], rng: np.random.Generator, weights: dict) -> list[int]:
    """Step 4: one object per rule of `order`, each used once."""
    favourites = {style.rules[i].object for i in order}
    used: set[int] = set()
    out = []
    for i in order:
        rule = style.rules[i]
        if rule.object not in used and rng.random() < style.loyalty:
            pick = rule.object
        else:
            ids, w = weights[rule.type]
            ok = np.array([o not in used and o not in favourites for o in ids.tolist()])
            if not ok.any():
                ok = np.array([o not in used for o in ids.tolist()])
            pick = int(rng.choice(ids, p=(w * ok) / (w * ok).sum()))
        used.add(pick)
        out.append(pick)
    return out


def _ancestors(style: RelationalStyle, i: int, present: set[int]) -> set[int]:
    out = set()
    while True:
        rel, ref, *_ = resolve(style, i, present)
        if rel in ROOTS:
            return out
        out.add(ref)
        i = ref


def sample_relational(style: RelationalStyle, table: Table, catalog: Catalog, rng: np.random.Generator,
                      weights: dict | None = None, stats: dict | None = None) -> list[Placement]:
    """One noisy trial of `style` on `table` (steps 1-6 of the module docstring).

    `stats`, when given, counts how each trial was laid out: "noisy", "noiseless" or "oracle" (step 6's fallbacks).
    """
    weights = weights if weights is not None else taste_weights(style, catalog)
    idx = with_least(style, [i for i, r in enumerate(style.rules) if r.p_include >= 1.0 or rng.random() < r.p_include])
    present = set(idx)
    order = list(idx)
    for k in range(1, len(order) - 1):  # the first plate stays first
        if rng.random() < style.noise.order and order[k] not in _ancestors(style, order[k + 1], present):
            order[k], order[k + 1] = order[k + 1], order[k]
    objects = dict(zip(order, _objects(style, order, rng, weights)))
    how = "noisy"
    for _ in range(RETRIES):
        xy, rot, ok = place(style, table, idx, draw_noise(style, rng))
        if ok:
            break
    else:
        how = "noiseless"
        xy, rot, ok = place(style, table, idx, None)
        if not ok:  # the oracle's rules fit on every table (relational_habits.sample_relational_style checks)
            how, idx = "oracle", oracle_rules(style)
            xy, rot, _ = place(style, table, idx, None)
            order = list(idx)
            objects = dict(zip(order, _objects(style, order, rng, weights)))
    if stats is not None:
        stats[how] = stats.get(how, 0) + 1
    at = {i: k for k, i in enumerate(idx)}
    return [Placement(int(objects[i]), float(xy[at[i], 0]), float(xy[at[i], 1]), float(rot[at[i]] % 360.0))
            for i in order]
