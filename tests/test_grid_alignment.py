"""Where a GMA image's cell borders fall among the image tokens (`vlm.token_grid`, `check_grid_resolution`).

Expected positions are computed by hand from the geometry: a GMA image of W px has a label margin m on each
side (render/lifting.py), so cell border c lies at m + c * (W - 2m) / cols px, i.e. at that times n / W tokens
for n tokens across. The token lattices are checked against what the processors themselves output."""

from __future__ import annotations

from pathlib import Path

import pytest
from finetune_support import dataset, tiny_dir
from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_train
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import save_dataset
from degusta_learn.shipped import shipped_model
from degusta_learn.vlm.inputs import check_grid_resolution, set_image_budget
from degusta_learn.vlm.token_grid import cell_alignment, gma_margin, image_token_grid

G8 = Grid(8, 8)
CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _approx(values):
    return pytest.approx(values, abs=1e-6)


def test_smolvlm_512_px_tile():
    # 26 px margins, 460 px table, 57.5 px cells, 64 px tokens: (26 + 57.5 c) / 64
    a = cell_alignment(G8, (512, 512), 26, (8, 8))
    assert a.x.borders == _approx([0.40625, 1.3046875, 2.203125, 3.1015625, 4.0, 4.8984375, 5.796875, 6.6953125,
                                   7.59375])
    assert a.x.offsets == _approx([0.40625, 0.3046875, 0.203125, 0.1015625, 0.0, 0.1015625, 0.203125, 0.3046875,
                                   0.40625])
    assert a.y == a.x and a.max_offset == pytest.approx(0.40625) and not a.aligned
    assert a.x.tokens_per_cell == pytest.approx(460 / 8 / 64)
    line = a.describe()
    assert line.startswith("8x8 grid on 512 x 512 px (26 px label margins) -> 8 x 8 image tokens of 64 px: "
                           "0.90 tokens per cell; columns and rows' borders at [0.41, 1.30, 2.20, 3.10, 4.00,")
    assert "up to 0.41 of a token (mean 0.23)" in line and "\n" not in line


def test_qwen2vl_448_and_504_px():
    # 448 px: 22 px margins, 50.5 px cells, 28 px tokens: (22 + 50.5 c) / 28
    a = cell_alignment(G8, (448, 448), 22, (16, 16))
    assert a.x.borders[:5] == _approx([22 / 28, 72.5 / 28, 123 / 28, 173.5 / 28, 8.0])
    assert a.x.offsets[:5] == _approx([6 / 28, 11.5 / 28, 11 / 28, 5.5 / 28, 0.0])
    assert a.max_offset == pytest.approx(11.5 / 28)  # 0.41
    # 504 px: 25 px margins, 56.75 px cells: (25 + 56.75 c) / 28, within 3 px of a token border everywhere
    b = cell_alignment(G8, (504, 504), 25, (18, 18))
    assert b.x.borders[:5] == _approx([25 / 28, 81.75 / 28, 138.5 / 28, 195.25 / 28, 9.0])
    assert b.max_offset == pytest.approx(3 / 28)  # 0.107
    assert b.x.tokens_per_cell == pytest.approx(56.75 / 28)


def test_tiny_base_256_px():
    # 13 px margins, 28.75 px cells, 32 px tokens: the same fractions as SmolVLM's (a 5% margin either way)
    a = cell_alignment(G8, (256, 256), 13, (8, 8))
    assert a.x.borders[:3] == _approx([13 / 32, 41.75 / 32, 70.5 / 32])
    assert a.max_offset == pytest.approx(0.40625)


def test_a_grid_of_whole_tokens_lines_up():
    # 6 x 6 cells of 32 px inside 32 px margins, one token per 32 px: every border on a token border
    a = cell_alignment(Grid(6, 6), (256, 256), 32, (8, 8))
    assert a.x.borders == _approx([1, 2, 3, 4, 5, 6, 7]) and a.aligned and a.max_offset == 0
    assert a.describe().endswith("every cell border lies on a token border (aligned)")


def test_a_non_square_image_squashed_onto_a_square_tile():
    # 512 x 384 px, 26 px margins, squared onto 8 x 8 tokens: rows at (26 + 41.5 c) * 8 / 384 = (26 + 41.5 c) / 48
    a = cell_alignment(G8, (512, 384), 26, (8, 8))
    assert a.y.borders[0] == pytest.approx(26 / 48) and a.y.borders[-1] == pytest.approx(358 / 48)
    assert a.y.offsets[0] == pytest.approx(1 - 26 / 48) and a.max_offset == pytest.approx(22 / 48)
    assert a.y.tokens_per_cell == pytest.approx(332 / 8 / 48)
    assert "columns' borders" in a.describe() and "rows' borders" in a.describe()


def test_the_margin_is_where_the_renderer_puts_the_table(small_dataset):
    assert [gma_margin(s) for s in (128, 256, 448, 504, 512)] == [8, 13, 22, 25, 26]
    im = Renderer.for_dataset(small_dataset, size=512).table(0, G8)
    assert im.size == (512, 512)
    margin_rgb = im.getpixel((0, 240))
    for x in (1, 25, 512 - 26, 511):  # label margin (y = 240: between the row labels and the row lines)
        assert im.getpixel((x, 240)) == margin_rgb, x
    for x in (31, 256 - 5, 512 - 31):  # the table
        assert im.getpixel((x, 240)) != margin_rgb, x


def _pixels(processor, image: Image.Image):
    return processor.image_processor(images=[image], return_tensors="pt")


def test_idefics3_tokens_match_the_processor():
    from degusta_learn.vlm.load import load_processor
    from transformers import AutoConfig

    folder = tiny_dir("idefics3")
    processor, config = load_processor(str(folder), "model.name"), AutoConfig.from_pretrained(folder)
    set_image_budget(processor, config, 64)
    unit = config.vision_config.patch_size * config.scale_factor  # 4 px patches, pixel shuffle 2: 8 px a token
    for size in ((128, 128), (128, 96)):
        pv = _pixels(processor, Image.new("RGB", size, "white"))["pixel_values"]  # (1, tiles, 3, H, W)
        assert pv.shape[1] == 1
        assert image_token_grid(processor, config, *size) == (pv.shape[-1] // unit, pv.shape[-2] // unit) == (8, 8)


def test_qwen2vl_tokens_match_the_processor():
    pytest.importorskip("torchvision")
    from degusta_learn.vlm.load import load_processor
    from transformers import AutoConfig

    folder = tiny_dir("qwen2vl")
    processor, config = load_processor(str(folder), "model.name"), AutoConfig.from_pretrained(folder)
    set_image_budget(processor, config, 504)
    for size, expect in (((504, 504), (18, 18)), ((448, 448), (18, 18)), ((600, 400), None)):
        thw = _pixels(processor, Image.new("RGB", size, "white"))["image_grid_thw"][0].tolist()  # patches of 14 px
        got = image_token_grid(processor, config, *size)
        assert got == (thw[2] // 2, thw[1] // 2)
        assert expect is None or got == expect


def test_fast_vlm_tokens_match_the_processor():
    from degusta_learn.vlm.load import load_processor
    from transformers import AutoConfig

    folder = shipped_model("tiny_vlm_base")
    processor, config = load_processor(str(folder), "model.name"), AutoConfig.from_pretrained(folder)
    set_image_budget(processor, config, 256)
    pv = _pixels(processor, Image.new("RGB", (300, 200), "white"))["pixel_values"]
    assert image_token_grid(processor, config, 300, 200) == (pv.shape[-1] // 32, pv.shape[-2] // 32) == (8, 8)


def test_check_grid_resolution_reports_alignment_only_with_a_render_size():
    from degusta_learn.vlm.load import load_processor
    from transformers import AutoConfig

    folder = tiny_dir("idefics3")
    processor, config = load_processor(str(folder), "model.name"), AutoConfig.from_pretrained(folder)
    set_image_budget(processor, config, 64)
    assert check_grid_resolution(processor, config, G8) is None
    a = check_grid_resolution(processor, config, G8, render_size=128)
    # 8 px margins, 14 px cells, 16 rendered px a token: (8 + 14 c) / 16
    assert a.x.borders[:5] == _approx([0.5, 1.375, 2.25, 3.125, 4.0]) and a.max_offset == pytest.approx(0.5)
    set_image_budget(processor, config, 32)  # 4 x 4 tokens: still refused, whatever the render size
    with pytest.raises(DegustaError, match=r"^model.image_size: images give the model 4 x 4 image tokens"):
        check_grid_resolution(processor, config, G8, render_size=128)


def test_the_finetune_dry_run_prints_the_alignment(tmp_path):
    data = save_dataset(dataset(), tmp_path / "data")
    out: list[str] = []
    run_train(CONFIGS / "finetune_tiny_cpu.yaml", [
        f"dataset={data}", f"model.name={tiny_dir('idefics3')}", f"trainer.run_dir={tmp_path / 'runs'}",
        "data.max_train_episodes=16", "data.render_size=128"], dry_run=True, log=out.append)
    line = next(x for x in "\n".join(out).splitlines() if x.strip().startswith("grid alignment"))
    assert "8x8 grid on 128 x 128 px (8 px label margins) -> 8 x 8 image tokens of 16 px: 0.88 tokens per cell" in line
    assert "off by [0.50, 0.38, 0.25, 0.12, 0.00, 0.12, 0.25, 0.38, 0.50]: up to 0.50 of a token" in line
