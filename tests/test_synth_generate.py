"""generate_dataset: files, byte-identical determinism, load round trip, refusing to overwrite, atomicity."""

import hashlib
import json

import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.scene import load_dataset, read_episodes
from degusta_learn.synth import STYLES_FILE, generate_dataset, read_styles, simulated_with_styles
from degusta_learn.synth import generate as generate_module


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def test_simulated_folder_is_complete_deterministic_and_loads(tmp_path):
    a = generate_dataset("simulated", tmp_path / "a", seed=3)
    b = generate_dataset("simulated", tmp_path / "b", seed=3)
    c = generate_dataset("simulated", tmp_path / "c", seed=4)
    assert set(_digest(a)) == {"catalog.json", "tables.json", "arrangements.jsonl", "meta.json", STYLES_FILE,
                               "episodes.jsonl"}
    assert _digest(a) == _digest(b)  # byte-identical
    assert _digest(a)["arrangements.jsonl"] != _digest(c)["arrangements.jsonl"]
    meta = json.loads((a / "meta.json").read_text())
    assert meta["name"] == "simulated" and meta["synthetic"] is True and meta["seed"] == 3
    assert meta["generator"] == "degusta_learn.synth.simulated" and meta["description"]
    ds = load_dataset(a)  # load_dataset(save) round trip
    mem, styles, episodes = simulated_with_styles(3)
    assert [x.to_json() for x in ds.arrangements] == [x.to_json() for x in mem.arrangements]
    assert ds.label == "simulated (SYNTHETIC data)"
    assert read_episodes(a / "episodes.jsonl", ds) == episodes
    assert list(read_styles(a / STYLES_FILE).values()) == styles
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders left


@pytest.mark.slow  # two full generations: ~3 s on a free core
def test_naturalistic_files_are_byte_identical(tmp_path):
    a = generate_dataset("naturalistic", tmp_path / "a")
    b = generate_dataset("naturalistic", tmp_path / "b")
    assert _digest(a) == _digest(b)
    ds = load_dataset(a)
    assert len(ds.arrangements) == 995 and len(ds.ratings) == 995 and ds.synthetic
    assert json.loads((a / "meta.json").read_text())["name"] == "naturalistic"


def test_refuses_non_empty_folder_unless_overwrite(tmp_path):
    out = tmp_path / "data"
    out.mkdir()
    generate_dataset("simulated", out)  # an existing empty folder is fine
    before = _digest(out)
    with pytest.raises(DegustaError, match=str(out)):
        generate_dataset("simulated", out, seed=1)
    assert _digest(out) == before
    generate_dataset("simulated", out, seed=1, overwrite=True)
    assert _digest(out)["arrangements.jsonl"] != before["arrangements.jsonl"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(DegustaError, match="not a folder"):
        generate_dataset("simulated", tmp_path / "file")
    with pytest.raises(DegustaError, match="unknown dataset"):
        generate_dataset("bogus", tmp_path / "x")


def test_failure_leaves_nothing_behind(tmp_path, monkeypatch):
    out = tmp_path / "data"
    generate_dataset("simulated", out)
    before = _digest(out)

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(generate_module, "write_styles", boom)
    with pytest.raises(RuntimeError):
        generate_dataset("simulated", out, overwrite=True)
    assert _digest(out) == before  # the old dataset is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no temp folder left


def test_cli_generate(tmp_path, capsys):
    assert main(["data", "generate", "simulated", "--out", str(tmp_path / "s")]) == 0
    assert "SYNTHETIC" in capsys.readouterr().out
    assert main(["data", "generate", "simulated", "--out", str(tmp_path / "s")]) == 2
    assert "not empty" in capsys.readouterr().err
