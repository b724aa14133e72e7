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

Everything is rendered in memory first and then written as one folder ((`files.folders`)): the
files land in a temporary folder beside `out` that is swapped in whole, so a bad input or a failure while
writing leaves `out` as it was (never a mix of old and new files). A folder that also holds files
`render` does not write keeps them; the episode files of a previous render are replaced.
"""

from __future__ import annotations

import io
from pathlib import Path

from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import atomic_write_bytes
from degusta_learn.files.folders import OutputKind, check_target, write_folder
from degusta_learn.files.guard import check_output_file, refuse_replacing_inputs
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer, method_liftings, oal_text, order_text
from degusta_learn.scene import Dataset, load_dataset, make_episodes

EPISODE_FILES = OutputKind("rendered episode", ("final_state_*.png", "initial_state_*.png", "objects_*.png",
                                                "objects.json", "order.txt"))


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
    files = {name: png_bytes(image) for name, image in images.items()}
    files.update({name: content.encode("utf-8") for name, content in texts.items()})
    check_target(out, EPISODE_FILES)
    refuse_replacing_inputs(out, kind=EPISODE_FILES, datasets=[ds.root], writes=list(files), key="--out")
    with write_folder(out, EPISODE_FILES) as tmp:
        for name, data in files.items():
            (tmp / name).write_bytes(data)
    return [out / name for name in files]


def render_catalog(dataset: Dataset | str | Path, out: str | Path, size: int = 448) -> Path:
    """Write the contact sheet of the whole catalog (every type's GoMO sheet, `size` px each)."""
    out = Path(out)
    if out.is_dir():
        raise DegustaError(f"{out}: is a folder; give the PNG file to write, e.g. {out / 'catalog.png'}")
    if out.suffix.lower() != ".png":
        raise DegustaError(f"--out: {out}: the contact sheet is a PNG image; give a path ending in .png")
    ds = _dataset(dataset)
    check_output_file(out, datasets=[ds.root], key="--out")
    if out.exists() and not _is_png(out):
        raise DegustaError(f"--out: {out} exists and is not a PNG image; it is left untouched: remove it yourself "
                           "or choose another path")
    data = png_bytes(Renderer.for_dataset(ds, size).catalog_sheet())
    atomic_write_bytes(out, data)  # an unwritable path is a DegustaError naming it (files.atomic.atomic_open)
    return out


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _is_png(path: Path) -> bool:
    """Whether the file at `path` starts with the PNG signature (only a PNG is replaced by a contact sheet)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(PNG_SIGNATURE)) == PNG_SIGNATURE
    except OSError:
        return False
