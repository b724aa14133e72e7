"""Command-line flags: out-of-range numbers and unknown verbs are one `degusta: error:` line and exit 2,
before anything runs; an error that quotes a key pasted into a config is redacted."""

from pathlib import Path

import pytest

from degusta_learn.cli import main


@pytest.mark.parametrize("argv, names", [
    (["data", "generate", "naturalistic", "--out", "x", "--seed", "-1"], "--seed"),
    (["data", "generate", "naturalistic", "--out", "x", "--seed", "99999999999999999999999999"], "--seed"),
    (["data", "episodes", "d", "--context", "2", "--out", "e.jsonl", "--seed", "banana"], "--seed"),
    (["evaluate", "--dataset", "d", "--predictions", "p", "--out", "o", "--bootstrap", "100000000000"], "--bootstrap"),
    (["evaluate", "--dataset", "d", "--predictions", "p", "--out", "o", "--bootstrap", "0"], "--bootstrap"),
    (["evaluate", "--dataset", "d", "--predictions", "p", "--out", "o", "--seed", "-1"], "--seed"),
    (["render", "catalog", "d", "--out", "c.png", "--size", "100000"], "--size"),
    (["render", "episode", "d", "--participant", "p000", "--target", "-3", "--context", "2", "--method", "mogma",
      "--out", "o"], "--target"),
    (["predict"], "--config"),
    (["bogus"], "verb"),
    # an empty --out was the current folder: evaluate replaced a report.md there
    (["evaluate", "--dataset", "d", "--predictions", "p", "--out", ""], "--out: an empty path"),
    (["render", "episode", "d", "--participant", "p000", "--target", "0", "--context", "2", "--method", "mogma",
      "--out", " "], "--out: an empty path"),
    (["data", "generate", "naturalistic", "--out", ""], "--out: an empty path"),
])
def test_bad_flags_are_one_line_and_exit_2(argv, names, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("degusta: error: ") and names in err[0]
    assert list(tmp_path.iterdir()) == []  # nothing ran, nothing written


def test_help_is_not_an_error(capsys):
    assert main(["--help"]) == 0
    assert "usage: degusta" in capsys.readouterr().out


def test_an_error_quoting_a_pasted_key_is_redacted(tmp_path, capsys, small_dataset_dir):
    zeroshot = Path(__file__).resolve().parents[1] / "configs" / "zeroshot_mogma_gpt4o.yaml"
    key = "sk-proj-abcdef1234567890"
    code = main(["predict", "--config", str(zeroshot), "--set", f"backend.api_key_env={key}",
                 "--set", f"dataset={small_dataset_dir}", "--set", f"out={tmp_path / 'p.jsonl'}"])
    err = capsys.readouterr().err
    assert code == 2 and key not in err and "***" in err
