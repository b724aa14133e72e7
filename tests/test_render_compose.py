"""The composed object sheet (`compose: [objects]`) is legible at the model's input size: the five GoMO sheets'
objects are redrawn on one canvas (render/compose.py), not five sheets shrunk into it (ids ~4 px, a third blank)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_small_dataset
from PIL import Image

from degusta_learn.render import text
from degusta_learn.render.compose import CANVAS_BG, objects_layout, sheet_source
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import make_episodes
from degusta_learn.task.prompt import ImagePart, Prompt, build_prompt
from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt

RENDER = 448  # data.render_size of the GPU fine-tuning configs


def composed(size: int = RENDER):
    ds = make_small_dataset(n_participants=4, n_trials=5)  # the default catalog: 5 types x 25 objects
    prompt = build_prompt("mogma", ds, make_episodes(ds, 2, "test", 0)[0], Renderer.for_dataset(ds, size=size),
                          Grid(8, 8))
    return ds, prompt, adapt_prompt(prompt, PromptOptions(compose=["objects"]))


def model_input(canvas: Image.Image, side: int) -> np.ndarray:
    """Luminance of the canvas resized to the model's `side` px tile. SmolVLM's image processor (one tile,
    resample=1) resizes with PIL's LANCZOS: its pixel values equal this resize within 2/255 (checked)."""
    return np.asarray(canvas.convert("RGB").resize((side, side), Image.Resampling.LANCZOS)).astype(float).mean(axis=2)


def id_glyph_heights(ds, lum: np.ndarray, canvas_size: int) -> list[int]:
    """Rows of dark ink inside each id mark's box (its border excluded), in the model's pixels."""
    catalog = ds.catalog
    counts = [len(catalog.of_type(t)) for t in catalog.types]
    lay = objects_layout(counts, max((str(o.id) for o in catalog), key=len), canvas_size)
    scale = lum.shape[0] / canvas_size
    heights, row = [], 0
    for t in catalog.types:
        objs = catalog.of_type(t)
        for i, obj in enumerate(objs):
            r, c = divmod(i, lay.cols)
            x0, y0 = lay.cell(row + r, c)
            w, h = text.mark_size(str(obj.id), lay.font)
            bx, by = x0 + lay.gap + 1, y0 + lay.gap + 1
            box = lum[int((by + 2) * scale):int((by + h - 3) * scale) + 1,
                      int((bx + 2) * scale):int((bx + w - 3) * scale) + 1]
            heights.append(int((box < 128).any(axis=1).sum()))
        row += -(-len(objs) // lay.cols)
    return heights


def blank_fraction(canvas: Image.Image, block: int = 16) -> float:
    """Share of the canvas in `block` px squares holding nothing but the canvas background."""
    a = (np.asarray(canvas.convert("RGB")) == CANVAS_BG).all(axis=2)
    n = a.shape[0] // block
    return float(a[:n * block, :n * block].reshape(n, block, n, block).all(axis=(1, 3)).mean())


def test_composed_object_ids_are_legible_at_smolvlms_input_size():
    ds, _, small = composed()
    canvas = small.images[0].image
    assert small.images[0].name == "objects.jpg" and canvas.size == (RENDER, RENDER)
    heights = id_glyph_heights(ds, model_input(canvas, 512), RENDER)
    assert len(heights) == 125
    # digits of every id are >= 8 px tall in the 512 px tile SmolVLM sees (five shrunk sheets: ~4 px)
    assert min(heights) >= 8, sorted(heights)[:5]
    assert max(heights) <= 13  # and what is measured is the digits, not the box around them


def test_composed_object_sheet_has_no_large_blank_area():
    _, _, small = composed()
    assert blank_fraction(small.images[0].image) < 0.05  # only the unused cells ending each type's band


def test_every_object_is_on_the_composed_sheet_in_type_bands():
    ds, prompt, small = composed()
    sheets = [p for p in prompt.images if p.name.startswith("objects_")]
    sources = [sheet_source(p.image) for p in sheets]
    assert [s[0] for s in sources] == ds.catalog.types
    assert [o.id for s in sources for o in s[1]] == [o.id for t in ds.catalog.types for o in ds.catalog.of_type(t)]
    caption = small.parts[small.parts.index(small.images[0]) - 1]
    assert caption == ("objects.jpg shows the objects of objects_cup.jpg, objects_fork.jpg, objects_knife.jpg, "
                       "objects_plate.jpg, objects_spoon.jpg in one image, in this order:")
    assert not any(isinstance(p, str) and p.startswith("objects_") for p in small.parts)  # no per-sheet labels


def test_training_and_prediction_compose_the_same_canvas():
    _, prompt, first = composed()
    again = adapt_prompt(prompt, PromptOptions(compose=["objects"]))  # the hf backend re-applies the options
    assert first.images[0].encode() == again.images[0].encode()
    assert first.parts[:2] == again.parts[:2]


def test_images_without_a_gomo_source_are_tiled_titled():
    size = 128
    parts = ["These are the objects I have."]
    for t, colour in (("cup", "red"), ("fork", "blue")):
        parts += [f"objects_{t}.jpg:", ImagePart(f"objects_{t}.jpg", Image.new("RGB", (size, size), colour))]
    small = adapt_prompt(Prompt("mogma", parts), PromptOptions(compose=["objects"]))
    assert [p.name for p in small.images] == ["objects.jpg"]
    assert small.parts[1] == "objects.jpg shows the objects of objects_cup.jpg, objects_fork.jpg in one image, in this order:"
    assert np.asarray(small.images[0].image)[0, 0].tolist() == [255, 255, 255]  # tiled, centred on white
    assert small.images[0].image.size == (size, size)


@pytest.mark.parametrize("size", [64, 224])
def test_small_canvases_still_compose(size):
    _, _, small = composed(size)
    assert small.images[0].image.size == (size, size)
