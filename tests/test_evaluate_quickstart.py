"""The main job end to end at a reduced size: every method, one report, every linked file present."""

import json
import re

import pytest

from degusta_learn.cli import main


@pytest.mark.slow
def test_quickstart_small_end_to_end(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    assert main(["quickstart", "--out", str(tmp_path / "qs"), "--small"]) == 0
    out = capsys.readouterr().out
    report = tmp_path / "qs" / "report"
    assert out.strip().splitlines()[-1].endswith(f"{report / 'report.html'} in a browser)")
    assert "export OPENAI_API_KEY" in out
    metrics = json.loads((report / "metrics.json").read_text())
    assert set(metrics["methods"]) == {"random", "population_mean", "copy_nearest", "consensus", "oracle", "learned",
                                       "tiny_vlm_zeroshot", "tiny_vlm_finetuned"}
    assert not metrics["failed_methods"]
    text = (report / "report.md").read_text()
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        assert (report / link).is_file(), link
    # Every config it ran is written beside the results, so each step can be re-run by hand.
    assert {p.name for p in (tmp_path / "qs" / "configs").glob("*.yaml")} >= {"learned_cpu.yaml", "finetune_tiny_cpu.yaml"}
