"""Exit codes a script can trust: 0 ok, 2 a user error, 3 it ran and wrote its output but something it reports failed
(a compare / quickstart method, a dry-run check on this machine), 130 interrupted; `degusta --version`.

The dry-run cases (train --dry-run of a GPU config on a CPU machine: exit 3) are in tests/test_train_dry_run.py."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import degusta_learn
from degusta_learn.cli import ExitCode, main
from degusta_learn.evaluate.compare import Comparison
from degusta_learn.scene import Prediction, load_dataset, make_episodes, write_episodes, write_predictions

ROOT = Path(__file__).parent.parent


@pytest.fixture
def world(small_dataset_dir, tmp_path):
    """A compare config writer over one episode set, with a perfect predictions file and two broken methods:
    a predict config naming an unknown method, and a predictions file whose every prediction failed."""
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    write_predictions(tmp_path / "good.jsonl", [Prediction(e.id, e.participant, e.target, "good",
                                                           list(ds.arrangement(e.participant, e.target).placements))
                                                for e in eps])
    write_predictions(tmp_path / "all_failed.jsonl", [Prediction(e.id, e.participant, e.target, "x", [], True)
                                                      for e in eps])
    (tmp_path / "nope.yaml").write_text(f"method: nope\ndataset: {small_dataset_dir}\nout: {tmp_path / 'n.jsonl'}\n")
    methods = {"good": {"name": "good", "predictions": str(tmp_path / "good.jsonl")},
               "broken": {"name": "broken", "config": str(tmp_path / "nope.yaml")},
               "hopeless": {"name": "hopeless", "predictions": str(tmp_path / "all_failed.jsonl")}}

    def config(*names: str) -> Path:
        path = tmp_path / "cmp.yaml"
        lines = [f"dataset: {small_dataset_dir}", f"out: {tmp_path / 'cmp'}", f"episodes: {tmp_path / 'eps.jsonl'}",
                 "n_bootstrap: 20", "qualitative: 0", "render_size: 64", "methods:"]
        path.write_text("\n".join(lines + [f"  - {json.dumps(methods[n])}" for n in names]) + "\n")
        return path

    return config, tmp_path / "cmp"


def test_compare_with_failed_methods_exits_3_with_the_report_written(world, capsys):
    config, out = world
    assert main(["compare", "--config", str(config("good", "broken", "hopeless"))]) == ExitCode.PARTIAL == 3
    stdout, err = capsys.readouterr()
    assert f"wrote the comparison report to {out / 'report.md'}" in stdout
    assert err == f"degusta: 2 of 3 methods failed: broken, hopeless; the report lists why and scores the rest: " \
                  f"{out / 'report.md'}\n"
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["methods"]) == {"good"} and set(metrics["failed_methods"]) == {"broken", "hopeless"}
    report = (out / "report.md").read_text()
    assert "unknown method 'nope'" in report and "every one of its" in report


def test_compare_exit_codes_from_a_real_process(world):
    """What a shell script sees: `python -m degusta_learn.cli compare` exits 3, 0 or 2."""
    config, out = world

    def compare(*names):
        return subprocess.run([sys.executable, "-m", "degusta_learn.cli", "compare", "--config", str(config(*names))],
                              capture_output=True, text=True, timeout=600)

    partial = compare("good", "broken")
    assert partial.returncode == 3, partial.stdout + partial.stderr
    assert partial.stderr.startswith("degusta: 1 of 2 methods failed: broken;") and partial.stderr.count("\n") == 1
    assert (out / "report.md").is_file() and "unknown method 'nope'" in (out / "report.md").read_text()
    ok = compare("good")
    assert ok.returncode == 0 and ok.stderr == "", ok.stderr
    assert json.loads((out / "metrics.json").read_text())["failed_methods"] == {}
    before = (out / "report.md").read_bytes()
    none = compare("broken", "hopeless")  # every method failed: an error, no report written
    assert none.returncode == 2 and none.stderr.startswith("degusta: error: every method failed"), none.stderr
    assert (out / "report.md").read_bytes() == before


def test_compare_all_ok_exits_0_and_every_method_failed_exits_2(world, capsys):
    config, out = world
    assert main(["compare", "--config", str(config("good"))]) == ExitCode.OK
    assert capsys.readouterr().err == ""
    before = (out / "report.md").read_bytes()
    assert main(["compare", "--config", str(config("broken", "hopeless"))]) == ExitCode.USER_ERROR
    err = capsys.readouterr().err
    assert err.startswith("degusta: error: every method failed, so no report was written") and err.count("\n") == 1
    assert (out / "report.md").read_bytes() == before


def test_quickstart_with_a_failed_method_exits_3(tmp_path, capsys, monkeypatch):
    """quickstart ends in compare: its failed methods give the same exit 3 and one line naming them."""
    from degusta_learn import quickstart

    report = tmp_path / "qs" / "report"
    result = {"value": Comparison(report, {"tiny_base_finetuned": "every one of its 12 predictions failed"}, 8)}
    monkeypatch.setattr(quickstart, "run_quickstart", lambda out, small, with_api: result["value"])
    assert main(["quickstart", "--out", str(tmp_path / "qs"), "--small"]) == 3
    out, err = capsys.readouterr()
    assert f"quickstart finished: open {report / 'report.md'}" in out
    assert err.startswith("degusta: 1 of 8 methods failed: tiny_base_finetuned;") and err.count("\n") == 1
    result["value"] = Comparison(report, {}, 8)
    assert main(["quickstart", "--out", str(tmp_path / "qs"), "--small"]) == 0
    assert capsys.readouterr().err == ""


def test_version_prints_the_package_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"degusta {degusta_learn.__version__}\n"
    done = subprocess.run([sys.executable, "-m", "degusta_learn.cli", "--version"], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and done.stdout == f"degusta {degusta_learn.__version__}\n", done.stderr
    # the version the code reports is the one the package is built with
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1) == degusta_learn.__version__


def test_every_exit_code_is_documented():
    docs = (ROOT / "docs" / "reliability.md").read_text()
    table = docs[docs.index("## Exit codes"):]
    cli_doc = sys.modules["degusta_learn.cli"].__doc__
    for code in ExitCode:
        assert re.search(rf"^\| {code.value} \|", table, re.M), code
        assert re.search(rf"^    {code.value} ", cli_doc, re.M), code


def test_sigterm_is_handled_as_an_interrupt_with_status_143(tmp_path):
    """A real process killed by SIGTERM mid-run (a scheduler, `timeout`): one line, exit 128 + 15."""
    import signal
    import time

    code = ("import sys, time; import degusta_learn.cli as c\n"
            "def slow(args):\n    print('started', flush=True); time.sleep(60)\n"
            "c.cmd_configs_list = slow\nsys.exit(c.main(['configs', 'list']))\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    assert proc.stdout.readline().strip() == "started"
    proc.send_signal(signal.SIGTERM)
    start = time.monotonic()
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGTERM == 143 and time.monotonic() - start < 30
    assert err.strip() == "degusta: terminated (SIGTERM); finished work is kept (re-run to resume)"
