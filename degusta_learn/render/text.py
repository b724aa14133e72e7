"""Fonts and label drawing for the lifted images (PIL only).

The font is DejaVu Sans Bold shipped inside matplotlib (a declared dependency), so labels look the same
on every machine with the same Pillow/FreeType; without it Pillow's embedded default font is used.
Labels get a halo (a stroke in a contrasting colour) or a rounded box so they stay readable on any
background. Every function draws its text on one line (textsafe.one_line: whitespace runs as one space,
control characters as visible escapes): a word with a newline or a NUL draws instead of raising (Pillow's
anchored text refuses multi-line strings).

Example:
    from PIL import Image, ImageDraw
    from degusta_learn.render.text import draw_mark
    im = Image.new("RGB", (64, 64), "gray"); draw_mark(ImageDraw.Draw(im), (4, 4), "17", size=14)
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

from PIL import ImageDraw, ImageFont

from degusta_learn.textsafe import one_line


def _font_path() -> Path | None:
    spec = importlib.util.find_spec("matplotlib")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "mpl-data" / "fonts" / "ttf" / "DejaVuSans-Bold.ttf"
    return path if path.is_file() else None


@functools.lru_cache(maxsize=64)
def font(size: int) -> ImageFont.FreeTypeFont:
    """A bold sans font of `size` pixels (cached)."""
    path = _font_path()
    size = max(6, int(size))
    if path is not None:
        return ImageFont.truetype(str(path), size)
    return ImageFont.load_default(size=size)


def text_size(text: str, size: int) -> tuple[int, int]:
    """(width, height) in pixels of `text` drawn at font `size` (ink box)."""
    x0, y0, x1, y1 = font(size).getbbox(one_line(text, limit=None))
    return x1 - x0, y1 - y0


def draw_centered(draw: ImageDraw.ImageDraw, center: tuple[float, float], text: str, size: int,
                  fill=(0, 0, 0), halo=None, halo_width: int = 0) -> None:
    """Draw `text` centred on `center` (ink-box centred), optionally with a halo stroke."""
    f = font(size)
    draw.text(center, one_line(text, limit=None), font=f, fill=fill, anchor="mm",
              stroke_width=halo_width if halo is not None else 0, stroke_fill=halo)


def draw_mark(draw: ImageDraw.ImageDraw, top_left: tuple[float, float], text: str, size: int) -> tuple[int, int, int, int]:
    """A numeric mark: black digits in a white rounded box with a black border; returns the box."""
    w, h = text_size(text, size)
    pad_x, pad_y = max(2, size // 4), max(2, size // 5)
    x0, y0 = int(round(top_left[0])), int(round(top_left[1]))
    box = (x0, y0, x0 + w + 2 * pad_x, y0 + h + 2 * pad_y)
    draw.rounded_rectangle(box, radius=max(2, size // 3), fill=(255, 255, 255), outline=(0, 0, 0), width=1)
    draw_centered(draw, ((box[0] + box[2] + 1) / 2, (box[1] + box[3] + 1) / 2), text, size)
    return box


def mark_size(text: str, size: int) -> tuple[int, int]:
    """(width, height) of the box `draw_mark` draws for `text`."""
    w, h = text_size(text, size)
    return w + 2 * max(2, size // 4) + 1, h + 2 * max(2, size // 5) + 1
