"""Composed canvases: several prompt images drawn as ONE image, for a small VLM's image-token budget.

- `objects_canvas`: the objects of several GoMO sheets REDRAWN on one canvas at its own scale, not the
  sheets shrunk: one band of rows per object type (alternating band colours, types in sheet order), each
  object in its own cell with its id mark at the cell's top-left and the object below it. The layout
  (columns) is chosen for the largest cells, and the cells are stretched to fill the canvas, so the
  only blank is the unused cells at the end of a band. The id mark is as large as the cell's width
  allows (the longest id must fit). The default catalog (5 types x 25 objects) on a 448 px canvas: 13 x 10
  cells of 34.5 x 44.8 px, id digits 8 px tall (9-11 px in SmolVLM's 512 px input), 2.6% blank; five
  GoMO sheets shrunk into one 448 px canvas (the former layout) gave ids ~4 px tall with 40% blank.
- `tile_canvas`: any named images tiled in a near-square grid, each titled with its name (the generic
  composition of the "context" and "all" groups).

Why redraw rather than shrink: a GoMO sheet spends 9% on its title and draws ids at ~20% of a cell;
shrinking five sheets into one keeps those proportions at a third of the size. Why not tile the canvas
to the processor's image splitting: each tile costs as many image tokens as one separate sheet, so that
is the five-separate-sheets option again (docs/finetune.md, "Composed object sheet").

A GoMO sheet drawn by `Renderer.gomo_sheet` carries what it shows in `image.info[GOMO_SOURCE]` (type,
objects, dataset root), so the objects can be redrawn from the prompt's images alone: training
(`finetune/data.py`), perception pretraining and the hf backend compose identical canvases.

Example:
    r = Renderer.for_dataset(ds, size=448)
    canvas = objects_canvas([sheet_source(r.gomo(t)) for t in ds.catalog.types], size=448)
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

from PIL import Image, ImageDraw

from degusta_learn.render import text
from degusta_learn.render.sprites import sprite
from degusta_learn.scene import object_size

GOMO_SOURCE = "degusta_gomo"
"""Key of a GoMO sheet's `Image.info` entry: (type, objects, root) of what the sheet shows."""
CANVAS_BG = (255, 255, 255)  # unused cells
BAND_BG = ((232, 229, 222), (214, 222, 232))  # alternating type bands (warm / cool grey)
TILE_BG, TILE_EDGE = (246, 244, 240), (190, 186, 178)
MARK_SHARE = 0.42  # the id mark takes at most this share of a cell's height; the object the rest


def sheet_source(image: Image.Image) -> tuple | None:
    """(type, objects, root) of a GoMO sheet drawn by `Renderer.gomo_sheet`; None for any other image."""
    source = image.info.get(GOMO_SOURCE)
    return tuple(source) if source is not None else None


@dataclass(frozen=True)
class ObjectsLayout:
    """Where `objects_canvas` draws: `cols` x `rows` cells of `cell_w` x `cell_h` px, id marks at font `font`."""

    cols: int
    rows: int
    cell_w: float
    cell_h: float
    font: int
    gap: int

    def cell(self, row: int, col: int) -> tuple[float, float]:
        """Top-left corner of a cell."""
        return col * self.cell_w, row * self.cell_h


def objects_layout(counts: Sequence[int], longest_id: str, size: int) -> ObjectsLayout:
    """The layout of `objects_canvas` for bands of `counts` objects on a `size` px canvas."""
    best = None
    for cols in range(1, max(counts) + 1):
        rows = sum(math.ceil(n / cols) for n in counts)
        side = min(size / cols, size / rows)
        blank = cols * rows - sum(counts)
        if best is None or (side, -blank) > best[0]:
            best = ((side, -blank), cols, rows)
    _, cols, rows = best
    cw, ch = size / cols, size / rows
    gap = max(1, round(min(cw, ch) * 0.04))
    fs = 6
    while fs < 64:
        w, h = text.mark_size(longest_id, fs + 1)
        if w > cw - 2 * gap - 2 or h > MARK_SHARE * ch:
            break
        fs += 1
    return ObjectsLayout(cols, rows, cw, ch, fs, gap)


def objects_canvas(sheets: Sequence[tuple], size: int) -> Image.Image:
    """Every object of `sheets` ((type, objects, root) each, see `sheet_source`) on one `size` px canvas."""
    key = tuple((t, tuple(objs), None if root is None else str(root)) for t, objs, root in sheets)
    return _objects_canvas(key, int(size)).copy()


@functools.lru_cache(maxsize=8)
def _objects_canvas(sheets: tuple, size: int) -> Image.Image:
    counts = [len(objs) for _, objs, _ in sheets]
    longest = max((str(o.id) for _, objs, _ in sheets for o in objs), key=lambda s: text.text_size(s, 20)[0])
    lay = objects_layout(counts, longest, size)
    im = Image.new("RGB", (size, size), CANVAS_BG)
    draw = ImageDraw.Draw(im)
    row = 0
    for band, (_, objs, root) in enumerate(sheets):
        band_rows = math.ceil(len(objs) / lay.cols)
        used = min(len(objs), lay.cols)
        draw.rectangle((0, round(row * lay.cell_h), round(used * lay.cell_w) - 1,
                        round((row + band_rows) * lay.cell_h) - 1), fill=BAND_BG[band % 2])
        for i, obj in enumerate(objs):
            r, c = divmod(i, lay.cols)
            _draw_object(im, draw, obj, root, *lay.cell(row + r, c), lay)
        row += band_rows
        if len(objs) % lay.cols:  # the unused cells at the end of the band stay blank
            x, y = lay.cell(row - 1, len(objs) % lay.cols)
            draw.rectangle((round(x), round(y), size - 1, round(y + lay.cell_h) - 1), fill=CANVAS_BG)
    return im


def _draw_object(im, draw, obj, root, x0: float, y0: float, lay: ObjectsLayout) -> None:
    """One cell: a rounded tile, the id mark at its top-left, the object centred below the mark."""
    g = lay.gap
    draw.rounded_rectangle((round(x0 + g), round(y0 + g), round(x0 + lay.cell_w - g) - 1,
                            round(y0 + lay.cell_h - g) - 1), radius=max(2, round(lay.cell_w * 0.08)),
                           fill=TILE_BG, outline=TILE_EDGE)
    box = text.draw_mark(draw, (x0 + g + 1, y0 + g + 1), str(obj.id), lay.font)
    top = box[3] + 1
    room_w, room_h = lay.cell_w - 2 * g - 2, y0 + lay.cell_h - g - 1 - top
    width, length = object_size(obj)
    unit = max(1.0, min(room_w * 0.92 / width, room_h * 0.92 / length))
    sp = sprite(obj, unit, root, shadow=True)
    cx, cy = x0 + lay.cell_w / 2, top + room_h / 2
    im.paste(sp, (round(cx - sp.width / 2), round(cy - sp.height / 2)), sp)


def tile_canvas(images: Sequence[tuple[str, Image.Image]], size: int) -> Image.Image:
    """Tile named images into one square canvas of `size` px, each tile titled with its name."""
    n = len(images)
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    tile = size // cols
    title = max(10, tile // 10)
    canvas = Image.new("RGB", (size, size), "white")
    draw = ImageDraw.Draw(canvas)
    y0 = (size - rows * tile) // 2
    for k, (name, im) in enumerate(images):
        r, c = divmod(k, cols)
        x, y = c * tile, y0 + r * tile
        body = im.convert("RGB").resize((tile - 2, tile - title - 2), Image.Resampling.LANCZOS)
        canvas.paste(body, (x + 1, y + title + 1))
        draw.rectangle([x, y, x + tile - 1, y + tile - 1], outline=(60, 60, 60))
        draw.text((x + 3, y + 1), name.rsplit(".", 1)[0], fill=(0, 0, 0))
    return canvas
