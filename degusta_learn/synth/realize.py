"""Turn a latent style into arrangements on a table: noisy samples (the data) and the expected one (oracle).

A trial of a style on a table is made in this order (SYNTHETIC data; every choice is in docs/data.md):

1. **count**: each slot is set with probability `p_include` (at least 3 slots: the most likely are added);
2. **order**: the person's slot order with adjacent swaps, each with probability `noise.order`;
3. **objects**: each slot gets its favourite object with probability `loyalty`, otherwise another
   unused object of its type drawn with weight `exp(strictness * taste)`, where taste = the share of the
   object's colours among the favourite colours + half the share of its materials among the favourite
   materials;
4. **where**: each setting's anchor `(u, v)` (+ a per-trial shift ~ N(0, noise.anchor)) is mapped onto
   the surface's bounding box; slot offsets are scaled by `scale * exp(N(0, noise.scale))`, rotated by the
   setting's facing, the whole layout is turned about its mean anchor by N(0, noise.turn) degrees, and
   each object moves by N(0, noise.position) and turns by N(0, noise.rotation);
5. **fit**: `geometry.fit_into` keeps footprints on the surface; a draw whose objects overlap by more than
   `MAX_OVERLAP` is redrawn (up to 4 times).

`expected_arrangement` is the same without any noise: slots with p_include >= 0.5, favourite objects,
no shift, turn or spacing change. It is the oracle's prediction.
"""

from __future__ import annotations

import math

import numpy as np

from degusta_learn.scene import Catalog, Placement, Table
from degusta_learn.synth.geometry import bounds, fit_into, max_overlap, sizes_of
from degusta_learn.synth.style import Style
from degusta_learn.synth.taste import catalog_features

MAX_OVERLAP = 0.3
MIN_OBJECTS = 3


def taste_weights(style: Style, catalog: Catalog) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per type: (object ids, unnormalized weights exp(strictness * taste)) of non-favourite picks."""
    feats = catalog_features(catalog)
    return {t: (feats[t].ids, np.exp(style.strictness * feats[t].taste(style.colors, style.materials)))
            for t in {s.type for s in style.slots}}


def layout(style: Style, table: Table, idx: list[int], shift=(0.0, 0.0), turn: float = 0.0,
           log_scale: float = 0.0, pos_noise=None, rot_noise=None) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) and rotations (N,) of slots `idx` on `table`, before fitting."""
    # Plain-Python arithmetic: N is ~5, where numpy's per-call overhead dominates.
    x0, y0, x1, y1 = bounds(table)
    w, h = x1 - x0, y1 - y0
    sets = style.settings
    k = style.scale * math.exp(log_scale)
    t = math.radians(turn)
    ct, st = math.cos(t), math.sin(t)
    px = x0 + (sum(s.u for s in sets) / len(sets) + shift[0]) * w  # pivot: the mean anchor
    py = y0 + (sum(s.v for s in sets) / len(sets) + shift[1]) * h
    xy, rot = [], []
    for i in idx:
        slot = style.slots[i]
        setting = sets[slot.setting]
        f = math.radians(setting.facing)
        cf, sf = math.cos(f), math.sin(f)
        dx, dy = slot.dx * k, slot.dy * k
        x = x0 + (setting.u + shift[0]) * w + dx * cf - dy * sf - px
        y = y0 + (setting.v + shift[1]) * h + dx * sf + dy * cf - py
        xy.append((px + x * ct - y * st, py + x * st + y * ct))
        rot.append(slot.rotation + setting.facing + turn)
    xy, rot = np.array(xy), np.array(rot)
    if pos_noise is not None:
        xy = xy + pos_noise
    if rot_noise is not None:
        rot = rot + rot_noise
    return xy, rot % 360.0


def _placements(objects: list[int], xy: np.ndarray, rot: np.ndarray) -> list[Placement]:
    return [Placement(int(o), float(x), float(y), float(r)) for o, (x, y), r in zip(objects, xy, rot % 360.0)]


def _least(style: Style, chosen: list[int]) -> list[int]:
    """Top up a slot selection to MIN_OBJECTS with the most likely remaining slots (keeps style order)."""
    if len(chosen) >= MIN_OBJECTS:
        return chosen
    rest = sorted((i for i in range(len(style.slots)) if i not in chosen),
                  key=lambda i: (-style.slots[i].p_include, i))
    return sorted(chosen + rest[:MIN_OBJECTS - len(chosen)])


def expected_arrangement(style: Style, table: Table) -> list[Placement]:
    """The style on `table` without noise: the oracle's prediction."""
    idx = _least(style, [i for i, s in enumerate(style.slots) if s.p_include >= 0.5])
    xy, rot = layout(style, table, idx)
    sizes = sizes_of([style.slots[i].type for i in idx])
    xy = fit_into(table, xy, rot, sizes)
    return _placements([style.slots[i].object for i in idx], xy, rot)


def sample_arrangement(style: Style, table: Table, catalog: Catalog, rng: np.random.Generator,
                       weights: dict | None = None) -> list[Placement]:
    """One noisy trial of `style` on `table` (steps 1-5 of the module docstring)."""
    weights = weights if weights is not None else taste_weights(style, catalog)
    noise = style.noise
    idx = _least(style, [i for i, s in enumerate(style.slots) if s.p_include >= 1.0 or rng.random() < s.p_include])
    for k in range(len(idx) - 1):
        if rng.random() < noise.order:
            idx[k], idx[k + 1] = idx[k + 1], idx[k]
    favourites = {style.slots[i].object for i in idx}
    used: set[int] = set()
    objects = []
    for i in idx:
        slot = style.slots[i]
        if slot.object not in used and rng.random() < style.loyalty:
            pick = slot.object
        else:
            ids, w = weights[slot.type]
            ok = np.array([o not in used and o not in favourites for o in ids.tolist()])
            if not ok.any():
                ok = np.array([o not in used for o in ids.tolist()])
            p = w * ok
            pick = int(rng.choice(ids, p=p / p.sum()))
        used.add(pick)
        objects.append(pick)
    shift = rng.normal(0.0, noise.anchor, size=2)
    turn = rng.normal(0.0, noise.turn)
    log_scale = rng.normal(0.0, noise.scale)
    sizes = sizes_of([style.slots[i].type for i in idx])
    for _attempt in range(4):
        xy, rot = layout(style, table, idx, shift, turn, log_scale,
                         rng.normal(0.0, noise.position, size=(len(idx), 2)),
                         rng.normal(0.0, noise.rotation, size=len(idx)))
        xy = fit_into(table, xy, rot, sizes)
        if max_overlap(xy, rot, sizes) <= MAX_OVERLAP:
            break
    return _placements(objects, xy, rot)
