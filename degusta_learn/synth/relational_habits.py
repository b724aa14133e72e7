"""Sampling the latent style of a `relational` participant: habits of placement rules, not slot templates.

`sample_relational_style(rng, participant, catalog, tables, multi)` draws, independently per participant
(probabilities in brackets; every gap, shift and angle is the person's own draw):

- a **habit**, how one place setting is built from rules (relational_style.py), each rule against the plate or
  an object already placed:
  - `classic` [0.30]: fork `beside` the plate to the left; knife to the right, spoon right of the knife; cup at
    the knife's `tip`, above-right; sometimes a salad fork left of the fork [0.3] or a dessert spoon above the
    plate, lying across [0.25];
  - `left_handed` [0.08]: `classic` mirrored (directions and rotations);
  - `compact` [0.17]: one utensil beside the plate, the cup above it on that side [0.7] or the other; rarely a
    knife on the far side;
  - `on_plate` [0.15]: fork and knife laid `on` the plate, parallel, both angled ("finished") or crossed;
    spoon beside, cup above-right;
  - `stacked` [0.15]: a bundle of 2-3 utensils on one side, each `stack`ed against the last (overlapping, a fan
    of personal angles); cup on the other side;
  - `above` [0.15]: 1-3 utensils lying across above the plate, each above the last; cup to one side;
- a **layout**: one diner [1 - `multi`] or, with probability `multi` (default 0.2), `opposite` [0.45], `beside`
  [0.3], `three` [0.1] or `four` [0.15] diners, each with the same habit; with fewer than four diners a shared
  serving plate at the `centre` [0.4], a serving spoon or fork on it;
- the **seat**: the near edge [0.7], far [0.1], left or right [0.1 each]; along it at the middle ~ N(0, 0.05)
  [0.6] or off to a side +-U[0.2, 0.45] [0.4] (several diners: +-U[0.42, 0.5] or 0, + N(0, 0.03)); plate inset from the
  edge U[0.02, 0.1] (several diners: U[0.01, 0.05]);
- **utensil angle**: parallel to the edge's normal (0) [0.6], angled +-U[8, 30] [0.3] or reversed (180) [0.1],
  plus N(0, 3); plates and cups 0 [0.8] or one personal angle;
- **spacing**: a personal gap U[0.006, 0.035], each rule's x exp(N(0, 0.3)); sideways shifts N(0, 0.012);
- **what**: plates and one utensil per plate always set; the others p_include ~ U[0.2, 1] or as stated;
- **order**: setting by setting [0.6] or type by type [0.4]; after the plate, fork, knife, spoon, cup [0.5] or a
  personal order of those types; the serving plate first or last [0.5 each]; always a topological order of the
  rule graph (an object after its reference), the first seat's plate first;
- **taste** as in the naturalistic generator (templates.favourite_logits: colours from COLOR_PRIOR, materials
  from MATERIAL_PRIOR, strictness U[0, 5], loyalty U[0.5, 0.95]);
- **noise** (times the `noise` option): position log-uniform [0.003, 0.012], rotation U[2, 10] deg, direction
  U[1, 6] deg, gap U[0.002, 0.012], seat U[0.01, 0.06], turn U[0, 6] deg, order swaps U[0, 0.25];
- **ratings**: ratings.sample_rating_traits.

A draw is kept when its types keep the plausibility rules (plausible.py: bounded duplicates per type, a utensil
per plate, plates always set, always-set utensils at least one per plate) and its oracle arrangement fits on every
table (relational_realize.fits); otherwise the person is drawn again (at most `MAX_DRAWS` times, then a plain
plate, fork and cup).
"""

from __future__ import annotations

import numpy as np

from degusta_learn.scene import Catalog, Table
from degusta_learn.synth.plausible import UTENSILS, violations
from degusta_learn.synth.ratings import sample_rating_traits
from degusta_learn.synth.relational_realize import oracle_rules, place
from degusta_learn.synth.relational_style import RelationalStyle, RelNoise, Rule, Seat
from degusta_learn.synth.taste import catalog_features
from degusta_learn.synth.templates import COLOR_PRIOR, MATERIAL_PRIOR, favourite_logits

HABITS = {"classic": 0.30, "left_handed": 0.08, "compact": 0.17, "on_plate": 0.15, "stacked": 0.15, "above": 0.15}
LAYOUTS = {"opposite": 0.45, "beside": 0.30, "three": 0.10, "four": 0.15}
"""Several diners, given that there are (the `multi` option's share of people)."""
SIDE_PRIOR = {"near": 0.7, "far": 0.1, "left": 0.1, "right": 0.1}
OPPOSITE = {"near": "far", "far": "near", "left": "right", "right": "left"}
MAX_DRAWS = 50

Spec = tuple  # (type, relation, local ref, direction, gap, shift, rotation, p_include)


def _pick(rng: np.random.Generator, prior: dict):
    keys = list(prior)
    p = np.array(list(prior.values()), dtype=float)
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


class _Person:
    """One person's spacing, angles and rule builder while their habit is drawn."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        kind = rng.choice(3, p=[0.6, 0.3, 0.1])
        self.angle = float([0.0, rng.choice([-1, 1]) * rng.uniform(8, 30), 180.0][kind] + rng.normal(0, 3)) % 360
        self.round = 0.0 if rng.random() < 0.8 else float(rng.uniform(0, 360))
        self.base_gap = float(rng.uniform(0.006, 0.035))

    def gap(self) -> float:
        return self.base_gap * float(np.exp(self.rng.normal(0, 0.3)))

    def shift(self) -> float:
        return float(self.rng.normal(0, 0.012))

    def p(self, lo: float = 0.2, hi: float = 1.0) -> float:
        return float(self.rng.uniform(lo, hi))


def _classic(me: _Person) -> list[Spec]:
    rng, a = me.rng, me.angle
    specs = [("plate", "edge", -1, 0.0, 0.0, 0.0, me.round, 1.0),
             ("fork", "beside", 0, 270.0, me.gap(), me.shift(), a, 1.0)]
    if rng.random() < 0.3:  # a salad fork outside the fork
        specs.append(("fork", "beside", 1, 270.0, me.gap(), me.shift(), a, me.p(0.2, 0.9)))
    knife = len(specs)
    specs.append(("knife", "beside", 0, 90.0, me.gap(), me.shift(), a, 1.0 if rng.random() < 0.7 else me.p(0.3, 0.9)))
    specs.append(("spoon", "beside", knife, 90.0, me.gap(), me.shift(), a, me.p()))
    specs.append(("cup", "tip", knife, float(rng.uniform(15, 60)), float(rng.uniform(0.0, 0.03)), 0.0, me.round,
                  me.p(0.3, 1.0)))
    if rng.random() < 0.25:  # a dessert spoon lying across above the plate
        specs.append(("spoon", "beside", 0, 0.0, me.gap(), me.shift(), 90.0 if rng.random() < 0.7 else 270.0,
                      me.p(0.2, 0.9)))
    return specs


def _mirrored(specs: list[Spec]) -> list[Spec]:
    return [(t, rel, ref, (-d) % 360, g, -s, (-r) % 360, p) for t, rel, ref, d, g, s, r, p in specs]


def _compact(me: _Person) -> list[Spec]:
    rng = me.rng
    side = 90.0 if rng.random() < 0.6 else 270.0
    utensil = _pick(rng, {"fork": 0.5, "spoon": 0.3, "knife": 0.2})
    up = float(rng.uniform(25, 60))
    cup_dir = (up if side == 90.0 else 360 - up) if rng.random() < 0.7 else (360 - up if side == 90.0 else up)
    specs = [("plate", "edge", -1, 0.0, 0.0, 0.0, me.round, 1.0),
             (utensil, "beside", 0, side, me.gap(), me.shift(), me.angle, 1.0),
             ("cup", "beside", 0, cup_dir, me.gap(), 0.0, me.round, 1.0)]
    if utensil != "knife" and rng.random() < 0.4:
        specs.append(("knife", "beside", 0, 360.0 - side, me.gap(), me.shift(), me.angle, me.p(0.1, 0.6)))
    return specs


def _on_plate(me: _Person) -> list[Spec]:
    rng = me.rng
    kind = rng.choice(3, p=[0.5, 0.3, 0.2])
    tilt = float(rng.uniform(20, 50))
    fork_rot, knife_rot = [(me.angle, me.angle), (tilt, tilt + rng.normal(0, 4)), (tilt, -tilt)][kind]
    specs = [("plate", "edge", -1, 0.0, 0.0, 0.0, me.round, 1.0),
             ("fork", "on", 0, 270.0, float(rng.uniform(0.01, 0.035)), me.shift(), float(fork_rot) % 360, 1.0),
             ("knife", "on", 0, 90.0, float(rng.uniform(0.01, 0.035)), me.shift(), float(knife_rot) % 360,
              1.0 if rng.random() < 0.6 else me.p(0.3, 0.9))]
    if rng.random() < 0.5:
        specs.append(("spoon", "beside", 0, 90.0, me.gap(), me.shift(), me.angle, me.p(0.2, 0.8)))
    specs.append(("cup", "beside", 0, float(rng.uniform(20, 70)), me.gap(), 0.0, me.round, 1.0))
    return specs


def _stacked(me: _Person) -> list[Spec]:
    rng = me.rng
    side = 90.0 if rng.random() < 0.6 else 270.0
    bundle = [str(t) for t in rng.permutation(["fork", "knife", "spoon"])[:int(rng.choice([2, 3]))]]
    fan = float(rng.uniform(0, 12))
    specs = [("plate", "edge", -1, 0.0, 0.0, 0.0, me.round, 1.0),
             (bundle[0], "beside", 0, side, me.gap(), me.shift(), me.angle, 1.0)]
    for k, t in enumerate(bundle[1:], start=1):
        specs.append((t, "stack", k, side, -float(rng.uniform(0.012, 0.026)), float(rng.normal(0, 0.015)),
                      (me.angle + k * fan * (1 if side == 90.0 else -1)) % 360, me.p(0.4, 1.0)))
    up = float(rng.uniform(20, 60))
    specs.append(("cup", "beside", 0, 360 - up if side == 90.0 else up, me.gap(), 0.0, me.round, 1.0))
    return specs


def _above(me: _Person) -> list[Spec]:
    rng = me.rng
    types = [str(t) for t in rng.permutation(["fork", "spoon", "knife"])[:int(rng.choice([1, 2, 3], p=[0.3, 0.5, 0.2]))]]
    across = 90.0 if rng.random() < 0.6 else 270.0
    specs = [("plate", "edge", -1, 0.0, 0.0, 0.0, me.round, 1.0)]
    for k, t in enumerate(types):
        specs.append((t, "beside", k, 0.0, me.gap(), me.shift(), (across + rng.normal(0, 3)) % 360,
                      1.0 if k == 0 else me.p(0.4, 1.0)))
    right = rng.random() < 0.8
    up = float(rng.uniform(50, 85))
    specs.append(("cup", "beside", 0, up if right else 360 - up, me.gap(), 0.0, me.round, 1.0))
    return specs


HABIT_RULES = {"classic": _classic, "left_handed": lambda me: _mirrored(_classic(me)), "compact": _compact,
               "on_plate": _on_plate, "stacked": _stacked, "above": _above}


def _seats(rng: np.random.Generator, layout: str) -> list[Seat]:
    side = _pick(rng, SIDE_PRIOR)
    if layout == "single":
        along = float(rng.normal(0, 0.05)) if rng.random() < 0.6 else float(rng.choice([-1, 1]) * rng.uniform(0.2, 0.45))
        return [Seat(side, along, float(rng.uniform(0.02, 0.1)))]
    inset = float(rng.uniform(0.01, 0.05))
    wide = float(rng.uniform(0.42, 0.5))
    pairs = {"opposite": [(side, 0.0), (OPPOSITE[side], 0.0)],
             "beside": [(side, -wide), (side, wide)],
             "three": [(side, -wide), (side, wide), (OPPOSITE[side], 0.0)],
             "four": [(side, -wide), (side, wide), (OPPOSITE[side], -wide), (OPPOSITE[side], wide)]}[layout]
    return [Seat(s, a + float(rng.normal(0, 0.03)), inset) for s, a in pairs]


def _rules(rng: np.random.Generator, me: _Person, specs: list[Spec], n_seats: int, serving: bool) -> list[Rule]:
    """The habit's specs for every seat (and the shared serving plate), in a topological placement order."""
    items = []  # (type, relation, global ref, seat, direction, gap, shift, rotation, p, group)
    for seat in range(n_seats):
        base = len(items)
        for t, rel, ref, d, g, s, r, p in specs:
            items.append((t, rel, -1 if ref < 0 else base + ref, seat, d, g, s, r, p, seat))
    if serving:
        base = len(items)
        items.append(("plate", "centre", -1, 0, float(rng.uniform(0, 360)), float(rng.uniform(0, 0.03)), 0.0, me.round,
                      1.0, -1))
        items.append((str(rng.choice(["spoon", "fork"])), "on", base, 0, float(rng.uniform(0, 360)),
                      float(rng.uniform(0.0, 0.03)), 0.0, float(rng.uniform(0, 360)), 1.0, -1))
    by_type = rng.random() < 0.4
    types = ["fork", "knife", "spoon", "cup"]
    ranks = types if rng.random() < 0.5 else [str(t) for t in rng.permutation(types)]
    rank = {"plate": 0, **{t: k + 1 for k, t in enumerate(ranks)}}
    shared_last = rng.random() < 0.5

    def key(j: int) -> tuple:
        t, group = items[j][0], items[j][9]
        group = (n_seats if shared_last else -0.5) if group < 0 else group
        return (rank[t], group, j) if by_type else (group, rank[t], j)

    placed: list[int] = [0]  # the first seat's plate first
    while len(placed) < len(items):
        ready = [j for j in range(len(items)) if j not in placed and (items[j][2] < 0 or items[j][2] in placed)]
        placed.append(min(ready, key=key))
    where = {j: k for k, j in enumerate(placed)}
    return [Rule(type=t, object=-1, relation=rel, ref=-1 if ref < 0 else where[ref], seat=seat, direction=_r(d % 360),
                 gap=_r(g), shift=_r(s), rotation=_r(r % 360), p_include=_r(p))
            for t, rel, ref, seat, d, g, s, r, p, _ in (items[j] for j in placed)]


def _favourites(rng: np.random.Generator, catalog: Catalog, rules: list[Rule], colors, materials,
                strictness: float) -> None:
    """Distinct favourite objects per rule: per type a ranked draw without replacement (Gumbel top-k)."""
    feats = catalog_features(catalog)
    for t in sorted({r.type for r in rules}):
        mine = [r for r in rules if r.type == t]
        f = feats[t]
        key = favourite_logits(f, colors, materials, strictness) + rng.gumbel(size=len(f.ids))
        for r, i in zip(mine, np.argsort(-key, kind="stable")[:len(mine)]):
            r.object = int(f.ids[i])


def relational_violations(style: RelationalStyle) -> tuple[str, ...]:
    """Why some trial of `style` could be implausible (plausible.RULES names); () when none can be."""
    broken = list(violations([r.type for r in style.rules]))
    if any(r.type == "plate" and r.p_include < 1.0 for r in style.rules):
        broken.append("plates")
    core = [r.type for r in style.rules if r.p_include >= 1.0]
    if sum(t in UTENSILS for t in core) < core.count("plate"):
        broken.append("utensils")
    return tuple(dict.fromkeys(broken))


def fits_everywhere(style: RelationalStyle, tables) -> bool:
    """Whether the style's oracle arrangement fits on every table (footprints on the surface, no overlaps)."""
    idx = oracle_rules(style)
    return all(place(style, table, idx, None)[2] for table in tables)


def _draw(rng: np.random.Generator, participant: str, catalog: Catalog, multi: float, noise: float) -> RelationalStyle:
    me = _Person(rng)
    habit = _pick(rng, HABITS)
    layout = "single" if rng.random() >= multi else _pick(rng, LAYOUTS)
    seats = _seats(rng, layout)
    serving = len(seats) in (2, 3) and rng.random() < 0.4
    rules = _rules(rng, me, HABIT_RULES[habit](me), len(seats), serving)
    n_colors = int(rng.choice([1, 2, 3], p=[0.5, 0.4, 0.1]))
    colors = [str(c) for c in rng.choice(list(COLOR_PRIOR), size=n_colors, replace=False,
                                         p=np.array(list(COLOR_PRIOR.values())) / sum(COLOR_PRIOR.values()))]
    materials = [str(m) for m in rng.choice(list(MATERIAL_PRIOR), size=int(rng.choice([1, 2], p=[0.7, 0.3])),
                                            replace=False, p=np.array(list(MATERIAL_PRIOR.values()))
                                            / sum(MATERIAL_PRIOR.values()))]
    strictness = _r(rng.uniform(0, 5))
    _favourites(rng, catalog, rules, set(colors), set(materials), strictness)
    rel_noise = RelNoise(position=_r(noise * np.exp(rng.uniform(np.log(0.003), np.log(0.012)))),
                         rotation=_r(noise * rng.uniform(2, 10)), direction=_r(noise * rng.uniform(1, 6)),
                         gap=_r(noise * rng.uniform(0.002, 0.012)), seat=_r(noise * rng.uniform(0.01, 0.06)),
                         turn=_r(noise * rng.uniform(0, 6)), order=_r(min(1.0, noise * rng.uniform(0, 0.25))))
    base, sensitivity = sample_rating_traits(rng)
    for s in seats:
        s.along, s.inset = _r(s.along), _r(s.inset)
    return RelationalStyle(participant=participant, habit=habit, layout=layout, seats=seats, rules=rules,
                           colors=colors, materials=materials, strictness=strictness,
                           loyalty=_r(rng.uniform(0.5, 0.95)), noise=rel_noise, rating_base=_r(base),
                           rating_sensitivity=_r(sensitivity))


def _plain(rng: np.random.Generator, participant: str, catalog: Catalog, noise: float) -> RelationalStyle:
    """The fallback person: a plate at the middle of the near edge, a fork left of it, a cup above-right."""
    style = _draw(rng, participant, catalog, 0.0, noise)
    style.habit, style.layout, style.seats = "compact", "single", [Seat("near", 0.0, 0.05)]
    style.rules = [Rule("plate", -1, "edge"), Rule("fork", -1, "beside", 0, 0, 270.0, 0.02),
                   Rule("cup", -1, "beside", 0, 0, 40.0, 0.02)]
    _favourites(rng, catalog, style.rules, set(style.colors), set(style.materials), style.strictness)
    return style


def sample_relational_style(rng: np.random.Generator, participant: str, catalog: Catalog, tables: list[Table],
                            multi: float = 0.2, noise: float = 1.0) -> RelationalStyle:
    """Draw one relational participant's latent style (distributions in the module docstring), conditioned on
    plausibility and on its oracle arrangement fitting every table of `tables`."""
    for _ in range(MAX_DRAWS):
        style = _draw(rng, participant, catalog, multi, noise)
        if not relational_violations(style) and fits_everywhere(style, tables):
            return style
    return _plain(rng, participant, catalog, noise)


def _r(x) -> float:
    """Styles are stored rounded (5 decimals), and used exactly as stored."""
    return round(float(x), 5)
