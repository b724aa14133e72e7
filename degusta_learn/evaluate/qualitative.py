"""Qualitative images: ground truth and each method's prediction side by side on the target table.

One PNG per chosen episode (the paper's qualitative figure): the first panel is the held-out ground
truth, then one panel per method, each the unmarked arrangement (UmA) on the target table, titled with
the method and its Kabsch RMSD / object accuracy on that episode. Titles are drawn on one line
(textsafe.one_line: control characters shown as escapes), shrunk and then cut with "…" to fit the panel.
"""

from __future__ import annotations

import io
from pathlib import Path

from PIL import Image, ImageDraw

from degusta_learn.files.atomic import atomic_write_bytes
from degusta_learn.render.lifting import Renderer
from degusta_learn.render.text import font
from degusta_learn.scene import Dataset, Placement
from degusta_learn.textsafe import one_line

_TITLE_H = 54  # title, score line, and a line for objects drawn off the table
_PER_ROW = 4  # panels per row: wide enough to compare, small enough to read


def _fit(draw: ImageDraw.ImageDraw, text: str, width: int, size: int, smallest: int) -> tuple[str, int]:
    """`text` on one line at the largest font size from `size` down to `smallest` that fits `width` pixels,
    cut with "…" where even the smallest does not (a 1,000-character id must not run off the panel)."""
    text = one_line(text, limit=400)
    while size > smallest and draw.textlength(text, font=font(size)) > width:
        size -= 1
    if draw.textlength(text, font=font(size)) > width:
        lo, hi = 0, len(text)  # the longest prefix that fits with the ellipsis
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if draw.textlength(text[:mid] + "…", font=font(size)) <= width:
                lo = mid
            else:
                hi = mid - 1
        text = text[:lo] + "…"
    return text, size


def _panel(renderer: Renderer, table_id: int, placements: list[Placement], title: str, subtitle: str) -> Image.Image:
    table = renderer.tables[table_id]
    off = sum(not bool(table.contains(p.x, p.y)) for p in placements)
    img = renderer.uma(table_id, placements, strict=False)  # a wrong answer off the table is still drawn
    canvas = Image.new("RGB", (img.width, img.height + _TITLE_H), "white")
    canvas.paste(img, (0, _TITLE_H))
    draw = ImageDraw.Draw(canvas)
    # a long method name ("tiny_base_finetuned + grammar") shrinks to fit instead of being cut off
    title, size = _fit(draw, title, canvas.width - 12, 15, 9)
    subtitle, sub_size = _fit(draw, subtitle, canvas.width - 12, 12, 9)
    draw.text((6, 2), title, fill="black", font=font(size))
    draw.text((6, 21), subtitle, fill=(80, 80, 80), font=font(sub_size))
    if off:  # its own line: appended to the score it ran past the panel's edge
        draw.text((6, 37), f"{off} object{'s' if off > 1 else ''} off the table", fill=(170, 60, 40), font=font(12))
    return canvas


def render_side_by_side(ds: Dataset, renderer: Renderer, participant: str, target: int,
                        predictions: dict[str, tuple[list[Placement], str]], path: Path) -> Path:
    """Write one PNG: ground truth, then each method's placements (with a score line), 4 panels a row."""
    gt = ds.arrangement(participant, target)
    panels = [_panel(renderer, gt.table, list(gt.placements), "ground truth", f"{participant} trial {target}")]
    panels += [_panel(renderer, gt.table, placements, method, score) for method, (placements, score) in predictions.items()]
    gap, w, h = 8, max(p.width for p in panels), max(p.height for p in panels)
    cols = min(_PER_ROW, len(panels))
    rows = -(-len(panels) // cols)
    sheet = Image.new("RGB", (cols * w + gap * (cols - 1), rows * h + gap * (rows - 1)), "white")
    for i, p in enumerate(panels):
        sheet.paste(p, ((i % cols) * (w + gap), (i // cols) * (h + gap)))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG", optimize=True)
    atomic_write_bytes(path, buf.getvalue())
    return path
