"""Procedural object outlines: the part masks of a sprite, per object type and shape (numpy only).

A sprite covers the object's footprint (scene.object_size: width across, length along) at rotation 0,
long axis pointing north. Masks are computed on sprite coordinates `u` (across, -0.5 left .. 0.5 right)
and `v` (along, -0.5 top/north .. 0.5 bottom), with `aspect` = physical length / width so round parts
stay round. Every shape returns its parts in drawing order as (role, mask); roles say which colour and
material paints them (see sprites.py):

    fork, knife, spoon   "handle" (colour1/material1) and "head" (tines, blade, bowl: colour2/material2),
                         plus "rivet" (metal dots on a wooden knife handle) and "bowl_in" (spoon hollow)
    plate                "rim" (colour2/material2) and "well" (colour1/material1)
    cup                  "handle" and "rim" (colour2/material2), "interior" (colour1/material1)

Conventions at rotation 0: a fork's tines, a knife's tip and a spoon's bowl are at the top (north); a
cup's handle points north (a cup "points" where its handle does); an oval plate is long north-south.

`footprint_points` turns the union of the masks into points (normalized table units around the
centroid) that grid.py uses to find the cells an object covers, so grid cells agree with the drawing.
"""

from __future__ import annotations

import functools

import numpy as np

Mask = np.ndarray  # (H, W) bool


def coords(w_px: int, l_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre sprite coordinates u, v, each (l_px, w_px)."""
    xs = ((np.arange(w_px) + 0.5) / w_px - 0.5).astype(np.float32)
    ys = ((np.arange(l_px) + 0.5) / l_px - 0.5).astype(np.float32)
    u, v = np.meshgrid(xs, ys)
    return u, v


def _ellipse(u, v, cu, cv, ru, rv) -> Mask:
    return ((u - cu) / ru) ** 2 + ((v - cv) / rv) ** 2 <= 1.0


def _smooth(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _handle(u, v, aspect, v0, hw0, hw1, v_end=0.5) -> Mask:
    """A cutlery handle from v0 (width 2*hw0) widening to 2*hw1 with a rounded end at v_end."""
    cap_rv = hw1 / aspect
    v1 = v_end - cap_rv
    hw = hw0 + (hw1 - hw0) * _smooth((v - v0) / max(v1 - v0, 1e-6))
    strip = (v >= v0) & (v <= v1) & (np.abs(u) <= hw)
    cap = _ellipse(u, v, 0.0, v1, hw1, cap_rv) & (v >= v1)
    return strip | cap


def fork(u, v, aspect, shape) -> list[tuple[str, Mask]]:
    slim = shape == "slim"
    n = 3 if slim else 4
    tine_w = 0.2 if slim else 0.155
    gap = (0.92 - n * tine_w) / (n - 1)
    tips = -0.49
    base_top = -0.24 if shape != "curved" else -0.2
    head = np.zeros_like(u, dtype=bool)
    for k in range(n):
        c = -0.46 + tine_w / 2 + k * (tine_w + gap)
        hw = np.full_like(u, tine_w / 2)
        if shape == "curved":  # pointed tines
            hw = tine_w / 2 * np.clip((v - tips) / 0.12, 0.25, 1.0)
        tine = (np.abs(u - c) <= hw) & (v >= tips) & (v <= base_top + 0.02)
        tip_cap = _ellipse(u, v, c, tips, tine_w / 2, tine_w / 2 / aspect) if shape != "curved" else False
        head |= tine | tip_cap
    # the base that joins the tines, narrowing into the neck
    t = (v - base_top) / 0.14
    hw = 0.46 - (0.46 - 0.1) * _smooth(t)
    head |= (v >= base_top) & (v <= base_top + 0.16) & (np.abs(u) <= hw)
    neck = (v >= base_top + 0.14) & (v <= 0.06) & (np.abs(u) <= 0.1)
    head |= neck
    handle = _handle(u, v, aspect, 0.04, 0.12, 0.27 if slim else 0.34)
    return [("handle", handle), ("head", head & ~handle)]


def knife(u, v, aspect, shape) -> list[tuple[str, Mask]]:
    spine, edge, v_tip = -0.34, 0.34, -0.5
    curve_start = -0.2
    # blade edge x as a function of v: straight down the blade, curving up to the tip on the spine side
    t = np.clip((v - curve_start) / (v_tip - curve_start), 0.0, 1.0)  # 0 at curve start, 1 at the tip
    edge_x = spine + (edge - spine) * np.sqrt(np.clip(1 - t**2, 0, 1))
    spine_x = np.full_like(u, spine)
    if shape == "rounded":  # round tip: the spine curves too
        spine_x = spine + 0.25 * (1 - np.sqrt(np.clip(1 - t**2, 0, 1)))
        edge_x = np.maximum(edge_x, spine_x)
    if shape == "serrated":
        teeth = np.abs(((v * aspect * 6.0) % 1.0) - 0.5) * 0.16
        edge_x = np.where(v > curve_start - 0.05, edge_x - teeth, edge_x)
    blade = (v >= v_tip) & (v <= 0.0) & (u >= spine_x) & (u <= edge_x)
    bolster = (v >= -0.02) & (v <= 0.05) & (np.abs(u) <= 0.32)
    handle = _handle(u, v, aspect, 0.05, 0.36, 0.42)
    return [("handle", handle), ("head", (blade | bolster) & ~handle)]


def knife_rivets(u, v, aspect) -> Mask:
    r = 0.12
    out = np.zeros_like(u, dtype=bool)
    for vc in (0.17, 0.29, 0.41):
        out |= _ellipse(u, v, 0.0, vc, r, r / aspect)
    return out


def spoon(u, v, aspect, shape) -> list[tuple[str, Mask]]:
    ru, elong = {"oval": (0.44, 1.55), "deep": (0.5, 1.25)}.get(shape, (0.49, 1.2))
    rv = ru * elong / aspect
    cv = -0.5 + rv + 0.005
    bowl = _ellipse(u, v, 0.0, cv, ru, rv)
    bowl_in = _ellipse(u, v, 0.0, cv - 0.1 * rv, ru * 0.72, rv * 0.72)
    neck = (v >= cv) & (v <= 0.08) & (np.abs(u) <= 0.09 + 0.04 * _smooth((v - cv) / (0.08 - cv)))
    handle = _handle(u, v, aspect, 0.06, 0.13, 0.29)
    head = (bowl | neck) & ~handle
    return [("handle", handle), ("head", head), ("bowl_in", bowl_in)]


def plate(u, v, aspect, shape) -> list[tuple[str, Mask]]:
    if shape == "square":
        def inside(r, corner):
            qu, qv = np.maximum(np.abs(u) - (r - corner), 0), np.maximum(np.abs(v) - (r - corner), 0)
            return qu**2 + qv**2 <= corner**2
        outer, well = inside(0.49, 0.1), inside(0.34, 0.06)
    elif shape == "oval":
        outer, well = _ellipse(u, v, 0, 0, 0.39, 0.49), _ellipse(u, v, 0, 0, 0.39 * 0.66, 0.49 * 0.7)
    elif shape == "octagonal":
        octa = np.maximum(np.maximum(np.abs(u), np.abs(v)), (np.abs(u) + np.abs(v)) / np.sqrt(2))
        outer, well = octa <= 0.49, octa <= 0.33
    else:
        r = np.hypot(u, v)
        outer, well = r <= 0.49, r <= 0.32
    return [("rim", outer & ~well), ("well", well)]


def cup(u, v, aspect, shape) -> list[tuple[str, Mask]]:
    radius, cv = {"tall": (0.37, 0.11), "mug": (0.39, 0.1)}.get(shape, (0.4, 0.09))
    top = cv - radius
    # the handle: a flat half-ring "ear" (outer ellipse minus a hole) sticking out north of the body
    reach = top + 0.49  # how far north of the body the handle reaches
    ho, hh = (0.25, 0.13) if shape == "mug" else (0.2, 0.1)
    outer = _ellipse(u, v, 0.0, top + 0.02, ho, reach + 0.02)
    hole = _ellipse(u, v, 0.0, top + 0.02, hh, (reach + 0.02) * 0.52)
    r = np.hypot(u, v - cv)
    body = r <= radius
    wall = 0.2 if shape == "mug" else 0.15
    interior = r <= radius * (1 - wall)
    handle = outer & ~hole & ~body
    return [("handle", handle), ("rim", body & ~interior), ("interior", interior)]


def generic(u, v, aspect, shape) -> list[tuple[str, Mask]]:
    """Unknown object types: a rounded box."""
    qu, qv = np.maximum(np.abs(u) - 0.38, 0), np.maximum(np.abs(v) - 0.38, 0)
    return [("well", qu**2 + qv**2 <= 0.1**2)]


SHAPES = {"fork": fork, "knife": knife, "spoon": spoon, "plate": plate, "cup": cup}


def parts(type_: str, shape: str, w_px: int, l_px: int, aspect: float) -> tuple[np.ndarray, np.ndarray, list]:
    """(u, v, [(role, mask), ...]) of a `type_`/`shape` sprite of w_px x l_px pixels."""
    u, v = coords(w_px, l_px)
    return u, v, SHAPES.get(type_, generic)(u, v, aspect, shape)


FOOTPRINT_PITCH = 0.0025  # normalized table units per mask pixel when building footprint points


@functools.lru_cache(maxsize=256)
def footprint_points(type_: str, shape: str, width: float, length: float, rectangle: bool = False) -> np.ndarray:
    """(N, 2) points (x right, y down; normalized table units, centroid at 0) covered at rotation 0.

    The points are the pixel centres of the sprite's outline mask at a pitch of FOOTPRINT_PITCH (so a
    cell the drawn object reaches into by more than ~half a pitch is found). `rectangle=True`
    gives the full footprint rectangle (used for objects drawn from a picture).
    """
    w_px = max(2, int(np.ceil(width / FOOTPRINT_PITCH)))
    l_px = max(2, int(np.ceil(length / FOOTPRINT_PITCH)))
    if rectangle:
        u, v = coords(w_px, l_px)
        mask = np.ones_like(u, dtype=bool)
    else:
        u, v, ps = parts(type_, shape, w_px, l_px, length / width)
        mask = np.zeros_like(u, dtype=bool)
        for _role, m in ps:
            mask |= m
    pts = np.stack([u[mask] * width, v[mask] * length], axis=1)
    return pts.astype(np.float64)
