"""`degusta render episode|catalog`: the files written, their content, and one-line errors."""

from __future__ import annotations

from PIL import Image

from degusta_learn.cli import main
from degusta_learn.scene import load_dataset, make_episodes


def _run(*argv) -> int:
    return main([str(a) for a in argv])


def test_render_episode_mogma_writes_the_image_set(small_dataset_dir, tmp_path):
    out = tmp_path / "ep"
    rc = _run("render", "episode", small_dataset_dir, "--participant", "p001", "--target", 2, "--context", 2,
              "--method", "mogma", "--out", out, "--size", 128, "--grid", 6)
    assert rc == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["final_state_1.png", "final_state_2.png", "initial_state_1.png", "objects_cup.png",
                     "objects_fork.png", "objects_knife.png", "objects_plate.png", "objects_spoon.png", "order.txt"]
    assert Image.open(out / "final_state_1.png").size == (128, 128)
    # the context is the one make_episodes picks (what predict sees), in order, one line per image
    ds = load_dataset(small_dataset_dir)
    ep = next(e for e in make_episodes(ds, 2, "all", 0) if e.participant == "p001" and e.target == 2)
    lines = (out / "order.txt").read_text().splitlines()
    for k, (trial, line) in enumerate(zip(ep.context, lines), start=1):
        types = [ds.catalog[p.object].type for p in ds.arrangement("p001", trial).placements]
        assert line == f"Placement order in final_state_{k}.png: {', '.join(types)}."
    assert len(lines) == 2


def test_render_episode_louma_writes_oal_and_no_sheets(small_dataset_dir, tmp_path):
    out = tmp_path / "ep"
    assert _run("render", "episode", small_dataset_dir, "--participant", "p000", "--target", 0, "--context", 0,
                "--method", "louma", "--out", out, "--size", 96) == 0
    assert sorted(p.name for p in out.iterdir()) == ["initial_state_1.png", "objects.json"]


def test_render_errors_are_one_line(small_dataset_dir, tmp_path, capsys):
    out = tmp_path / "ep"
    assert _run("render", "episode", small_dataset_dir, "--participant", "nobody", "--target", 0, "--context", 2,
                "--method", "logma", "--out", out) == 2
    assert "participant 'nobody'" in capsys.readouterr().err
    assert _run("render", "episode", small_dataset_dir, "--participant", "p000", "--target", 0, "--context", 2,
                "--method", "logma", "--out", out, "--grid", 0) == 2
    assert "--grid" in capsys.readouterr().err  # refused by the flag parser, before anything runs
    assert not out.exists()  # nothing half-written


def test_render_catalog(small_dataset_dir, tmp_path):
    out = tmp_path / "catalog.png"
    assert _run("render", "catalog", small_dataset_dir, "--out", out, "--size", 128) == 0
    im = Image.open(out)
    assert im.format == "PNG" and im.size[0] >= 3 * 128 and im.size[1] >= 2 * 128
