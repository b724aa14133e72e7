"""Prompt texts and images per method and context length (louma, logma, mouma, mogma x k = 0, 2, 4)."""

from __future__ import annotations

import json

import pytest
from conftest import make_small_dataset

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.cache import prompt_digest
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import make_episodes
from degusta_learn.task.prompt import ImagePart, build_prompt

DS = make_small_dataset(n_participants=3, n_trials=5)
R = Renderer.for_dataset(DS, size=64)
G = Grid(8, 8)
PAPER_GRID = ("Please list all grid cells the object will intersect after it is placed. Give the orientation as the "
              "closest cardinal direction [N, NE, E, SE, S, SW, W, NW] the object is pointing in after it is "
              "placed. The top of the image is N.")
PAPER_UNMARKED = ("Give a position in [x,y] where each value is a number between 0 and 1")
PAPER_END = "Give object_id as an integer."


def episode(k):
    return make_episodes(DS, k, "all")[0]


@pytest.mark.parametrize("method", ["louma", "logma", "mouma", "mogma"])
@pytest.mark.parametrize("k", [0, 2, 4])
def test_names_images_and_text(method, k):
    ep = episode(k)
    prompt = build_prompt(method, DS, ep, R, G)
    marked, gridded = method.startswith("mo"), method.endswith("gma")
    names = [p.name for p in prompt.images]
    sheets = [f"objects_{t}.jpg" for t in ("cup", "fork", "knife", "plate", "spoon")] if marked else []
    assert names == sheets + [f"final_state_{i}.jpg" for i in range(1, k + 1)] + ["initial_state_1.jpg"]
    # every image is announced by name right before it
    for i, part in enumerate(prompt.parts):
        if isinstance(part, ImagePart):
            assert prompt.parts[i - 1] == f"{part.name}:"
    text = prompt.text
    task = prompt.parts[-1]
    assert isinstance(task, str) and task.endswith("Include only this list in your response.")
    assert PAPER_END in task and prompt.episode == ep.id
    assert (PAPER_GRID in task) == gridded and (PAPER_UNMARKED in task) == (not gridded)
    assert ("'cardinal_direction': direction" in task) == gridded
    # OaL: the whole catalog as JSON, only for language-object methods
    has_json = '"class": "cup"' in text
    assert has_json == (not marked)
    if not marked:
        start = text.index("[\n{")
        catalog = json.loads(text[start:text.index("\n]", start) + 2])
        assert len(catalog) == 125 and catalog[17]["id"] == 17
    # context: named in the first sentence, with its placement order; none at k = 0
    if k:
        assert task.startswith("My preferences for setting a table are shown in the images named final_state_1.jpg")
        assert f"final_state_{k}.jpg. You are helping me set the table in initial_state_1.jpg" in task
        arr = DS.arrangement(ep.participant, ep.context[0])
        order = ", ".join(DS.catalog[p.object].type for p in arr.placements)
        assert f"Placement order in final_state_1.jpg: {order}." in prompt.parts
    else:
        assert "final_state" not in text and "preferences" not in text and "Placement order" not in text


def test_images_are_the_methods_liftings():
    ep = episode(2)
    target = DS.arrangement(ep.participant, ep.target)
    ctx = DS.arrangement(ep.participant, ep.context[0])
    grid_prompt = {p.name: p.image for p in build_prompt("mogma", DS, ep, R, G).images}
    plain_prompt = {p.name: p.image for p in build_prompt("louma", DS, ep, R, G).images}
    assert grid_prompt["initial_state_1.jpg"].tobytes() == R.table(target.table, grid=G).tobytes()
    assert plain_prompt["initial_state_1.jpg"].tobytes() == R.table(target.table).tobytes()
    assert grid_prompt["final_state_1.jpg"].tobytes() == R.gma(ctx.table, ctx.placements, G).tobytes()
    assert plain_prompt["final_state_1.jpg"].tobytes() == R.uma(ctx.table, ctx.placements).tobytes()
    assert grid_prompt["objects_fork.jpg"].tobytes() == R.gomo("fork").tobytes()
    assert grid_prompt["final_state_1.jpg"].size == (64, 64)


def test_png_format_and_grid_size_are_configurable():
    prompt = build_prompt("logma", DS, episode(2), R, Grid(6, 10), image_format="png")
    assert [p.name for p in prompt.images] == ["final_state_1.png", "final_state_2.png", "initial_state_1.png"]
    assert prompt.images[0].encode()[:8] == b"\x89PNG\r\n\x1a\n"
    assert prompt.images[0].data_url().startswith("data:image/png;base64,")
    assert "columns A to J from the left and rows 1 to 6" in prompt.parts[-1]
    jpeg = build_prompt("logma", DS, episode(2), R, G).images[0]
    assert jpeg.encode()[:3] == b"\xff\xd8\xff" and jpeg.mime == "image/jpeg"


def test_prompts_are_deterministic_so_cache_keys_repeat():
    a = build_prompt("mogma", DS, episode(4), Renderer.for_dataset(DS, size=64), G)
    b = build_prompt("mogma", DS, episode(4), Renderer.for_dataset(DS, size=64), G)
    assert prompt_digest(a) == prompt_digest(b)
    c = build_prompt("mogma", DS, make_episodes(DS, 4, "all")[1], R, G)
    assert prompt_digest(a) != prompt_digest(c)


def test_unknown_method_or_format():
    with pytest.raises(DegustaError, match="unknown prompting method"):
        build_prompt("random", DS, episode(0), R, G)
    with pytest.raises(DegustaError, match="image_format"):
        build_prompt("mogma", DS, episode(0), R, G, image_format="gif")
