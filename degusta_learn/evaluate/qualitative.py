"""Qualitative images: ground truth and each method's prediction side by side on the target table.

One PNG per chosen episode (the paper's qualitative figure): the first panel is the held-out ground
truth, then one panel per method, each the unmarked arrangement (UmA) on the target table, titled with
the method and its Kabsch RMSD / object accuracy on that episode.
"""

from __future__ import annotations

import io
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

from degusta_learn.fileio import atomic_write_bytes
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import Dataset, Placement

_TITLE_H = 34


def _panel(renderer: Renderer, table_id: int, placements: list[Placement], title: str, subtitle: str) -> Image.Image:
    table = renderer.tables[table_id]
    inside = [p for p in placements if bool(table.contains(p.x, p.y))]
    dropped = len(placements) - len(inside)
    img = renderer.uma(table_id, inside)
    canvas = Image.new("RGB", (img.width, img.height + _TITLE_H), "white")
    canvas.paste(img, (0, _TITLE_H))
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default()
    draw.text((6, 3), title, fill="black", font=font)
    note = subtitle + (f"  ({dropped} off-table not drawn)" if dropped else "")
    draw.text((6, 18), note, fill=(80, 80, 80), font=font)
    return canvas


def render_side_by_side(ds: Dataset, renderer: Renderer, participant: str, target: int,
                        predictions: dict[str, tuple[list[Placement], str]], path: Path) -> Path:
    """Write one PNG: ground truth, then each method's placements (with a score line) on the same table."""
    gt = ds.arrangement(participant, target)
    panels = [_panel(renderer, gt.table, list(gt.placements), "ground truth", f"{participant} trial {target}")]
    panels += [_panel(renderer, gt.table, placements, method, score) for method, (placements, score) in predictions.items()]
    gap = 8
    width = sum(p.width for p in panels) + gap * (len(panels) - 1)
    sheet = Image.new("RGB", (width, max(p.height for p in panels)), "white")
    x = 0
    for p in panels:
        sheet.paste(p, (x, 0))
        x += p.width + gap
    buf = io.BytesIO()
    sheet.save(buf, format="PNG", optimize=True)
    atomic_write_bytes(path, buf.getvalue())
    return path
