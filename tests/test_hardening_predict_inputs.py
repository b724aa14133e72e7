"""Predict inputs a hostile-input audit found unguarded: each is one line naming the key, file or line, and
nothing at `out` is replaced (a device or pipe there stays what it was)."""

from __future__ import annotations

import json
import os
import stat

import pytest
from conftest import make_small_dataset

from degusta_learn.cli import main as cli_main
from degusta_learn.scene import save_dataset


@pytest.fixture
def data(tmp_path):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path / "data")


def predict(capsys, *sets, config="baseline_population_mean"):
    code = cli_main(["predict", "--config", config, *[a for s in sets for a in ("--set", s)]])
    err = capsys.readouterr().err
    return code, err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("degusta: error: ") and "Traceback" not in err, err
    return lines[0]


def test_out_that_is_a_pipe_is_refused_and_left_a_pipe(data, tmp_path, capsys):
    """predict used to rename its output over whatever was at `out` (/dev/full became a regular file)."""
    fifo = tmp_path / "fifo.jsonl"
    os.mkfifo(fifo)
    code, err = predict(capsys, f"dataset={data}", f"out={fifo}", "split=all", "context=2")
    assert code == 2 and "is not a regular file" in one_line(err) and "out" in err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


@pytest.mark.parametrize("diagnostics", [5, "x", [1, 2]])
def test_a_replay_file_whose_diagnostics_is_not_an_object(data, tmp_path, capsys, diagnostics):
    """Was AttributeError: 'int' object has no attribute 'get'."""
    answers = tmp_path / "answers.jsonl"
    answers.write_text(json.dumps({"episode": "p000/t0/k2", "diagnostics": diagnostics}) + "\n")
    code, err = predict(capsys, f"dataset={data}", f"out={tmp_path / 'p.jsonl'}", "split=all", "context=2",
                        "method=mogma", "render_size=64", f"backend={{name: replay, path: {answers}}}",
                        "model.name=replay",
                        config="zeroshot_mogma_gpt4o")
    assert code == 2 and f"{answers}:1: diagnostics: expected an object" in one_line(err)
    assert not (tmp_path / "p.jsonl").exists()


@pytest.mark.parametrize("size", ["32768", "-64", "0"])
def test_model_image_size_is_bounded(data, tmp_path, capsys, size):
    """32768 tried to allocate gigabytes; -64 gave '-2 x -2 image tokens'; 0 was silently the default."""
    code, err = predict(capsys, f"dataset={data}", f"out={tmp_path / 'p.jsonl'}", f"model.image_size={size}",
                        config="predict_hf_base_zeroshot")
    assert code == 2 and "model.image_size: expected a value from 16 to 4,096" in one_line(err)


@pytest.mark.parametrize("backend", ["hf", "anthropic", "gemini"])
def test_a_backend_without_a_model_says_the_model_is_required(data, tmp_path, capsys, backend):
    """An hf section without `model` used to look for a local model called 'gpt-4o' (the openai default)."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"method: mogma\ndataset: {data}\nout: {tmp_path / 'p.jsonl'}\nsplit: all\ncontext: 2\n"
                   f"render_size: 64\nbackend: {{name: {backend}}}\n")
    code, err = predict(capsys, config=str(cfg))
    assert code == 2 and f"model.name: required for the {backend} backend" in one_line(err)
    code, err = predict(capsys, "dry_run=true", config=str(cfg))
    assert code == 2 and "model.name: required" in one_line(err)


def test_an_unknown_split_names_the_config_and_key(data, tmp_path, capsys):
    code, err = predict(capsys, f"dataset={data}", f"out={tmp_path / 'p.jsonl'}", "split=foo")
    assert code == 2 and "baseline_population_mean.yaml: split: expected one of" in one_line(err)


@pytest.mark.parametrize("url", ["notaurl", "ftp://x", "http://", "file:///etc/passwd"])
def test_a_base_url_that_is_not_http_is_refused(data, tmp_path, capsys, url):
    """It reached the client, which retried 'Connection error.' before the run stopped."""
    code, err = predict(capsys, f"dataset={data}", f"out={tmp_path / 'p.jsonl'}", f"backend.base_url={url}",
                        "dry_run=true", config="zeroshot_mogma_gpt4o")
    assert code == 2 and "backend.base_url: expected an http(s) URL" in one_line(err)


def test_an_out_ending_in_a_slash_is_refused(data, tmp_path, capsys):
    """out=newdir/ wrote a file called newdir."""
    code, err = predict(capsys, f"dataset={data}", f"out={tmp_path / 'newdir'}/", "split=all", "context=2")
    assert code == 2 and "ends in a slash" in one_line(err)
    assert not (tmp_path / "newdir").exists()
