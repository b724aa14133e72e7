"""The lifting functions: arrangements and objects as images (UmA, GMA, GoMO) or text (OaL, order).

- UmA (unmarked arrangement): the table image with each object's sprite pasted at its centroid,
  rotated clockwise by its rotation. The image frame is the table frame: normalized (x, y) is
  (x * width, y * height) in pixels. `table(id)` is the empty table (the initial state).
- GMA (grid-marked arrangement): the same scene drawn `size - 2 * margin` pixels wide inside a white
  margin (5% of `size`) that carries the labels: column letters along the top and bottom, row numbers
  along the left and right, outside the table so they never cover an object. Grid lines are drawn over
  the objects, semi-transparent, dark with a light companion line so they show on light and dark
  tables. `table(id, grid)` is the empty table with the grid.
- GoMO (grid of marked objects): one `size` x `size` sheet per object type, titled with the type; its
  objects (any number: ceil(sqrt(n)) columns) each with a white rounded box holding the object id in
  black at the object's top-left corner. `catalog_sheet()` tiles the GoMO sheets of every type. A sheet
  carries what it shows in `image.info[compose.GOMO_SOURCE]` (type, objects, root), from which
  `render.compose.objects_canvas` redraws several sheets as one legible composed canvas.
- OaL (objects as language): `oal_text`, the catalog as JSON text, one object a line.
- Order: `order_text`, one line listing the placement order of an arrangement's object types.

The four zero-shot methods combine one object lifting and one arrangement lifting (`METHODS`).
Rendering is deterministic (same inputs -> byte-identical images); sprites and empty tables are cached
per pixel size, GMA backgrounds and GoMO sheets per renderer.

Example:
    from degusta_learn.render.lifting import Renderer
    r = Renderer.for_dataset(ds, size=448)
    arr = ds.arrangements[0]
    r.gma(arr.table, arr.placements, Grid(8, 8)).save("gma.png"); r.gomo("fork").save("forks.png")
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

from PIL import Image, ImageDraw

from degusta_learn.errors import DegustaError
from degusta_learn.render import text
from degusta_learn.render.compose import GOMO_SOURCE
from degusta_learn.render.grid import Grid, as_grid
from degusta_learn.render.sprites import pixel_size, rotated_sprite, sprite
from degusta_learn.render.tables import table_image
from degusta_learn.scene import Arrangement, Catalog, Dataset, Placement, Table, object_size

METHODS = {"louma": ("oal", "uma"), "logma": ("oal", "gma"), "mouma": ("gomo", "uma"), "mogma": ("gomo", "gma")}
LIFTINGS = ("oal", "gomo", "uma", "gma")
GMA_MARGIN = 0.05  # label margin of GMA images, as a fraction of `size`
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 64, 4096
"""Image sizes a Renderer draws (pixels, longer side): 4096 px is 48 MB of RGB; larger is refused, not drawn."""
MAX_SHEET_PIXELS = 2**27
"""Most pixels of a catalog contact sheet (about 400 MB of RGB): many types at a large size are refused."""
SHEET_BG, TILE_BG, TILE_EDGE = (232, 229, 222), (246, 244, 240), (206, 202, 194)
PIL_BLOCKS = 64  # image memory blocks Pillow keeps for reuse (see _reuse_image_memory)


def _reuse_image_memory() -> None:
    """Let Pillow keep freed image memory for reuse (unless PILLOW_BLOCKS_MAX says otherwise).

    By default Pillow returns every freed image buffer to the OS, so each new 448 px image page-faults
    its memory in again; keeping up to PIL_BLOCKS blocks (~40 MB at most for 448 px images) halves the
    time of a warm image set. This is Pillow's documented block-allocator setting.
    """
    if "PILLOW_BLOCKS_MAX" not in os.environ and Image.core.get_blocks_max() < PIL_BLOCKS:
        Image.core.set_blocks_max(PIL_BLOCKS)


def method_liftings(method: str) -> tuple[str, str]:
    """(object lifting, arrangement lifting) of a zero-shot method; DegustaError if unknown."""
    if method not in METHODS:
        raise DegustaError(f"unknown method {method!r} (expected one of {', '.join(METHODS)})")
    return METHODS[method]


def gomo_layout(n: int) -> tuple[int, int]:
    """(columns, rows) of a GoMO sheet of n objects: ceil(sqrt(n)) columns, as many rows as needed."""
    cols = max(1, math.ceil(math.sqrt(n)))
    return cols, max(1, math.ceil(n / cols))


class Renderer:
    """Draws the lifted images of one catalog and table set at `size` pixels (longer image side)."""

    def __init__(self, catalog: Catalog, tables: dict[int, Table], root: Path | str | None = None, size: int = 448):
        if isinstance(size, bool) or not isinstance(size, int) or not MIN_IMAGE_SIZE <= size <= MAX_IMAGE_SIZE:
            shown = f"an integer of {len(str(abs(size)))} digits" if isinstance(size, int) and abs(size) > 10**12 \
                else " ".join(repr(size).split())[:60]
            raise DegustaError(f"size (image_size): expected an image size from {MIN_IMAGE_SIZE} to "
                               f"{MAX_IMAGE_SIZE:,} pixels, got {shown}")
        self.catalog, self.tables, self.size = catalog, dict(tables), size
        self.root = str(root) if root is not None else None
        self.margin = max(8, round(size * GMA_MARGIN))
        self._gma_cache: dict = {}
        self._gomo_cache: dict[str, Image.Image] = {}
        _reuse_image_memory()

    @classmethod
    def for_dataset(cls, ds: Dataset, size: int = 448) -> Renderer:
        return cls(ds.catalog, ds.tables, ds.root, size)

    # -- arrangements -------------------------------------------------------------------------------
    def _table(self, table_id: int) -> Table:
        if table_id not in self.tables:
            raise DegustaError(f"unknown table id {table_id!r} (tables: {sorted(self.tables)})")
        return self.tables[table_id]

    @staticmethod
    def _fit(table: Table, box: int) -> tuple[int, int]:
        scale = box / max(table.width, table.height)
        return max(1, round(table.width * scale)), max(1, round(table.height * scale))

    def _paste_objects(self, canvas: Image.Image, table: Table, placements: Sequence[Placement],
                       box: tuple[int, int, int, int], strict: bool) -> None:
        """Paste the placements' sprites onto `canvas`, the table image occupying `box`, clipped to it."""
        x0, y0, x1, y1 = box
        w, h = x1 - x0, y1 - y0
        unit = math.sqrt(w * h)  # pixels per normalized unit (= w for square tables)
        for p in placements:
            if p.object not in self.catalog:
                raise DegustaError(f"placement of object {p.object}: not in the catalog")
            obj = self.catalog[p.object]
            if strict and not _inside(table.surface, p.x, p.y):
                raise DegustaError(f"object {p.object} ({obj.type}) at ({p.x:.3f}, {p.y:.3f}) is outside the "
                                   f"surface of table {table.id} ({table.name or 'unnamed'})")
            sp = rotated_sprite(obj, unit, p.rotation, self.root)
            left, top = x0 + round(p.x * w - sp.width / 2), y0 + round(p.y * h - sp.height / 2)
            if left < x0 or top < y0 or left + sp.width > x1 or top + sp.height > y1:  # clip to the table
                cl, ct = max(left, x0), max(top, y0)
                cr, cb = min(left + sp.width, x1), min(top + sp.height, y1)
                if cr <= cl or cb <= ct:
                    continue
                sp = sp.crop((cl - left, ct - top, cr - left, cb - top))
                left, top = cl, ct
            canvas.paste(sp, (left, top), sp)

    def uma(self, table_id: int, placements: Sequence[Placement], *, strict: bool = True) -> Image.Image:
        """Unmarked arrangement. `strict=False` draws objects off the surface instead of raising."""
        table = self._table(table_id)
        w, h = self._fit(table, self.size)
        canvas = table_image(table, w, h, self.root).copy()
        self._paste_objects(canvas, table, placements, (0, 0, w, h), strict)
        return canvas

    def gma(self, table_id: int, placements: Sequence[Placement], grid: Grid | int, *, strict: bool = True) -> Image.Image:
        """Grid-marked arrangement (labels in the margin, grid lines over the objects)."""
        table, grid = self._table(table_id), self._need_grid(grid)
        background, lines = self._gma_parts(table, grid)
        out = background.copy()
        m = self.margin
        self._paste_objects(out, table, placements, (m, m, out.width - m, out.height - m), strict)
        _draw_lines(out, lines)
        return out

    def arrangement(self, lifting: str, table_id: int, placements: Sequence[Placement], grid: Grid | int | None = None) -> Image.Image:
        """Dispatch by lifting name: "uma" or "gma"."""
        if lifting == "uma":
            return self.uma(table_id, placements)
        if lifting == "gma":
            return self.gma(table_id, placements, grid)
        raise DegustaError(f"unknown arrangement lifting {lifting!r} (expected uma or gma)")

    def table(self, table_id: int, grid: Grid | int | None = None) -> Image.Image:
        """The empty table (the initial state), with the grid when `grid` is given."""
        table = self._table(table_id)
        if grid is None:
            return table_image(table, *self._fit(table, self.size), self.root).copy()
        grid = self._need_grid(grid)
        key = ("empty", table.id, grid)
        if key not in self._gma_cache:
            background, lines = self._gma_parts(table, grid)
            out = background.copy()
            _draw_lines(out, lines)
            self._gma_cache[key] = out
        return self._gma_cache[key].copy()

    @staticmethod
    def _need_grid(grid) -> Grid:
        grid = as_grid(grid)
        if grid is None:
            raise DegustaError("a grid-marked image needs a grid (e.g. Grid(8, 8))")
        return grid

    def _gma_parts(self, table: Table, grid: Grid) -> tuple[Image.Image, list]:
        """(margin canvas with labels and the empty table, grid lines as (box, RGBA fill)), cached."""
        key = ("parts", table.id, grid)
        if key in self._gma_cache:
            return self._gma_cache[key]
        m = self.margin
        w, h = self._fit(table, self.size - 2 * m)
        canvas = Image.new("RGB", (w + 2 * m, h + 2 * m), (252, 252, 250))
        canvas.paste(table_image(table, w, h, self.root), (m, m))
        draw = ImageDraw.Draw(canvas)
        cw, ch = w / grid.cols, h / grid.rows
        fs = max(8, min(round(m * 0.68), round(min(cw, ch) * 0.75)))
        for c in range(grid.cols):
            x = m + (c + 0.5) * cw
            for y in (m / 2, h + 1.5 * m):
                text.draw_centered(draw, (x, y), chr(ord("A") + c), fs)
        for r in range(grid.rows):
            y = m + (r + 0.5) * ch
            for x in (m / 2, w + 1.5 * m):
                text.draw_centered(draw, (x, y), str(r + 1), fs if r < 9 else max(8, round(fs * 0.85)))
        # each line: a dark stripe with a light companion stripe (visible on light and dark tables),
        # semi-transparent; stored as (box, RGBA fill) rectangles blended over the objects
        lw = max(1, round(self.size / 448))
        overlay = []
        for c in range(grid.cols + 1):
            x = m + min(round(c * cw), w - lw)
            overlay.append(((x, m, x + lw - 1, m + h - 1), (0, 0, 0, 120)))
            if 0 < c < grid.cols:
                overlay.append(((x + lw, m, x + 2 * lw - 1, m + h - 1), (255, 255, 255, 100)))
        for r in range(grid.rows + 1):
            y = m + min(round(r * ch), h - lw)
            overlay.append(((m, y, m + w - 1, y + lw - 1), (0, 0, 0, 120)))
            if 0 < r < grid.rows:
                overlay.append(((m, y + lw, m + w - 1, y + 2 * lw - 1), (255, 255, 255, 100)))
        self._gma_cache[key] = (canvas, overlay)
        return canvas, overlay

    # -- objects -------------------------------------------------------------------------------------
    def gomo(self, type_: str) -> Image.Image:
        """The grid-of-marked-objects sheet of one object type."""
        if type_ not in self._gomo_cache:
            objs = self.catalog.of_type(type_)
            if not objs:
                raise DegustaError(f"object type {type_!r} has no objects in the catalog "
                                   f"(types: {', '.join(self.catalog.types)})")
            self._gomo_cache[type_] = self.gomo_sheet(type_, objs)
        return self._gomo_cache[type_].copy()

    def gomo_sheet(self, type_: str, objs: Sequence) -> Image.Image:
        """A GoMO sheet of the given objects of one type, in the given order (`gomo` draws all of them).

        Perception pretraining draws random subsets in random order, so a sheet position says nothing
        about an id without looking at the sheet.
        """
        s = self.size
        title_h, pad = round(s * 0.09), round(s * 0.02)
        n = len(objs)
        cols, rows = gomo_layout(n)
        cell = min((s - 2 * pad) / cols, (s - title_h - pad) / rows)
        x0 = (s - cell * cols) / 2
        im = Image.new("RGB", (s, s), SHEET_BG)
        draw = ImageDraw.Draw(im)
        title, fs = f"{type_} ({n} objects, marked with their ids)", max(10, round(s * 0.042))
        while fs > 8 and text.text_size(title, fs)[0] > s - 2 * pad:  # long type names: smaller font
            fs -= 1
        text.draw_centered(draw, (s / 2, title_h / 2 + pad / 2), title, fs)
        mark_fs = max(10, min(round(cell * 0.2), round(s * 0.042)))
        for i, obj in enumerate(objs):
            r, c = divmod(i, cols)
            cx0, cy0 = x0 + c * cell, title_h + r * cell
            gap = max(1, round(cell * 0.03))
            draw.rounded_rectangle((round(cx0 + gap), round(cy0 + gap), round(cx0 + cell - gap), round(cy0 + cell - gap)),
                                   radius=round(cell * 0.08), fill=TILE_BG, outline=TILE_EDGE)
            # the mark sits at the object's top-left: just left of slim objects (clear of a knife's tip),
            # on the empty bounding-box corner of round ones (overlap 15% of the width); pair centred
            mw, mh = text.mark_size(str(obj.id), mark_fs)
            width, length = object_size(obj)
            overlap = 0.15 if width > 0.5 * length else 0.0
            unit = min(cell * 0.8 / length, (cell - mw - 4 * gap) / ((1 - overlap) * width))
            w_px, l_px = pixel_size(obj, unit)
            sp = sprite(obj, unit, self.root, shadow=True)
            shift = overlap * w_px - (0 if overlap else 2)  # how far the mark reaches into the object's box
            ox = cx0 + (cell - (mw + w_px - shift)) / 2 + mw - shift
            oy = cy0 + (cell - l_px) / 2 + cell * 0.03
            im.paste(sp, (round(ox + w_px / 2 - sp.width / 2), round(oy + l_px / 2 - sp.height / 2)), sp)
            mx = max(cx0 + gap + 1, ox + shift - mw)
            my = max(cy0 + gap + 1, oy - (mh * 0.25 if overlap else 0))
            text.draw_mark(draw, (mx, my), str(obj.id), mark_fs)
        im.info[GOMO_SOURCE] = (type_, tuple(objs), self.root)  # what it shows: composed canvases redraw it
        return im

    def catalog_sheet(self) -> Image.Image:
        """Every type's GoMO sheet tiled in ceil(sqrt(n_types)) columns: a contact sheet of the catalog."""
        types = self.catalog.types
        cols = math.ceil(math.sqrt(len(types)))
        rows = math.ceil(len(types) / cols)
        gap = max(2, self.size // 100)
        width, height = cols * self.size + (cols - 1) * gap, rows * self.size + (rows - 1) * gap
        if width * height > MAX_SHEET_PIXELS:
            fit = max(s for s in range(MIN_IMAGE_SIZE - 1, self.size)
                      if s < MIN_IMAGE_SIZE or (cols * s + (cols - 1) * max(2, s // 100))
                      * (rows * s + (rows - 1) * max(2, s // 100)) <= MAX_SHEET_PIXELS)
            hint = f"use a size of at most {fit}" if fit >= MIN_IMAGE_SIZE else "the catalog has too many types"
            raise DegustaError(f"size: a contact sheet of {len(types)} types at {self.size} px would be "
                               f"{width:,} x {height:,} pixels (at most {MAX_SHEET_PIXELS:,}); {hint}")
        sheet = Image.new("RGB", (cols * self.size + (cols - 1) * gap, rows * self.size + (rows - 1) * gap), (90, 90, 90))
        for i, type_ in enumerate(types):
            r, c = divmod(i, cols)
            sheet.paste(self.gomo(type_), (c * (self.size + gap), r * (self.size + gap)))
        return sheet


def _draw_lines(canvas: Image.Image, lines: list) -> None:
    """Blend the grid lines (semi-transparent rectangles) into the RGB `canvas` in place."""
    draw = ImageDraw.Draw(canvas, "RGBA")  # "RGBA" on an RGB image: fills are alpha-blended
    for box, fill in lines:
        draw.rectangle(box, fill=fill)


def _inside(polygon, x: float, y: float) -> bool:
    """Even-odd point-in-polygon test (Table.contains for one point, without numpy overhead)."""
    inside = False
    n = len(polygon)
    for i in range(n):
        (xa, ya), (xb, yb) = polygon[i], polygon[(i + 1) % n]
        if (ya > y) != (yb > y) and x < xa + (y - ya) * (xb - xa) / (yb - ya):
            inside = not inside
    return inside


def oal_text(catalog: Catalog) -> str:
    """Objects as language: the catalog as a JSON list, one object per line (no image paths)."""
    return "[\n" + ",\n".join(json.dumps(o.to_json(with_image=False)) for o in catalog) + "\n]"


def order_text(arrangement: Arrangement, catalog: Catalog, image_name: str) -> str:
    """One line: the order in which the object types of `arrangement` were placed."""
    types = []
    for p in arrangement.placements:
        if p.object not in catalog:
            raise DegustaError(f"placement of object {p.object}: not in the catalog")
        types.append(catalog[p.object].type)
    return f"Placement order in {image_name}: {', '.join(types)}."
