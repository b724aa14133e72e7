"""Lifting functions: image sizes, colours, determinism, picture entries, odd catalogs, bad inputs."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.render import sprites, tables
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import METHODS, Renderer, gomo_layout, method_liftings, oal_text, order_text
from degusta_learn.scene import (
    Arrangement,
    Catalog,
    CatalogObject,
    Placement,
    Table,
    default_catalog,
    default_tables,
)

SIZE = 128  # small images keep the tests fast; the layout is the same at 448
CAT = default_catalog()
TABLES = {t.id: t for t in default_tables()}


def _png(im: Image.Image) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return buf.getvalue()


RED = CatalogObject(900, "plate", "red", "red", "plastic", "plastic", shape="round", pattern="solid")
BLUE = CatalogObject(901, "plate", "blue", "blue", "ceramic", "ceramic", shape="square", pattern="solid")
MINE = Catalog((*CAT.objects, RED, BLUE))


def test_image_sizes_and_modes():
    r = Renderer(MINE, TABLES, size=SIZE)
    pl = [Placement(RED.id, 0.5, 0.5, 0.0)]
    for im in (r.uma(0, pl), r.gma(0, pl, Grid(8, 8)), r.table(0), r.table(0, 6), r.gomo("cup")):
        assert im.mode == "RGB" and im.size == (SIZE, SIZE)
    assert r.catalog_sheet().size[0] > 2 * SIZE


def test_objects_are_drawn_in_their_colours_at_their_centroid():
    r = Renderer(MINE, TABLES, size=SIZE)
    im = np.asarray(r.uma(2, [Placement(RED.id, 0.3, 0.5, 0), Placement(BLUE.id, 0.7, 0.5, 0)])).astype(int)
    empty = np.asarray(r.table(2)).astype(int)
    (r1, g1, b1), (r2, g2, b2) = im[64, int(0.3 * SIZE)], im[64, int(0.7 * SIZE)]
    assert r1 > g1 + 60 and r1 > b1 + 60  # red plate
    assert b2 > r2 + 60 and b2 > g2 + 30  # blue plate
    assert (im[5, 5] == empty[5, 5]).all()  # far from the objects the table is untouched


def test_gma_has_labels_in_a_margin_and_lines_that_keep_objects_visible():
    r = Renderer(MINE, TABLES, size=448)
    im = np.asarray(r.gma(2, [Placement(RED.id, 0.5625, 0.5625, 0)], Grid(8, 8))).astype(int)
    m = r.margin
    assert (im[:m, :m] > 240).all()  # the margin corner is white: labels live in the margin
    assert (im[:m, m:-m] < 80).any()  # ... and the top margin has dark label ink
    x = m + round(0.5625 * (448 - 2 * m))  # the plate's centre (mid-cell, no line there)
    rr, gg, bb = im[x, x]
    assert rr > gg + 60
    line_x = m + round(0.5 * (448 - 2 * m))  # the grid line through the plate is blended, not opaque
    assert im[x, line_x][0] > 60


def test_deterministic_png_bytes_after_clearing_caches():
    pl = [Placement(o, 0.3 + 0.1 * i, 0.5, 17.0 * i) for i, o in enumerate((3, 30, 55, 80, 105))]
    first = _png(Renderer(CAT, TABLES, size=SIZE).gma(1, pl, Grid(6, 6)))
    for cache in (sprites._sprite, sprites._rotated, tables._table_image):
        cache.cache_clear()
    assert _png(Renderer(CAT, TABLES, size=SIZE).gma(1, pl, Grid(6, 6))) == first


def test_deterministic_across_processes():
    code = ("import hashlib, io; from degusta_learn.scene import default_catalog, default_tables, Placement;"
            "from degusta_learn.render.lifting import Renderer;"
            "r = Renderer(default_catalog(), {t.id: t for t in default_tables()}, size=96);"
            "b = io.BytesIO(); r.uma(3, [Placement(12, 0.4, 0.5, 33.0), Placement(60, 0.6, 0.5, 200.0)]).save(b, 'PNG');"
            "print(hashlib.sha256(b.getvalue()).hexdigest())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    r = Renderer(CAT, TABLES, size=96)
    here = _png(r.uma(3, [Placement(12, 0.4, 0.5, 33.0), Placement(60, 0.6, 0.5, 200.0)]))
    assert out == hashlib.sha256(here).hexdigest()


def test_picture_entries_plug_in(tmp_path):
    Image.new("RGBA", (8, 8), (0, 200, 0, 255)).save(tmp_path / "green.png")
    Image.new("RGB", (16, 16), (255, 0, 255)).save(tmp_path / "magenta.png")
    obj = CatalogObject(0, "plate", "green", "green", "plastic", "plastic", image="green.png")
    table = Table(0, 512, 512, ((0.1, 0.1), (0.9, 0.1), (0.9, 0.9), (0.1, 0.9)), image="magenta.png")
    r = Renderer(Catalog((obj,)), {0: table}, root=tmp_path, size=SIZE)
    im = np.asarray(r.uma(0, [Placement(0, 0.5, 0.5, 0)])).astype(int)
    assert tuple(im[64, 64]) == (0, 200, 0)  # the picture, not a procedural plate
    assert tuple(im[2, 2]) == (255, 0, 255)  # the table picture
    # scaled to the plate's physical size: 0.17 of the image
    green = (im[:, :, 1] == 200) & (im[:, :, 0] == 0)
    assert abs(green[64].sum() - 0.17 * SIZE) <= 2


def test_missing_or_broken_pictures_name_the_file(tmp_path):
    (tmp_path / "notes.png").write_text("not an image")
    for name, match in (("missing.png", "missing.png.*not found"), ("notes.png", "notes.png.*not a readable image")):
        obj = CatalogObject(0, "cup", "red", "red", "plastic", "plastic", image=name)
        r = Renderer(Catalog((obj,)), TABLES, root=tmp_path, size=SIZE)
        with pytest.raises(DegustaError, match=match):
            r.uma(0, [Placement(0, 0.5, 0.5, 0)])
    table = dataclasses.replace(TABLES[0], image="missing.png")
    with pytest.raises(DegustaError, match="missing.png"):
        Renderer(CAT, {0: table}, root=tmp_path, size=SIZE).table(0)


def test_placement_outside_the_table_names_the_object():
    r = Renderer(CAT, TABLES, size=SIZE)
    with pytest.raises(DegustaError, match="object 80 .*outside the surface of table 1"):
        r.gma(1, [Placement(80, 0.03, 0.03, 0)], Grid(8, 8))  # the round marble table's corner
    assert r.uma(1, [Placement(80, 0.03, 0.03, 0)], strict=False).size == (SIZE, SIZE)
    with pytest.raises(DegustaError, match="not in the catalog"):
        r.uma(0, [Placement(999, 0.5, 0.5, 0)])
    with pytest.raises(DegustaError, match="unknown table"):
        r.uma(42, [])


def test_unknown_names_and_grids():
    r = Renderer(CAT, TABLES, size=SIZE)
    for bad in ("lomga", "oal", ""):
        with pytest.raises(DegustaError, match="unknown method"):
            method_liftings(bad)
    assert {method_liftings(m) for m in METHODS} == {("oal", "uma"), ("oal", "gma"), ("gomo", "uma"), ("gomo", "gma")}
    with pytest.raises(DegustaError, match="unknown arrangement lifting"):
        r.arrangement("gomo", 0, [])
    with pytest.raises(DegustaError, match="rows"):
        r.gma(0, [], Grid(0, 8))
    with pytest.raises(DegustaError, match="no objects"):
        r.gomo("teapot")


@pytest.mark.parametrize("n", [1, 7, 40])
def test_gomo_any_catalog_size(n):
    objs = tuple(CatalogObject(i, "fork", "red", "silver", "plastic", "metal", shape="straight") for i in range(n))
    cols, rows = gomo_layout(n)
    assert cols == int(np.ceil(np.sqrt(n))) and cols * rows >= n > cols * (rows - 1)
    im = np.asarray(Renderer(Catalog(objs), TABLES, size=SIZE * 2).gomo("fork")).astype(int)
    red = (im[:, :, 0] > 150) & (im[:, :, 1] < 80) & (im[:, :, 2] < 80)
    assert red.any()
    # every tile holds its object: red pixels in each occupied column of tiles
    xs = np.flatnonzero(red.any(axis=0))
    assert xs.max() - xs.min() > (cols - 1) * (SIZE * 2 * 0.96 / cols) * 0.8


def test_oal_and_order_text():
    data = json.loads(oal_text(CAT))
    assert len(data) == len(CAT) and data[17]["class"] == CAT[17].type and "image" not in data[0]
    arr = Arrangement("p", 0, 0, (Placement(80, 0.5, 0.5), Placement(30, 0.3, 0.5), Placement(3, 0.7, 0.3)))
    line = order_text(arr, CAT, "final_state_1.jpg")
    assert line == "Placement order in final_state_1.jpg: plate, fork, cup." and "\n" not in line
