"""Colours, materials and patterns of procedural sprites (numpy only).

- `rgb(name)`: the colour vocabulary (scene.COLORS) as RGB in [0, 1]; an unknown name gets a stable
  hashed colour.
- `shade(material, ...)`: how a material lights a part: a multiplicative shade, an additive highlight
  and an alpha. wood = grain lines along the long axis; metal = cylindrical gradient with a bright
  specular streak; glass = translucent (alpha ~0.5) with a white glint; ceramic = glossy highlight spot;
  plastic = flat and matte. Unknown materials shade like plastic.
- `pattern(name, ...)`: where a pattern (striped, dotted, checkered, floral, rimmed) paints the accent
  colour; plates and cups carry it over their whole face, cutlery on the handle.

All randomness (wood grain) comes from an RNG seeded by the object's description, so a sprite is the
same in every process.
"""

from __future__ import annotations

import hashlib

import numpy as np

PALETTE = {
    "beige": (226, 206, 166), "black": (38, 38, 42), "blue": (38, 96, 204), "brown": (124, 78, 42),
    "gold": (214, 172, 52), "gray": (132, 134, 140), "green": (46, 150, 72), "pink": (242, 138, 182),
    "purple": (128, 66, 172), "red": (208, 38, 38), "silver": (196, 200, 206), "white": (246, 246, 243),
    "yellow": (246, 206, 36),
}


def stable_rng(*parts) -> np.random.Generator:
    """A numpy Generator seeded by a hash of `parts` (stable across processes, unlike hash())."""
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def rgb(name: str) -> np.ndarray:
    """Colour name -> (3,) float RGB in [0, 1]; unknown names get a hashed, mid-saturated colour."""
    if name in PALETTE:
        return np.asarray(PALETTE[name], dtype=np.float64) / 255.0
    c = stable_rng("color", name).uniform(0.15, 0.85, size=3)
    return c


def luminance(c: np.ndarray) -> float:
    return float(0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2])


def accent(c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """The pattern colour: colour2 when it differs from colour1, else a darker or lighter colour1."""
    if np.abs(c1 - c2).max() > 1e-6:
        return c2
    return c1 * 0.42 if luminance(c1) > 0.5 else c1 * 0.35 + 0.6


def _across(u: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Position across the mask in each row, -1 (left edge) .. 1 (right edge); 0 outside."""
    big = np.where(mask, u, np.inf).min(axis=1, keepdims=True)
    small = np.where(mask, u, -np.inf).max(axis=1, keepdims=True)
    ok = np.isfinite(big) & np.isfinite(small) & (small > big)
    lo, hi = np.where(ok, big, 0.0), np.where(ok, small, 1.0)
    return np.clip(np.where(mask, 2 * (u - lo) / np.maximum(hi - lo, 1e-9) - 1, 0.0), -1, 1)


def _noise1d(rng: np.random.Generator, t: np.ndarray, n: int = 9) -> np.ndarray:
    knots = rng.normal(size=n)
    return np.interp((t + 0.5) * (n - 1), np.arange(n), knots)


def shade(material: str, u, v, mask, aspect: float, round_: bool, rng: np.random.Generator):
    """(shade (H, W), highlight (H, W), alpha (H, W)) of `material` over `mask`.

    `round_` says the part is seen as a disc (plates, cups: radial lighting) rather than a bar
    (cutlery: lighting across its width).
    """
    ones = np.ones_like(u)
    vv = v * aspect
    if round_:
        r = np.hypot(u, vv)
        light = np.clip(0.5 - (u + vv) * 0.7, 0, 1)  # brighter toward the upper left
    else:
        s = _across(u, mask)
        light = np.clip(1 - s * s, 0, 1) ** 0.5  # a bar, rounder in the middle
    if material == "metal":
        if round_:
            theta = np.arctan2(vv, u)
            sheen = np.cos(2 * (theta + np.pi / 4))
            sh = 0.74 + 0.2 * sheen + 0.1 * np.cos(r * 40)
            hi = 0.45 * np.clip(sheen, 0, 1) ** 6 + 0.35 * np.exp(-((u + 0.2) ** 2 + (vv + 0.2) ** 2) / 0.004)
        else:
            sh = 0.5 + 0.5 * light
            hi = 0.8 * np.exp(-((s + 0.35) / 0.2) ** 2) + 0.3 * np.exp(-((s - 0.6) / 0.15) ** 2)
        return sh, hi, ones
    if material == "wood":
        freq, wobble = (7.0, 0.18) if round_ else (3.5, 0.45)
        phase = u * freq + wobble * _noise1d(rng, v, 5) + 0.08 * _noise1d(rng, u, 4)
        g = 0.5 + 0.5 * np.sin(2 * np.pi * phase)
        lines = np.abs(((phase * 2.0) % 1.0) - 0.5) < 0.06
        sh = (0.8 + 0.2 * g) * np.where(lines, 0.78, 1.0) * (0.9 + 0.1 * light)
        return sh, np.zeros_like(u), ones
    if material == "glass":
        if round_:
            d = (u + 0.22) * 0.8 + (vv + 0.22) * 0.6  # a soft diagonal streak toward the upper left
            glint = np.exp(-((u - vv + 0.05) / 0.05) ** 2) * np.exp(-(d / 0.12) ** 2)
        else:
            glint = np.exp(-((s + 0.45) / 0.18) ** 2)
        return 0.9 + 0.1 * light, 0.7 * glint, np.full_like(u, 0.5)
    if material == "ceramic":
        if round_:
            hi = 0.45 * np.exp(-((u + 0.2) ** 2 + (vv + 0.2) ** 2) / 0.0035)
            sh = 0.9 + 0.1 * light
        else:
            hi = 0.5 * np.exp(-((s + 0.3) / 0.2) ** 2)
            sh = 0.8 + 0.2 * light
        return sh, hi, ones
    # plastic and anything unknown: matte, nearly flat
    return 0.92 + 0.08 * light, np.zeros_like(u), ones


def _hex_dots(uu, vv, spacing, radius):
    row = np.round(vv / (spacing * 0.866))
    off = (row % 2) * spacing / 2
    du = uu - off - np.round((uu - off) / spacing) * spacing
    dv = vv - row * spacing * 0.866
    return du**2 + dv**2 <= (radius * spacing) ** 2


def _flowers(uu, vv, centres, petal):
    out = np.zeros_like(uu, dtype=bool)
    for cx, cy in centres:
        for k in range(5):
            a = 2 * np.pi * k / 5 - np.pi / 2
            px, py = cx + petal * np.cos(a), cy + petal * np.sin(a)
            out |= (uu - px) ** 2 + (vv - py) ** 2 <= (petal * 0.78) ** 2
        out &= ~((uu - cx) ** 2 + (vv - cy) ** 2 <= (petal * 0.45) ** 2)
    return out


def shapes_oval(outer_at) -> bool:
    """Whether the outline is narrower than tall (an oval plate): its left edge is inside x = -0.45."""
    m = outer_at(1.0)
    return not m[:, : max(1, m.shape[1] // 20)].any()


def pattern(name: str, type_: str, u, v, aspect: float, outer_at) -> np.ndarray:
    """Boolean (H, W) mask where pattern `name` paints the accent colour.

    `outer_at(scale)` returns the object's outline mask shrunk by `scale` (used by "rimmed").
    """
    uu, vv = u, v * aspect
    none = np.zeros_like(u, dtype=bool)
    cutlery = type_ in ("fork", "knife", "spoon")
    if cutlery:  # on the handle only: bands, dots, checks or a flower in width units
        on = (v > 0.08)
        if name == "striped":
            return on & (((vv * 2.2) % 1.0) < 0.42)
        if name == "dotted":
            return on & _hex_dots(uu, vv, 0.42, 0.3)
        if name == "checkered":
            return on & (((np.floor(uu * 4) + np.floor(vv * 4)) % 2) == 0)
        if name == "floral":
            return _flowers(uu, vv, [(0.0, 0.33 * aspect)], 0.16)
        if name == "rimmed":
            return ((v > 0.1) & (v < 0.14)) | ((v > 0.36) & (v < 0.4))
        return none
    n = 8.0 if type_ == "plate" else 6.0
    if name == "striped":
        return ((vv * n) % 1.0) < 0.4
    if name == "dotted":
        return _hex_dots(uu, vv, 1.0 / n, 0.27)
    if name == "checkered":
        return ((np.floor(uu * n) + np.floor(vv * n)) % 2) == 0
    if name == "floral":
        if type_ == "cup":
            cy = 0.12 * aspect
            centres = [(0.0, cy)] + [(0.2 * np.cos(a), cy + 0.2 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 7)[:-1]]
            return _flowers(uu, vv, centres, 0.045)
        ring = np.linspace(0, 2 * np.pi, 9)[:-1]
        rx = 0.31 if shapes_oval(outer_at) else 0.41
        centres = [(0.0, 0.0)] + [(rx * np.cos(a), 0.41 * np.sin(a)) for a in ring]
        return _flowers(uu, vv, centres, 0.032)
    if name == "rimmed":
        return outer_at(0.97) & ~outer_at(0.84)
    return none
