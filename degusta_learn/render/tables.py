"""Empty-table images: a textured surface in the shape of the table's polygon on a floor (cached).

The look follows `Table.name`: "oak" (light planks), "walnut" (dark planks), "marble" (white with grey
veins), "white" (a white cloth), "slate" (dark grey stone). Any other name gets a look hashed from the
name (one of those textures in a hashed colour), so distinct names give distinct tables. Outside the
surface polygon is a grey-blue concrete floor; the table casts a soft shadow on it and has a darker
edge. A table with `image` is that picture (relative to the dataset root), resized to the image size.

Example:
    from degusta_learn.scene import default_tables
    from degusta_learn.render.tables import table_image
    table_image(default_tables()[1], 448, 448).save("/tmp/marble.png")
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFilter

from degusta_learn.render.materials import stable_rng
from degusta_learn.render.sprites import open_picture, picture_path
from degusta_learn.scene import Table

LOOKS = {  # name -> (texture, base colour)
    "oak": ("planks", (201, 156, 100)),
    "walnut": ("planks", (110, 68, 42)),
    "marble": ("marble", (236, 234, 230)),
    "white": ("cloth", (248, 248, 246)),
    "slate": ("stone", (74, 80, 88)),
}
FLOOR = (152, 160, 166)


def look(table: Table) -> tuple[str, tuple[int, int, int]]:
    """(texture, base RGB) of a table: named looks, else hashed from the name (or the id)."""
    if table.name in LOOKS:
        return LOOKS[table.name]
    rng = stable_rng("table-look", table.name or f"table-{table.id}")
    texture = ("planks", "marble", "cloth", "stone")[int(rng.integers(4))]
    base = tuple(int(c) for c in rng.integers(60, 240, size=3))
    return texture, base


def _noise(rng: np.random.Generator, w: int, h: int, cells: tuple[int, int]) -> np.ndarray:
    """Smooth value noise (h, w) in about [-1, 1]: a coarse random grid upsampled bicubically."""
    coarse = rng.uniform(-1, 1, size=(cells[1], cells[0])).astype(np.float32)
    return np.asarray(Image.fromarray(coarse, "F").resize((w, h), Image.Resampling.BICUBIC))


def _texture(kind: str, base, w: int, h: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) float RGB in [0, 1] of a surface texture."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    x, y = x / max(w, h), y / max(w, h)
    base = np.asarray(base, np.float32) / 255
    if kind == "planks":
        n_planks = 7
        plank = np.floor(y * n_planks)
        tone = 0.9 + 0.2 * stable_rng("planks", int(rng.integers(1 << 30))).uniform(size=n_planks + 1)[plank.astype(int)]
        warp = _noise(rng, w, h, (6, 24)) * 0.6 + plank * 1.7
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (y * 70 + warp))
        seam = np.abs((y * n_planks) % 1.0 - 0.5) > 0.494
        shade = tone * (0.88 + 0.12 * grain) * np.where(seam, 0.7, 1.0)
        return np.clip(base * shade[..., None], 0, 1)
    if kind == "marble":
        turb = _noise(rng, w, h, (4, 4)) * 1.0 + _noise(rng, w, h, (11, 11)) * 0.25
        veins = np.abs(np.sin((x * 1.6 + y * 1.1) * np.pi * 2 + turb * 2.2))
        fine = np.abs(np.sin((x * 0.7 - y * 1.9) * np.pi * 2 + turb * 3.0))
        shade = 1 - 0.17 * np.exp(-veins / 0.06) - 0.08 * np.exp(-fine / 0.03) - 0.012 * _noise(rng, w, h, (23, 23))
        tint = np.array([0.92, 0.93, 0.96], np.float32)
        return np.clip(base * (shade[..., None] * tint + (1 - tint) * shade[..., None] ** 8), 0, 1)
    if kind == "cloth":
        ix, iy = np.mgrid[0:h, 0:w][::-1]
        weave = ((ix // 2 + iy // 2) % 2).astype(np.float32)
        shade = 0.97 + 0.015 * weave + 0.015 * _noise(rng, w, h, (7, 7))
        return np.clip(base * shade[..., None], 0, 1)
    # stone
    shade = 1 + 0.07 * _noise(rng, w, h, (9, 9)) + 0.05 * rng.uniform(-1, 1, size=(h, w)).astype(np.float32)
    return np.clip(base * shade[..., None], 0, 1)


def _min_filter(a: np.ndarray, k: int) -> np.ndarray:
    """The minimum over each pixel's k x k square (edges replicated): Pillow's `MinFilter(k)`, byte for byte.

    Pillow's rank filter costs k^2 per pixel, and k grows with the image (the rim band is w / 110 px), so a table
    cost size^4: 0.7 s at 896 px, minutes at 4096. The square minimum is separable; scipy's 1-D passes cost
    O(1) per pixel whatever k (benchmarks/RESULTS.md, "Render cost by image size").
    """
    from scipy.ndimage import minimum_filter

    return minimum_filter(a, size=k, mode="nearest")


def surface_mask(table: Table, w: int, h: int) -> Image.Image:
    """The antialiased surface polygon as an "L" image (255 inside)."""
    ss = 4
    big = Image.new("L", (w * ss, h * ss), 0)
    ImageDraw.Draw(big).polygon([(px * w * ss, py * h * ss) for px, py in table.surface], fill=255)
    return big.resize((w, h), Image.Resampling.BOX)


def table_image(table: Table, w: int, h: int, root: str | Path | None = None) -> Image.Image:
    """The cached RGB image of the empty `table` at w x h pixels (do not modify it in place)."""
    return _table_image(table, w, h, str(root) if root is not None else None)


@functools.lru_cache(maxsize=64)
def _table_image(table: Table, w: int, h: int, root: str | None) -> Image.Image:
    if table.image:
        if root is None:
            from degusta_learn.errors import DegustaError

            raise DegustaError(f"table {table.id}: image {table.image!r} is relative to a dataset folder, but "
                               "the renderer has no root (use Renderer.for_dataset or pass root=)")
        pic = open_picture(picture_path(root, table.image, f"image of table {table.id}"), f"image of table {table.id}")
        return pic.convert("RGB").resize((w, h), Image.Resampling.LANCZOS)
    rng = stable_rng("table", table.id, table.name, w, h)
    kind, base = look(table)
    floor = np.asarray(FLOOR, np.float32) / 255 * (1 + 0.025 * _noise(rng, w, h, (23, 23)))[..., None]
    mask_img = surface_mask(table, w, h)
    mask = np.asarray(mask_img, np.float32)[..., None] / 255
    off = max(2, w // 90)
    shadow = np.asarray(mask_img.filter(ImageFilter.GaussianBlur(off * 1.5)), np.float32)[..., None] / 255
    shadow = np.roll(shadow, (off, off), axis=(0, 1))
    floor = floor * (1 - 0.45 * shadow)
    edge_w = max(2, w // 110)
    inner = _min_filter(np.asarray(mask_img), 2 * edge_w + 1).astype(np.float32)[..., None] / 255
    surface = _texture(kind, base, w, h, rng)
    surface = surface * (0.72 + 0.28 * inner)  # darker rim band: the table's edge
    out = floor * (1 - mask) + surface * mask
    return Image.fromarray(np.round(np.clip(out, 0, 1) * 255).astype(np.uint8), "RGB")
