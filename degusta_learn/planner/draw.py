"""plan.png: the table to set with the plan drawn on it (the unmarked arrangement the rest of the toolkit draws) and
each object labelled with its step, under a title line naming the method and what the planner changed."""

from __future__ import annotations

from pathlib import Path

from PIL import Image, ImageDraw

from degusta_learn.planner.plan import Plan
from degusta_learn.render.lifting import Renderer
from degusta_learn.render.text import draw_mark, font, mark_size
from degusta_learn.scene import Catalog, Table
from degusta_learn.textsafe import one_line

TITLE_H = 40


def plan_image(plan: Plan, catalog: Catalog, table: Table, root: str | Path | None = None, size: int = 512) -> Image.Image:
    """The plan on `table` at `size` pixels (longer side), step labels at the objects, a title strip above."""
    renderer = Renderer(catalog, {table.id: table}, root, size)
    img = renderer.uma(table.id, plan.placements, strict=False).convert("RGB")
    draw = ImageDraw.Draw(img)
    label = max(10, round(img.width / 32))
    for s in plan.steps:
        w, h = mark_size(str(s.step), label)
        x = min(max(s.x * img.width - w / 2, 0), img.width - w)
        y = min(max(s.y * img.height - h / 2, 0), img.height - h)
        draw_mark(draw, (x, y), str(s.step), label)
    canvas = Image.new("RGB", (img.width, img.height + TITLE_H), "white")
    canvas.paste(img, (0, TITLE_H))
    d = plan.diagnostics
    changed = [f"{len(d.get('replaced') or [])} replaced" if d.get("replaced") else "",
               f"{len(d.get('dropped') or [])} dropped" if d.get("dropped") else "",
               f"{len(d.get('clamped') or [])} moved onto the surface" if d.get("clamped") else "",
               f"{d['cut']} cut (n_objects)" if d.get("cut") else "",
               "FAILED" if plan.failed else ""]
    title = one_line(f"{plan.method}: {len(plan.steps)} steps on table {table.name or table.id}", limit=80)
    note = "; ".join(c for c in changed if c) or f"numbers: placement order; context {d.get('context', '?')}"
    draw = ImageDraw.Draw(canvas)
    draw.text((6, 3), title, fill="black", font=font(15))
    draw.text((6, 22), one_line(note, limit=100), fill=(90, 90, 90), font=font(12))
    return canvas


__all__ = ["plan_image"]
