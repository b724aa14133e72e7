"""`degusta render`: write an episode's lifted images and texts, or the catalog contact sheet.

Usage:
    degusta data generate naturalistic --out data/naturalistic
    degusta render episode data/naturalistic --participant p000 --target 0 --context 4 --method mogma --out runs/render
    degusta render catalog data/naturalistic --out runs/catalog.png

`render episode` writes, for the episode of `make_episodes(ds, context, "all", seed)` whose participant
and target trial are given (the same episode `degusta predict` sees):

    final_state_K.png    context arrangement K (GMA for logma/mogma, UmA for louma/mouma)
    initial_state_1.png  the empty target table (with the grid for logma/mogma)
    objects_TYPE.png     one GoMO sheet per object type (mouma/mogma)
    objects.json         the catalog as JSON text, OaL (louma/logma)
    order.txt            one placement-order line per context image (when the context is not empty)

Everything is rendered in memory first and then written file by file atomically, so a bad input
leaves no output behind.
"""

from __future__ import annotations

import io
from pathlib import Path

from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.fileio import atomic_write_bytes, atomic_write_text
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer, method_liftings, oal_text, order_text
from degusta_learn.scene import Dataset, load_dataset, make_episodes


def png_bytes(image: Image.Image) -> bytes:
    """PNG encoding (deterministic: no timestamps, fixed compression)."""
    buf = io.BytesIO()
    image.save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def _dataset(dataset: Dataset | str | Path) -> Dataset:
    return dataset if isinstance(dataset, Dataset) else load_dataset(dataset)


def render_episode(dataset: Dataset | str | Path, participant: str, target: int, context: int, method: str,
                   out: str | Path, size: int = 448, grid: int = 8, seed: int = 0) -> list[Path]:
    """Write one episode's image set and prompt texts into `out`; returns the files written."""
    ds = _dataset(dataset)
    objects_lifting, arrangement_lifting = method_liftings(method)
    g = Grid(grid, grid)
    episode = next((e for e in make_episodes(ds, context, "all", seed)
                    if e.participant == str(participant) and e.target == target), None)
    if episode is None:
        if str(participant) not in ds.participants:
            raise DegustaError(f"participant {participant!r} is not in the dataset")
        raise DegustaError(f"participant {participant!r} has no trial {target} to use as the target")
    renderer = Renderer.for_dataset(ds, size)
    gridded = g if arrangement_lifting == "gma" else None
    images: dict[str, Image.Image] = {}
    lines = []
    for k, trial in enumerate(episode.context, start=1):
        arr = ds.arrangement(episode.participant, trial)
        name = f"final_state_{k}.png"
        images[name] = renderer.arrangement(arrangement_lifting, arr.table, arr.placements, gridded)
        lines.append(order_text(arr, ds.catalog, name))
    target_table = ds.arrangement(episode.participant, episode.target).table
    images["initial_state_1.png"] = renderer.table(target_table, gridded)
    texts: dict[str, str] = {}
    if objects_lifting == "gomo":
        for type_ in ds.catalog.types:
            images[f"objects_{type_}.png"] = renderer.gomo(type_)
    else:
        texts["objects.json"] = oal_text(ds.catalog) + "\n"
    if lines:
        texts["order.txt"] = "\n".join(lines) + "\n"
    out = Path(out)
    written = []
    for name, image in images.items():
        atomic_write_bytes(out / name, png_bytes(image))
        written.append(out / name)
    for name, content in texts.items():
        atomic_write_text(out / name, content)
        written.append(out / name)
    return written


def render_catalog(dataset: Dataset | str | Path, out: str | Path, size: int = 448) -> Path:
    """Write the contact sheet of the whole catalog (every type's GoMO sheet, `size` px each)."""
    ds = _dataset(dataset)
    out = Path(out)
    atomic_write_bytes(out, png_bytes(Renderer.for_dataset(ds, size).catalog_sheet()))
    return out
