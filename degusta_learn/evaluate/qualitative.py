"""Qualitative images: ground truth and each method's prediction side by side on the target table.

One PNG per chosen episode (the paper's qualitative figure): the first panel is the held-out ground
truth, then one panel per method, each the unmarked arrangement (UmA) on the target table, titled with
the method and its Kabsch RMSD / object accuracy on that episode. Titles are drawn on one line
(textsafe.one_line: control characters shown as escapes), shrunk and then cut with "…" to fit the panel.

Each panel also says why it scores what it scores: the placement order and the matching behind the
scores (`match_marks`, from `metrics.matched_pairs` with the report's matching rule):

- ground truth: each object labelled with its placement step 1..n;
- a method: each predicted object labelled "j→g", its own step j and the step g of the true object it
  was matched to, green where it is the same object, orange where it is another one (accuracy counts only
  green), with a thin line of that colour to where the true object lies; a prediction left unmatched
  reads "j×" in grey; the true positions are drawn as faint rings, red (with their step) where no
  prediction was matched to that object.

A legend under the panels says this and names the matching rule.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

from PIL import Image, ImageDraw

from degusta_learn.files.atomic import atomic_write_bytes
from degusta_learn.metrics import matched_pairs
from degusta_learn.render.lifting import Renderer
from degusta_learn.render.text import font
from degusta_learn.scene import Arrangement, Catalog, Dataset, Placement
from degusta_learn.textsafe import one_line

_TITLE_H = 54  # title, score line, and a line for objects drawn off the table
_PER_ROW = 4  # panels per row: wide enough to compare, small enough to read
SAME, OTHER, UNMATCHED, MISSED = (30, 140, 60), (225, 120, 10), (120, 120, 120), (205, 35, 35)
"""Mark colours: matched to the same object, matched to another object, a prediction left unmatched, a true
object no prediction was matched to."""


@dataclass(frozen=True)
class PredictionMark:
    """What one predicted object's label says."""

    step: int  # its place in the answer, 1-based (the placement order)
    gt_step: int | None  # placement step (1-based) of the true object it was matched to; None: unmatched
    same_object: bool  # matched to exactly the same object id (what object accuracy counts)


@dataclass(frozen=True)
class MatchMarks:
    """What a method's panel draws: one mark per predicted object (answer order), the 0-based (gt_index,
    pred_index) pairs of `metrics.matched_pairs`, and the 1-based steps of the true objects left unmatched."""

    predictions: tuple[PredictionMark, ...]
    pairs: tuple[tuple[int, int], ...]
    missed: tuple[int, ...]


def match_marks(catalog: Catalog, gt: Arrangement, prediction, matching: str = "hungarian") -> MatchMarks:
    """The marks of one prediction (a Prediction, or a sequence of Placements) against its ground truth, from the
    pairs the scores use (`metrics.matched_pairs` with `matching`): a failed prediction has no pairs."""
    pairs = matched_pairs(catalog, gt, prediction, matching=matching)
    placements = list(getattr(prediction, "placements", prediction) or ())
    by_pred = {p.pred_index: p for p in pairs}
    marks = tuple(PredictionMark(j + 1, by_pred[j].gt_index + 1 if j in by_pred else None,
                                 j in by_pred and by_pred[j].same_object) for j in range(len(placements)))
    matched = {p.gt_index for p in pairs}
    return MatchMarks(marks, tuple((p.gt_index, p.pred_index) for p in pairs),
                      tuple(i + 1 for i in range(len(gt.placements)) if i not in matched))


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


def _label_size(width: int) -> int:
    """Font size of the step labels: legible at the reports' 256 px panels (12 px), never huge."""
    return max(9, min(16, round(width / 21)))


_OFFSETS = ((0, -1), (0, 1), (1, 0), (-1, 0), (1, -1), (-1, -1), (1, 1), (-1, 1), (0, -2), (0, 2), (2, 0), (-2, 0))
"""Where a label may go, in label-box units from its object's centre: above first, then around it."""


def _overlap(a, b) -> float:
    return max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1]))


def _place_labels(draw: ImageDraw.ImageDraw, labels: list, size: int, bounds: tuple[int, int]) -> None:
    """Draw `labels` ((x, y), text, box colour or None for black on white) next to their points, each at the
    first of `_OFFSETS` that overlaps no label drawn before it and stays inside `bounds` (else where it
    overlaps least): dense settings (a knife beside a fork beside a plate) stay readable."""
    f, placed = font(size), []
    pad = max(1, size // 6)
    for (x, y), text, colour in labels:
        x0, y0, x1, y1 = draw.textbbox((0, 0), text, font=f, anchor="mm")
        w, h = x1 - x0 + 2 * pad, y1 - y0 + 2 * pad
        best, best_cost = None, None
        for dx, dy in _OFFSETS:
            cx, cy = x + dx * (w / 2 + 2), y + dy * (h / 2 + 2)
            box = (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)
            outside = box[0] < 0 or box[1] < 0 or box[2] > bounds[0] or box[3] > bounds[1]
            cost = sum(_overlap(box, b) for b in placed) + (w * h if outside else 0)
            if best_cost is None or cost < best_cost:
                best, best_cost = box, cost
            if cost == 0:
                break
        placed.append(best)
        plain = colour is None
        draw.rounded_rectangle(best, radius=max(2, size // 3), fill=(255, 255, 255) if plain else colour,
                               outline=(0, 0, 0) if plain else (255, 255, 255), width=1)
        draw.text(((best[0] + best[2]) / 2, (best[1] + best[3]) / 2), text, font=f,
                  fill=(0, 0, 0) if plain else (255, 255, 255), anchor="mm")


def _draw_marks(img: Image.Image, gt: Arrangement, placements: list[Placement], marks: MatchMarks | None) -> Image.Image:
    """`img` (the table as drawn, w x h px for the unit square) with the steps and, for a method, the matching."""
    w, h = img.width, img.height
    size = _label_size(w)

    def px(p: Placement) -> tuple[float, float]:
        return p.x * w, p.y * h

    out = img.convert("RGBA")
    if marks is None:  # the ground truth: its placement order
        _place_labels(ImageDraw.Draw(out), [(px(p), str(i + 1), None) for i, p in enumerate(gt.placements)], size,
                      out.size)
        return out.convert("RGB")
    overlay = Image.new("RGBA", out.size, (0, 0, 0, 0))
    od = ImageDraw.Draw(overlay)
    r = max(3, round(w / 64))
    missed = set(marks.missed)
    for i, p in enumerate(gt.placements):  # faint rings where the true objects are, red where left unmatched
        x, y = px(p)
        colour = (*MISSED, 235) if i + 1 in missed else (40, 40, 40, 150)
        od.ellipse((x - r, y - r, x + r, y + r), outline=colour, width=2)
    for gi, pj in marks.pairs:  # a line from each predicted object to the true object it was matched to
        colour = SAME if marks.predictions[pj].same_object else OTHER
        od.line([px(placements[pj]), px(gt.placements[gi])], fill=(*colour, 220), width=2)
    out = Image.alpha_composite(out, overlay)
    labels = [(px(gt.placements[step - 1]), str(step), MISSED) for step in marks.missed]
    for mark, p in zip(marks.predictions, placements):
        if mark.gt_step is None:
            labels.append((px(p), f"{mark.step}×", UNMATCHED))
        else:
            labels.append((px(p), f"{mark.step}→{mark.gt_step}", SAME if mark.same_object else OTHER))
    _place_labels(ImageDraw.Draw(out), labels, size, out.size)
    return out.convert("RGB")


def _panel(renderer: Renderer, gt: Arrangement, placements: list[Placement], title: str, subtitle: str,
           marks: MatchMarks | None) -> Image.Image:
    table = renderer.tables[gt.table]
    off = sum(not bool(table.contains(p.x, p.y)) for p in placements)
    img = renderer.uma(gt.table, placements, strict=False)  # a wrong answer off the table is still drawn
    img = _draw_marks(img, gt, placements, marks)
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


LEGEND = (("Numbers: placement step. On a prediction, j→g: its step j, matched to the true object of step g",
           (40, 40, 40)), ("(matching: {matching}).", (40, 40, 40)),
          ("Green: the same object.", SAME), ("Orange: another object.", OTHER),
          ("Grey j×: not matched.", UNMATCHED), ("Red ring and red step: a true object left unmatched.", MISSED))
"""The legend under the panels: (text, colour) pieces, wrapped to the sheet's width."""


def _legend(width: int, matching: str) -> Image.Image:
    """The legend strip: LEGEND's pieces flowed word by word into lines of at most `width` pixels."""
    size = 12
    f = font(size)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    space = probe.textlength(" ", font=f)
    lines: list[list[tuple[float, str, tuple]]] = [[]]
    x = 0.0
    for text, colour in LEGEND:
        for word in text.format(matching=matching).split():
            wlen = probe.textlength(word, font=f)
            if x and x + wlen > width - 12:
                lines.append([])
                x = 0.0
            lines[-1].append((x, word, colour))
            x += wlen + space
    line_h = size + 5
    strip = Image.new("RGB", (width, 6 + line_h * len(lines)), "white")
    draw = ImageDraw.Draw(strip)
    for row, words in enumerate(lines):
        for x, word, colour in words:
            draw.text((6 + x, 4 + row * line_h), word, fill=colour, font=f)
    return strip


def render_side_by_side(ds: Dataset, renderer: Renderer, participant: str, target: int,
                        predictions: dict, path: Path, matching: str = "hungarian") -> Path:
    """Write one PNG: ground truth, then each method's placements (with a score line), 4 panels a row, the
    placement steps and the matching under rule `matching` drawn on them (module docstring), a legend below.

    `predictions`: method -> (placements, score line); the placements may be the Prediction itself, so that a
    failed one is drawn as the scores see it (nothing matched).
    """
    gt = ds.arrangement(participant, target)
    panels = [_panel(renderer, gt, list(gt.placements), "ground truth", f"{participant} trial {target}", None)]
    for method, (prediction, score) in predictions.items():
        placements = list(getattr(prediction, "placements", prediction) or ())
        marks = match_marks(ds.catalog, gt, prediction, matching)
        panels.append(_panel(renderer, gt, placements, method, score, marks))
    gap, w, h = 8, max(p.width for p in panels), max(p.height for p in panels)
    cols = min(_PER_ROW, len(panels))
    rows = -(-len(panels) // cols)
    width = cols * w + gap * (cols - 1)
    legend = _legend(width, matching)
    sheet = Image.new("RGB", (width, rows * h + gap * (rows - 1) + legend.height), "white")
    for i, p in enumerate(panels):
        sheet.paste(p, ((i % cols) * (w + gap), (i // cols) * (h + gap)))
    sheet.paste(legend, (0, rows * h + gap * (rows - 1)))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG", optimize=True)
    atomic_write_bytes(path, buf.getvalue())
    return path
