"""Sampling the latent style of a synthetic naturalistic participant (SYNTHETIC data).

`sample_style(rng, participant, catalog)` draws, independently per participant:

- a layout **template** from `TEMPLATES` (probabilities in brackets): `western` [0.30] (plate; fork(s)
  left; knife, spoon right; cup above right; optional salad fork and dessert spoon), `mirrored` [0.10]
  (the same, left-right mirrored), `minimal` [0.15] (plate, one utensil, cup; rarely a knife), `multi`
  [0.13] (2-4 place settings, facing each other or side by side), `row` [0.12] (3-6 objects in a line)
  and `freeform` [0.20] (3-8 objects at person-specific random spots, with person-specific rotations; a
  spot is tried 60 times, and when fewer than 3 objects found room, cups are added where most room is);
- an **anchor**: near edge [0.45], centre [0.25], a near corner [0.15], a side [0.10] or the far edge
  [0.05] of the surface, plus a personal offset ~ N(0, 0.04) per coordinate, clipped to [0.12, 0.88];
- the **utensil angle**: 0 (pointing to the far side) [0.55], 45 or 315 [0.1 each], 90 [0.1], 270 or
  180 [0.05 each], plus a personal offset ~ N(0, 4) degrees; round objects keep 0 [0.8] or one personal
  angle; horizontal utensils are stacked beside the plate instead of in a row;
- **spacing** `scale` ~ U[0.85, 1.25] (`multi`: U[0.8, 1.0]);
- **how many**: core slots always set, optional slots with p_include ~ U[0.2, 1.0];
- **order**: the template's order [0.5] or a personal random permutation [0.5];
- **taste**: 1-3 favourite colours (drawn with `COLOR_PRIOR`), 1-2 favourite materials (`MATERIAL_PRIOR`),
  strictness ~ U[0, 5], loyalty ~ U[0.5, 0.95]; favourite objects per type are drawn without
  replacement with weight popularity x exp((strictness + 1) * taste), so ids are partly predictable;
- **noise**: position log-uniform in [0.004, 0.02], rotation U[2, 12] deg, anchor U[0.01, 0.05],
  turn U[0, 6] deg, spacing U[0.02, 0.08], order swaps U[0, 0.25];
- **ratings**: `rating_base` ~ U[60, 98] and a log-normal `rating_sensitivity` (see ratings.py).

With `plausible=True`, `row` and `freeform` draw their types from the same prior conditioned on the rules of
plausible.py, and always set their plates and a utensil per plate; every other draw is the same.
"""

from __future__ import annotations

import numpy as np

from degusta_learn.scene import Catalog
from degusta_learn.synth.plausible import core_mask, plausible_types, violations
from degusta_learn.synth.ratings import sample_rating_traits
from degusta_learn.synth.style import Noise, Setting, Slot, Style
from degusta_learn.synth.taste import TypeFeatures, catalog_features

TEMPLATES = {"western": 0.30, "mirrored": 0.10, "minimal": 0.15, "multi": 0.13, "row": 0.12, "freeform": 0.20}
ANCHORS = {"near_edge": 0.45, "centre": 0.25, "corner": 0.15, "side": 0.10, "far_edge": 0.05}
UTENSIL_ANGLES = {0: 0.55, 45: 0.10, 315: 0.10, 90: 0.10, 270: 0.05, 180: 0.05}
COLOR_PRIOR = {"silver": 1.5, "white": 1.2, "black": 1.2, "blue": 1.2, "red": 1.0, "gray": 1.0, "yellow": 0.9,
               "green": 0.8, "gold": 0.8, "beige": 0.8, "brown": 0.8, "pink": 0.7, "purple": 0.7}
MATERIAL_PRIOR = {"metal": 1.3, "ceramic": 1.2, "glass": 1.0, "plastic": 0.8, "wood": 0.8}
TYPE_PRIOR = {"plate": 0.25, "cup": 0.2, "fork": 0.2, "knife": 0.15, "spoon": 0.2}
PLATE_R = 0.085  # half a plate (catalog TYPE_SIZE)
MIN_SLOTS = 3  # every style has at least realize.MIN_OBJECTS slots, so every trial can set that many

Spec = tuple  # (type, dx, dy, rotation, p_include, setting)


def _pick(rng: np.random.Generator, prior: dict):
    """A key of `prior` drawn with probability proportional to its value."""
    u = rng.random() * sum(prior.values())
    for key, weight in prior.items():
        u -= weight
        if u < 0:
            return key
    return key


def _utensils(types, side: int, angle: float, setting: int = 0, p=None) -> list[Spec]:
    """Utensils beside a plate at the origin: a row (upright/diagonal) or a stack (horizontal)."""
    p = p or [1.0] * len(types)
    horizontal = abs(np.sin(np.radians(angle))) > 0.85
    out = []
    for k, (t, pk) in enumerate(zip(types, p)):
        if horizontal:
            dx, dy = side * (PLATE_R + 0.11), (k - (len(types) - 1) / 2) * 0.048
        else:
            gap = 0.048 if abs(np.sin(np.radians(angle))) < 0.3 else 0.062
            dx, dy = side * (PLATE_R + gap * (k + 1) - 0.003), 0.0
        out.append((t, dx, dy, angle, pk, setting))
    return out


def _western(rng, angle, round_rot, setting=0, with_extras=True) -> list[Spec]:
    p_knife = 1.0 if rng.random() < 0.7 else rng.uniform(0.3, 0.9)
    left = ["fork"] + (["fork"] if with_extras and rng.random() < 0.3 else [])
    p_left = [1.0] + [rng.uniform(0.2, 0.9)] * (len(left) - 1)
    specs = [("plate", 0.0, 0.0, round_rot, 1.0, setting)]
    specs += _utensils(left, -1, angle, setting, p_left)
    specs += _utensils(["knife", "spoon"], 1, angle, setting, [p_knife, rng.uniform(0.2, 1.0)])
    specs.append(("cup", 0.17, -0.16, round_rot, rng.uniform(0.3, 1.0), setting))
    if with_extras and rng.random() < 0.25 and abs(np.sin(np.radians(angle))) < 0.85:
        specs.append(("spoon", 0.0, -0.135, 90.0, rng.uniform(0.2, 0.9), setting))
    return specs


def _minimal(rng, angle, round_rot) -> list[Spec]:
    side = 1 if rng.random() < 0.6 else -1
    utensil = _pick(rng, {"fork": 0.5, "spoon": 0.3, "knife": 0.2})
    specs = [("plate", 0.0, 0.0, round_rot, 1.0, 0)] + _utensils([utensil], side, angle)
    specs.append(("cup", side * -0.15 if rng.random() < 0.3 else side * 0.16, -0.16, round_rot, 1.0, 0))
    if utensil != "knife" and rng.random() < 0.5:
        specs += _utensils(["knife"], -side, angle, 0, [rng.uniform(0.1, 0.5)])
    return specs


def _multi(rng, angle, round_rot) -> tuple[list[Setting], list[Spec]]:
    layouts = [[(0.5, 0.8, 0), (0.5, 0.2, 180)], [(0.27, 0.78, 0), (0.73, 0.78, 0)],
               [(0.27, 0.8, 0), (0.73, 0.8, 0), (0.5, 0.2, 180)],
               [(0.27, 0.8, 0), (0.73, 0.8, 0), (0.27, 0.2, 180), (0.73, 0.2, 180)]]
    chosen = layouts[int(rng.choice(4, p=[0.35, 0.2, 0.2, 0.25]))]
    settings = [Setting(float(np.clip(u + rng.normal(0, 0.02), 0.1, 0.9)), float(np.clip(v + rng.normal(0, 0.02), 0.1, 0.9)),
                        float(f)) for u, v, f in chosen]
    p_cup, p_spoon = rng.uniform(0.2, 1.0), rng.uniform(0.0, 0.8)
    specs = []
    for s in range(len(settings)):
        specs += [("plate", 0.0, 0.0, round_rot, 1.0, s)] + _utensils(["fork"], -1, angle, s)
        specs += _utensils(["knife", "spoon"], 1, angle, s, [1.0, p_spoon])
        specs.append(("cup", 0.17, -0.16, round_rot, p_cup, s))
    return settings, specs


def _extent(t: str, rot: float, axis: int) -> float:
    from degusta_learn.scene import TYPE_SIZE

    w, length = TYPE_SIZE[t]
    r = np.radians(rot)
    return abs(w * np.cos(r)) + abs(length * np.sin(r)) if axis == 0 else abs(w * np.sin(r)) + abs(length * np.cos(r))


def _row(rng, angle, round_rot, plausible: bool = False) -> list[Spec]:
    n = int(rng.integers(3, 7))
    types = plausible_types(rng, n, _type) if plausible else [_pick(rng, TYPE_PRIOR) for _ in range(n)]
    n = len(types)
    rots = [round_rot if t in ("plate", "cup") else angle for t in types]
    axis = 0 if rng.random() < 0.75 else 1  # a horizontal line, or a vertical one
    gap = rng.uniform(0.012, 0.04)
    ext = [_extent(t, r, axis) for t, r in zip(types, rots)]
    pos = np.concatenate([[0.0], np.cumsum([(a + b) / 2 + gap for a, b in zip(ext[:-1], ext[1:])])])
    pos -= pos.mean()
    if plausible:  # plates and a utensil per plate always set: plausible.core_mask
        p = [1.0 if core else rng.uniform(0.3, 0.95) for core in core_mask(types)]
    else:
        p = [1.0, 1.0, 1.0] + [rng.uniform(0.3, 0.95) for _ in range(n - 3)]
    return [(t, float(c) if axis == 0 else 0.0, float(c) if axis == 1 else 0.0, r, pk, 0)
            for t, c, r, pk in zip(types, pos, rots, p)]


def _freeform(rng, round_rot) -> list[Spec]:
    from degusta_learn.scene import TYPE_SIZE

    n = int(rng.integers(3, 9))
    half = rng.uniform(0.14, 0.3)
    specs, placed = [], []
    for k in range(n):
        t = _pick(rng, TYPE_PRIOR)
        r_k = max(TYPE_SIZE[t]) / 2
        for _ in range(60):
            c = rng.uniform(-half, half, size=2)
            if all(np.hypot(*(c - q)) > r_k + rq + 0.01 for q, rq in placed):
                break
        else:
            continue
        placed.append((c, r_k))
        rot = round_rot if t in ("plate", "cup") else float(rng.uniform(0, 360))
        specs.append((t, float(c[0]), float(c[1]), rot, 1.0 if k < 3 else rng.uniform(0.4, 1.0), 0))
    while len(specs) < MIN_SLOTS:  # crowded out: add a cup (the smallest object) where there is most room
        r_k = max(TYPE_SIZE["cup"]) / 2
        spots = rng.uniform(-max(half, 0.2), max(half, 0.2), size=(64, 2))
        room = np.array([min((np.hypot(*(c - q)) - rq for q, rq in placed), default=1.0) for c in spots])
        c = spots[int(np.argmax(room))]
        placed.append((c, r_k))
        specs.append(("cup", float(c[0]), float(c[1]), round_rot, 1.0, 0))
    return specs


def _type(rng) -> str:
    return _pick(rng, TYPE_PRIOR)


def _freeform_plausible(rng, round_rot, attempts: int = 50) -> list[Spec]:
    """`_freeform` with types drawn under the plausibility rules (plausible.py): a slot that finds no room is
    dropped, and a draw whose placed slots break a rule (or are fewer than 3) is redrawn whole."""
    from degusta_learn.scene import TYPE_SIZE

    for _ in range(attempts):
        types = plausible_types(rng, int(rng.integers(3, 9)), _type)
        half = rng.uniform(0.14, 0.3)
        placed, kept = [], []
        for t in types:
            r_k = max(TYPE_SIZE[t]) / 2
            for _ in range(60):
                c = rng.uniform(-half, half, size=2)
                if all(np.hypot(*(c - q)) > r_k + rq + 0.01 for q, rq in placed):
                    placed.append((c, r_k))
                    kept.append((t, c))
                    break
        kept_types = [t for t, _ in kept]
        if len(kept) >= MIN_SLOTS and not violations(kept_types):
            break
    else:  # never reached in practice: a plate with a fork and a cup always fit
        kept_types = ["plate", "fork", "cup"]
        kept = list(zip(kept_types, np.array([[0.0, 0.0], [-0.13, 0.0], [0.15, -0.15]])))
    specs = []
    for (t, c), core in zip(kept, core_mask(kept_types)):
        rot = round_rot if t in ("plate", "cup") else float(rng.uniform(0, 360))
        specs.append((t, float(c[0]), float(c[1]), rot, 1.0 if core else rng.uniform(0.4, 1.0), 0))
    return specs


def _anchor(rng) -> Setting:
    kind = _pick(rng, ANCHORS)
    side = 0.22 if rng.random() < 0.5 else 0.78
    u, v = {"near_edge": (0.5, 0.78), "centre": (0.5, 0.5), "corner": (side, 0.75), "side": (side, 0.5),
            "far_edge": (0.5, 0.25)}[kind]
    u, v = np.clip([u + rng.normal(0, 0.04), v + rng.normal(0, 0.04)], 0.12, 0.88)
    return Setting(float(u), float(v), 0.0)


def favourite_logits(f: TypeFeatures, colors, materials, strictness: float) -> np.ndarray:
    """(n,) log weights of the objects of one type as a style's favourite: popularity x exp((strictness + 1) x
    taste). The favourites are drawn without replacement with these weights (Gumbel top-k), so the first
    favourite of a type is the softmax of these logits."""
    pop = np.log(f.colors @ [COLOR_PRIOR.get(c, 0.8) for c in f.color_names]) \
        + np.log(f.materials @ [MATERIAL_PRIOR.get(m, 0.8) for m in f.material_names] / 2)
    return pop + (strictness + 1) * f.taste(colors, materials)


def _favourites(rng, catalog: Catalog, specs, colors, materials, strictness) -> list[int]:
    """Distinct favourite objects per slot: per type a ranked draw without replacement (Gumbel top-k)."""
    need: dict[str, int] = {}
    for t, *_ in specs:
        need[t] = need.get(t, 0) + 1
    feats = catalog_features(catalog)
    ranked = {}
    for t, k in need.items():
        f = feats[t]
        key = favourite_logits(f, colors, materials, strictness) + rng.gumbel(size=len(f.ids))
        ranked[t] = [int(f.ids[i]) for i in np.argsort(-key, kind="stable")[:k]]
    seen: dict[str, int] = {}
    out = []
    for t, *_ in specs:
        out.append(int(ranked[t][seen.get(t, 0)]))
        seen[t] = seen.get(t, 0) + 1
    return out


def sample_style(rng: np.random.Generator, participant: str, catalog: Catalog, plausible: bool = False) -> Style:
    """Draw one synthetic participant's latent style (distributions in the module docstring).

    `plausible`: `row` and `freeform` draw their types under the rules of plausible.py (the other templates keep
    them already); off, the draws are exactly the default generator's.
    """
    template = _pick(rng, TEMPLATES)
    angle = float((_pick(rng, UTENSIL_ANGLES) + rng.normal(0, 4)) % 360)
    round_rot = 0.0 if rng.random() < 0.8 else float(rng.uniform(0, 360))
    settings = [_anchor(rng)]
    scale = float(rng.uniform(0.85, 1.25))
    if template in ("western", "mirrored"):
        specs = _western(rng, angle, round_rot)
        if template == "mirrored":
            specs = [(t, -dx, dy, (-r) % 360, p, s) for t, dx, dy, r, p, s in specs]
    elif template == "minimal":
        specs = _minimal(rng, angle, round_rot)
    elif template == "multi":
        settings, specs = _multi(rng, angle, round_rot)
        scale = float(rng.uniform(0.8, 1.0))
    elif template == "row":
        specs = _row(rng, angle, round_rot, plausible)
    else:
        specs = _freeform_plausible(rng, round_rot) if plausible else _freeform(rng, round_rot)
    if rng.random() < 0.5:
        specs = [specs[i] for i in rng.permutation(len(specs))]
    n_colors = int(rng.choice([1, 2, 3], p=[0.5, 0.4, 0.1]))
    colors = list(rng.choice(list(COLOR_PRIOR), size=n_colors, replace=False,
                             p=np.array(list(COLOR_PRIOR.values())) / sum(COLOR_PRIOR.values())))
    materials = list(rng.choice(list(MATERIAL_PRIOR), size=int(rng.choice([1, 2], p=[0.7, 0.3])), replace=False,
                                p=np.array(list(MATERIAL_PRIOR.values())) / sum(MATERIAL_PRIOR.values())))
    strictness = float(rng.uniform(0, 5))
    favourites = _favourites(rng, catalog, specs, set(colors), set(materials), _r(strictness))
    slots = [Slot(type=t, dx=round(float(dx), 5), dy=round(float(dy), 5), rotation=round(float(r) % 360, 3),
                  object=o, setting=int(s), p_include=round(float(p), 4))
             for (t, dx, dy, r, p, s), o in zip(specs, favourites)]
    noise = Noise(position=_r(np.exp(rng.uniform(np.log(0.004), np.log(0.02)))), rotation=_r(rng.uniform(2, 12)),
                  anchor=_r(rng.uniform(0.01, 0.05)), turn=_r(rng.uniform(0, 6)),
                  scale=_r(rng.uniform(0.02, 0.08)), order=_r(rng.uniform(0, 0.25)))
    base, sensitivity = sample_rating_traits(rng)
    for s in settings:
        s.u, s.v = _r(s.u), _r(s.v)
    return Style(participant=participant, template=template, settings=settings, slots=slots,
                 colors=[str(c) for c in colors], materials=[str(m) for m in materials], strictness=_r(strictness),
                 loyalty=_r(rng.uniform(0.5, 0.95)), scale=_r(scale), noise=noise,
                 rating_base=_r(base), rating_sensitivity=_r(sensitivity))


def _r(x: float) -> float:
    """Styles are stored rounded (5 decimals), and used exactly as stored."""
    return round(float(x), 5)
