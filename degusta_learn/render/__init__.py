"""Rendering (PIL + numpy): sprites, tables, grid geometry and the lifting functions.

- grid.py      Grid (cell ids, footprint -> cells, decode), directions, circular mean, quantization_rmsd
- lifting.py   Renderer (uma, gma, table, gomo, catalog_sheet), oal_text, order_text, METHODS
- commands.py  render_episode, render_catalog (the `degusta render` verb)
- compose.py   objects_canvas (the composed object sheet, redrawn legibly), tile_canvas (other composed groups)
- sprites.py / shapes.py / materials.py   procedural (or picture) object sprites; tables.py   table images

See docs/render.md for the conventions and pictures.
"""

from degusta_learn.render.grid import (
    DIRECTIONS,
    Grid,
    as_grid,
    circular_mean,
    direction_to_rotation,
    quantization_rmsd,
    rotation_to_direction,
)
from degusta_learn.render.lifting import LIFTINGS, METHODS, Renderer, method_liftings, oal_text, order_text

__all__ = [
    "DIRECTIONS", "LIFTINGS", "METHODS", "Grid", "Renderer", "as_grid", "circular_mean", "direction_to_rotation",
    "method_liftings", "oal_text", "order_text", "quantization_rmsd", "rotation_to_direction",
]
