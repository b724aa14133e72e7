"""Sprites: physical scale, two colours, visibly different materials, orientation, caching."""

from __future__ import annotations

import numpy as np

from degusta_learn.render.sprites import pixel_size, sprite
from degusta_learn.scene import CatalogObject, default_catalog

CAT = default_catalog()
UNIT = 448


def _obj(type_, c1, c2, m1, m2, shape="round", pattern="solid"):
    return CatalogObject(999, type_, c1, c2, m1, m2, shape=shape, pattern=pattern)


def test_physical_scale():
    first = {t: CAT.of_type(t)[0] for t in ("plate", "cup", "knife", "spoon", "fork")}
    size = {t: pixel_size(o, UNIT) for t, o in first.items()}
    assert size["plate"][0] > size["cup"][0] * 2 and size["knife"][1] > size["spoon"][1] > size["spoon"][0]
    im = sprite(first["plate"], UNIT)
    assert im.size == size["plate"] and im.mode == "RGBA"


def test_two_colour_fork_handle_and_tines():
    fork = _obj("fork", "red", "blue", "plastic", "plastic", shape="straight")
    a = np.asarray(sprite(fork, 1000)).astype(int)  # (length, width, 4), tines at the top (north)
    h = a.shape[0]

    def dominant(rows):
        px = a[rows][a[rows][..., 3] > 250][:, :3]
        return px.mean(axis=0)

    top, bottom = dominant(slice(int(h * 0.05), int(h * 0.2))), dominant(slice(int(h * 0.75), int(h * 0.95)))
    assert top[2] > top[0] + 60  # blue tines (colour2) ...
    assert bottom[0] > bottom[2] + 60  # ... on a red handle (colour1)
    # tines: at a row near the top, opaque runs separated by gaps
    row = a[int(h * 0.08), :, 3] > 128
    assert np.count_nonzero(np.diff(row.astype(int)) == 1) >= 3


def test_materials_look_different():
    def stats(material):
        a = np.asarray(sprite(_obj("plate", "gray", "gray", material, material), UNIT)).astype(float)
        inside = a[20:56, 20:56]
        return inside[..., 3].mean(), inside[..., :3].mean(axis=2).std()

    glass_alpha, _ = stats("glass")
    plastic_alpha, plastic_std = stats("plastic")
    _, metal_std = stats("metal")
    _, wood_std = stats("wood")
    assert glass_alpha < 180 and plastic_alpha > 250  # glass is translucent
    assert metal_std > 2 * plastic_std and wood_std > 2 * plastic_std  # sheen and grain vs matte


def test_patterns_are_visible_on_plates():
    solid = np.asarray(sprite(_obj("plate", "white", "white", "ceramic", "ceramic"), UNIT)).astype(float)
    for pattern in ("striped", "dotted", "checkered", "floral", "rimmed"):
        pat = np.asarray(sprite(_obj("plate", "white", "white", "ceramic", "ceramic", pattern=pattern), UNIT))
        diff = np.abs(pat.astype(float)[..., :3] - solid[..., :3]).max(axis=2)
        assert (diff > 60).mean() > 0.03, pattern


def test_sprites_are_cached():
    o = CAT[3]
    assert sprite(o, UNIT) is sprite(o, UNIT) and sprite(o, UNIT) is not sprite(o, UNIT + 20)
