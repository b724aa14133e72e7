"""Where a grid-marked image's cell borders fall among the model's image tokens.

A grid method names the cells an object covers, and the model sees an image as a lattice of image tokens. Where
a cell border cuts through a token, that token mixes two cells (or a cell and a label of the margin): it is
the model's only view of both. `cell_alignment` says where every border falls, in tokens.

- The token lattice (`image_token_grid`): the processor resizes the WHOLE image onto it, so pixel column x of a
  W px wide image lies at x * n / W tokens for n tokens across. SmolVLM (Idefics3, one tile, no splitting):
  the image is squared to the 512 px tile, 16 px patches, pixel shuffle 4 -> one token per 64 px, 8 x 8.
  Qwen2-VL: each side rounded to a multiple of 28 px (`smart_resize`), 14 px patches merged 2 x 2 -> one
  token per 28 px. The tiny base (a CNN tower, `fast_vlm`): resized to its size, one token per output stride
  (32 px at 256).
- The cells (render/lifting.py): a grid-marked (GMA) image of W x H px carries a label margin of m px on each
  side (`Renderer.margin`, 5% of the render size); the table fills the rest, so column border c (0 .. cols, the
  table's edges included) lies at m + c * (W - 2m) / cols px, and likewise for rows.

Each border's offset is its distance to the nearest token border, as a fraction of a token: 0 lines up, 0.5 cuts
a token in half. The cells line up with the tokens only if every offset is 0 (a margin of whole tokens and a
whole number of tokens per cell).

Example (SmolVLM at 512 px: 26 px margins, 57.5 px cells, 64 px tokens):
    a = cell_alignment(Grid(8, 8), (512, 512), 26, (8, 8))
    a.x.borders[:2], a.x.offsets[:2], a.max_offset     # (0.406, 1.305), (0.406, 0.305), 0.406
"""

from __future__ import annotations

import math
from dataclasses import dataclass

ALIGNED = 1e-6
"""Offsets (fractions of a token) at most this small count as lined up."""


@dataclass(frozen=True)
class AxisAlignment:
    """The cell borders of one image axis (columns across, rows down) in image-token units."""

    cells: int
    """Cells along this axis (grid columns or rows)."""
    tokens: int
    """Image tokens along this axis."""
    pixels: int
    """Image size along this axis as rendered (px)."""
    margin: float
    """Label margin before the table (px)."""
    borders: tuple[float, ...]
    """Position of each cell border in tokens, `cells + 1` values: the table's two edges and the inner borders."""

    @property
    def offsets(self) -> tuple[float, ...]:
        """Distance of each border to the nearest token border, as a fraction of a token (0 .. 0.5)."""
        return tuple(abs(b - round(b)) for b in self.borders)

    @property
    def tokens_per_cell(self) -> float:
        return self.tokens * (self.pixels - 2 * self.margin) / self.cells / self.pixels

    @property
    def pixels_per_token(self) -> float:
        """Rendered pixels per image token (before the processor's resize)."""
        return self.pixels / self.tokens


@dataclass(frozen=True)
class GridAlignment:
    """Where the cells of a GMA image fall among its image tokens (`cell_alignment`)."""

    x: AxisAlignment
    y: AxisAlignment

    @property
    def max_offset(self) -> float:
        return max(self.x.offsets + self.y.offsets)

    @property
    def mean_offset(self) -> float:
        offsets = self.x.offsets + self.y.offsets
        return sum(offsets) / len(offsets)

    @property
    def aligned(self) -> bool:
        return self.max_offset <= ALIGNED

    def describe(self) -> str:
        """One line: the geometry, then 'the cell borders lie on token borders' or how far they are off."""
        x, y = self.x, self.y
        same = (x.cells, x.tokens, x.pixels, x.margin) == (y.cells, y.tokens, y.pixels, y.margin)
        size = f"{x.pixels} x {y.pixels} px"
        head = (f"{x.cells}x{y.cells} grid on {size} ({_num(x.margin)} px label margins) -> {x.tokens} x {y.tokens} "
                f"image tokens of {_num(x.pixels_per_token)} px: {_num(x.tokens_per_cell, 2)} tokens per cell")
        if not same:
            head += f" across, {_num(y.tokens_per_cell, 2)} down"
        if self.aligned:
            return head + "; every cell border lies on a token border (aligned)"
        axes = [("columns and rows", x)] if same else [("columns", x), ("rows", y)]
        where = "; ".join(f"{name}' borders at {_list(a.borders)} tokens, off by {_list(a.offsets)}"
                          for name, a in axes)
        return (head + f"; {where}: up to {self.max_offset:.2f} of a token (mean {self.mean_offset:.2f}), the tokens "
                "on those borders mix two cells or a cell and the labels")


def cell_alignment(grid, image_size: tuple[int, int], margin: float, tokens: tuple[int, int]) -> GridAlignment:
    """Cell borders of a GMA image in image tokens.

    Args:
        grid: the `Grid` drawn (rows, cols).
        image_size: (width, height) of the rendered GMA image, margins included (px).
        margin: the label margin on each side (px; `Renderer.margin`).
        tokens: (across, down) image tokens the processor makes of the image (`image_token_grid`).
    """
    (width, height), (nx, ny) = image_size, tokens
    return GridAlignment(_axis(grid.cols, nx, width, margin), _axis(grid.rows, ny, height, margin))


def _axis(cells: int, tokens: int, pixels: int, margin: float) -> AxisAlignment:
    cell = (pixels - 2 * margin) / cells
    borders = tuple((margin + c * cell) * tokens / pixels for c in range(cells + 1))
    return AxisAlignment(cells, tokens, pixels, margin, borders)


def gma_margin(render_size: int) -> int:
    """The label margin (px) of GMA images drawn at `render_size` (the renderer's own, not a copy of its rule)."""
    from degusta_learn.render.lifting import Renderer
    from degusta_learn.scene import Catalog

    return Renderer(Catalog(()), {}, size=render_size).margin


def image_token_grid(processor, model_config, width: int, height: int) -> tuple[int, int] | None:
    """(across, down) image tokens one `width` x `height` px image gets with this processor's budget (after
    `vlm.inputs.set_image_budget`); None where the geometry is not known (another model type, an Idefics3
    processor that splits images into tiles)."""
    ip = processor.image_processor
    mtype = getattr(model_config, "model_type", "")
    if mtype == "idefics3":
        if getattr(ip, "do_image_splitting", False):
            return None
        tile = (getattr(ip, "max_image_size", None) or {}).get("longest_edge")
        unit = model_config.vision_config.patch_size * model_config.scale_factor
        return (tile // unit,) * 2 if tile else None  # squared onto one tile whatever the aspect
    if mtype in ("qwen2_vl", "qwen2_5_vl"):
        try:
            from transformers.models.qwen2_vl.image_processing_qwen2_vl import smart_resize
        except ImportError:  # another transformers layout: say unknown rather than guess
            return None
        vc = model_config.vision_config
        unit = getattr(vc, "patch_size", 14) * getattr(vc, "spatial_merge_size", 2)
        size = getattr(ip, "size", None) or {}
        lo = size.get("shortest_edge") or getattr(ip, "min_pixels", None)
        hi = size.get("longest_edge") or getattr(ip, "max_pixels", None)
        if not (lo and hi):
            return None
        h, w = smart_resize(height, width, factor=unit, min_pixels=lo, max_pixels=hi)
        return w // unit, h // unit
    if mtype == "fast_vlm":
        size = getattr(ip, "size", None) or {}
        stride = getattr(processor, "patch_size", None)
        if not (stride and size.get("height") and size.get("width")):
            return None
        return size["width"] // stride, size["height"] // stride
    return None


def _num(v: float, digits: int = 1) -> str:
    return str(int(v)) if math.isclose(v, round(v)) else f"{v:.{digits}f}"


def _list(values) -> str:
    return "[" + ", ".join(f"{v:.2f}" for v in values) + "]"
