"""Output paths (red-team items 1-5): an `out` that cannot be written, or that is one of the command's inputs
(a dataset file, the config, the episodes, the response cache, the ledger, a predictions file), a user's
text file given to `render catalog`, a user's own ledger.json, and an unsafe `method` name in a predictions
file.

Every case runs the CLI (`degusta_learn.cli.main`) and asserts: exit status 2, one line
`degusta: error: ...` naming the path or key, the endangered file byte-identical afterwards, and no
temporary file left behind. The guards are `files.atomic.atomic_open`, `files.guard.check_output_file` /
`refuse_overwriting_inputs` and `files.guard.refuse_replacing_inputs`, shared by every command that writes.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import yaml
from conftest import make_small_dataset
from test_hardening_prompting import Server
from test_hardening_prompting import config as zeroshot_config

from degusta_learn.cli import main
from degusta_learn.scene import save_dataset


@pytest.fixture(scope="module")
def ds_dir(tmp_path_factory):
    return save_dataset(make_small_dataset(n_participants=5, n_trials=4), tmp_path_factory.mktemp("ds") / "data")


def snapshot(*folders):
    """Every file under the folders (and their hidden temp files) with its bytes."""
    out = {}
    for folder in folders:
        if os.path.isfile(folder):
            out[str(folder)] = Path(folder).read_bytes()
            continue
        for root, _, files in os.walk(folder):
            for f in files:
                p = os.path.join(root, f)
                out[p] = Path(p).read_bytes()
    return out


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2, (code, out, err)
    assert len(lines) == 1 and lines[0].startswith("degusta: error: ") and "Traceback" not in err, err
    return lines[0]


def predict_config(tmp_path, ds_dir, **extra):
    cfg = {"method": "random", "dataset": str(ds_dir), "out": str(tmp_path / "p.jsonl"), "context": 2,
           "split": "all", **extra}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def no_temp_files(*folders):
    for folder in folders:
        for root, dirs, files in os.walk(folder):
            assert not [n for n in files + dirs if n.endswith(".tmp")], (root, files, dirs)


# ----------------------------------------------------------------------------- item 1: unwritable outputs

UNWRITABLE = {  # name -> (out relative to tmp_path or absolute, words the message must hold)
    "a folder": ("folder", "is a folder"),
    "under a file": ("notes.txt/x.jsonl", "a parent"),
    "/proc": ("/proc/degusta_x.jsonl", "cannot write here"),
    "empty": ("", "empty"),
}


@pytest.mark.parametrize("case", list(UNWRITABLE))
def test_predict_out_that_cannot_be_written(case, tmp_path, ds_dir, capsys):
    out, words = UNWRITABLE[case]
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder" / "keep.txt").write_text("mine\n")
    (tmp_path / "notes.txt").write_text("my notes\n")
    cfg = predict_config(tmp_path, ds_dir)
    target = out if out.startswith("/") or not out else str(tmp_path / out)
    before = snapshot(tmp_path, ds_dir)
    line = run(capsys, "predict", "--config", cfg, "--set", f"out={target}")
    assert "out: " in line and words in line and (target in line or not target), line
    assert snapshot(tmp_path, ds_dir) == before
    no_temp_files(tmp_path)


@pytest.mark.parametrize("case", ["a folder", "under a file", "/proc", "empty"])
def test_data_episodes_out_that_cannot_be_written(case, tmp_path, ds_dir, capsys):
    out, words = UNWRITABLE[case]
    (tmp_path / "folder").mkdir()
    (tmp_path / "notes.txt").write_text("my notes\n")
    target = out if out.startswith("/") or not out else str(tmp_path / out)
    before = snapshot(tmp_path, ds_dir)
    line = run(capsys, "data", "episodes", ds_dir, "--context", "2", "--out", target)
    assert "--out: " in line and words in line, line
    assert snapshot(tmp_path, ds_dir) == before
    no_temp_files(tmp_path)


def test_compare_out_under_a_file(tmp_path, ds_dir, capsys):
    (tmp_path / "notes.txt").write_text("my notes\n")
    pcfg = predict_config(tmp_path, ds_dir)
    cmp = tmp_path / "cmp.yaml"
    cmp.write_text(yaml.safe_dump({"dataset": str(ds_dir), "out": str(tmp_path / "notes.txt" / "x"),
                                   "contexts": [2], "split": "all", "n_bootstrap": 10, "qualitative": 0,
                                   "methods": [{"name": "random", "config": str(pcfg)}]}))
    before = snapshot(tmp_path, ds_dir)
    line = run(capsys, "compare", "--config", cmp)
    assert "notes.txt" in line and "a parent" in line and "is a file" in line, line
    assert snapshot(tmp_path, ds_dir) == before


# ----------------------------------------------------------------------------- item 2: outputs that are inputs

def test_predict_never_replaces_a_dataset_file_the_config_or_the_episodes(tmp_path, ds_dir, capsys):
    cfg = predict_config(tmp_path, ds_dir)
    assert main(["data", "episodes", str(ds_dir), "--context", "2", "--split", "all",
                 "--out", str(tmp_path / "eps.jsonl")]) == 0
    capsys.readouterr()
    before = snapshot(tmp_path, ds_dir)
    for out, words in [(ds_dir / "arrangements.jsonl", "dataset file arrangements.jsonl"),
                       (ds_dir / "meta.json", "dataset file meta.json"),
                       (cfg, "is the config file"),
                       (tmp_path / "eps.jsonl", "config key 'episodes'")]:
        line = run(capsys, "predict", "--config", cfg, "--set", f"episodes={tmp_path / 'eps.jsonl'}",
                   "--set", f"out={out}")
        assert f"out: {out}" in line and words in line, line
        assert snapshot(tmp_path, ds_dir) == before
    # a new file beside the dataset's files is fine
    assert main(["predict", "--config", str(cfg), "--set", f"out={ds_dir / 'preds.jsonl'}"]) == 0
    os.unlink(ds_dir / "preds.jsonl")


def test_data_episodes_never_replaces_a_dataset_file(tmp_path, ds_dir, capsys):
    before = snapshot(ds_dir)
    for name in ("arrangements.jsonl", "catalog.json", "tables.json", "meta.json"):
        line = run(capsys, "data", "episodes", ds_dir, "--context", "2", "--out", ds_dir / name)
        assert f"--out: {ds_dir / name}" in line and "dataset" in line, line
    assert snapshot(ds_dir) == before


def test_evaluate_never_replaces_its_predictions(tmp_path, ds_dir, capsys):
    cfg = predict_config(tmp_path, ds_dir, out=str(tmp_path / "runs" / "metrics.json"))
    assert main(["predict", "--config", str(cfg)]) == 0
    capsys.readouterr()
    before = snapshot(tmp_path)
    line = run(capsys, "evaluate", "--dataset", ds_dir, "--predictions", tmp_path / "runs" / "metrics.json",
               "--out", tmp_path / "runs")
    assert "--out: " in line and "metrics.json is a predictions file" in line, line
    assert snapshot(tmp_path) == before


def test_compare_never_replaces_an_input(tmp_path, ds_dir, capsys):
    pcfg = predict_config(tmp_path, ds_dir, out=str(tmp_path / "cmp" / "report.md"))
    assert main(["predict", "--config", str(pcfg)]) == 0
    capsys.readouterr()
    cmp = tmp_path / "cmp.yaml"
    cmp.write_text(yaml.safe_dump({"dataset": str(ds_dir), "out": str(tmp_path / "cmp"), "contexts": [2],
                                   "split": "all", "n_bootstrap": 10, "qualitative": 0,
                                   "methods": [{"name": "random", "predictions": str(tmp_path / "cmp" / "report.md")}]}))
    before = snapshot(tmp_path)
    line = run(capsys, "compare", "--config", cmp)
    assert "report.md is the predictions file of method 'random'" in line, line
    assert snapshot(tmp_path) == before


@pytest.fixture
def server():
    s = Server()
    yield s
    s.close()


def test_zeroshot_out_is_never_the_cache_or_the_ledger(tmp_path, ds_dir, server, capsys):
    cfg = zeroshot_config(tmp_path, server.url, ds_dir)
    (tmp_path / "z").mkdir()
    cache = tmp_path / "z" / "responses_cache.sqlite"
    for sets, words in [([f"out={cache}"], "is the response cache"),
                        ([f"out={tmp_path / 'z' / 'x.sqlite'}", f"cache={tmp_path / 'z' / 'x.sqlite'}"],
                         "is the response cache"),
                        ([f"out={tmp_path / 'z' / 'ledger.json'}"], "is the ledger.json"),
                        ([f"out={tmp_path / 'z' / 'p.jsonl'}", f"cache={tmp_path / 'z' / 'ledger.json'}"],
                         "cache: ")]:
        before = snapshot(tmp_path)
        line = run(capsys, "predict", "--config", cfg, *[a for s in sets for a in ("--set", s)])
        assert words in line, line
        assert snapshot(tmp_path) == before
    assert server.requests == []
    # an existing cache with out == the cache: refused, the paid answers kept byte for byte
    assert main(["predict", "--config", str(cfg), "--set", f"out={tmp_path / 'z' / 'p.jsonl'}"]) == 0
    capsys.readouterr()
    asked = len(server.requests)
    before = snapshot(tmp_path)
    line = run(capsys, "predict", "--config", cfg, "--set", f"out={cache}")
    assert f"out: {cache} is the response cache" in line, line
    assert snapshot(tmp_path) == before and len(server.requests) == asked


# ----------------------------------------------------------------------------- item 3: render catalog

def test_render_catalog_writes_only_png(tmp_path, ds_dir, capsys):
    (tmp_path / "note2.txt").write_text("my note\n")
    (tmp_path / "fake.png").write_text("not a picture\n")
    before = snapshot(tmp_path, ds_dir)
    for out, words in [(ds_dir / "catalog.json", "ending in .png"), (tmp_path / "note2.txt", "ending in .png"),
                       (tmp_path / "fake.png", "is not a PNG image"), (tmp_path / "noext", "ending in .png")]:
        line = run(capsys, "render", "catalog", ds_dir, "--out", out, "--size", "64")
        assert str(out) in line and words in line, line
        assert snapshot(tmp_path, ds_dir) == before
    # a PNG (an earlier contact sheet) is replaced
    assert main(["render", "catalog", str(ds_dir), "--out", str(tmp_path / "cat.png"), "--size", "64"]) == 0
    assert main(["render", "catalog", str(ds_dir), "--out", str(tmp_path / "cat.png"), "--size", "64"]) == 0
    assert (tmp_path / "cat.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    no_temp_files(tmp_path)


def test_render_episode_never_replaces_a_dataset_picture(tmp_path, capsys):
    ds = save_dataset(make_small_dataset(n_participants=5, n_trials=4), tmp_path / "d")
    (ds / "pictures").mkdir()
    shutil.copy(ds / "catalog.json", ds / "pictures" / "order.txt")  # a file of the dataset, named as render writes
    before = snapshot(ds)
    line = run(capsys, "render", "episode", ds, "--participant", "p000", "--target", "0", "--context", "2",
               "--method", "logma", "--size", "64", "--out", ds / "pictures")
    assert "order.txt" in line and "a file of the dataset" in line, line
    assert snapshot(ds) == before


# ----------------------------------------------------------------------------- item 4: a user's ledger.json

def test_a_users_ledger_json_is_never_replaced(tmp_path, ds_dir, server, capsys):
    cfg = zeroshot_config(tmp_path, server.url, ds_dir)
    (tmp_path / "ud").mkdir()
    (tmp_path / "ud" / "ledger.json").write_text('{"my": "own ledger notes"}\n')
    before = snapshot(tmp_path)
    line = run(capsys, "predict", "--config", cfg, "--set", f"out={tmp_path / 'ud' / 'p.jsonl'}")
    assert f"{tmp_path / 'ud' / 'ledger.json'}: exists and is not a ledger degusta wrote" in line, line
    assert snapshot(tmp_path) == before and server.requests == []
    # our own ledger (marked) is replaced by the next run
    assert main(["predict", "--config", str(cfg)]) == 0
    ledger = json.loads((tmp_path / "run" / "ledger.json").read_text())
    assert ledger["kind"] == "degusta zero-shot ledger"
    assert main(["predict", "--config", str(cfg)]) == 0


# ----------------------------------------------------------------------------- item 5: method names

@pytest.mark.parametrize("method", ["a/../../b\n<script>", "../../escaped", "", ".hidden", "x" * 81, "a b"])
def test_unsafe_method_names_in_predictions_are_refused(method, tmp_path, ds_dir, capsys):
    cfg = predict_config(tmp_path, ds_dir)
    assert main(["predict", "--config", str(cfg)]) == 0
    capsys.readouterr()
    rows = [json.loads(x) for x in (tmp_path / "p.jsonl").read_text().splitlines()]
    (tmp_path / "p.jsonl").write_text("".join(json.dumps({**r, "method": method}) + "\n" for r in rows))
    before = snapshot(tmp_path)
    line = run(capsys, "evaluate", "--dataset", ds_dir, "--predictions", tmp_path / "p.jsonl",
               "--out", tmp_path / "eval")
    assert f"{tmp_path / 'p.jsonl'}:1: field 'method': " in line, line
    assert "not a safe method name" in line or "must be printable" in line or not method, line  # the reader: '', a newline
    assert snapshot(tmp_path) == before and not (tmp_path / "eval").exists()
