"""Issue 12, items 7 and 8: predictions that lie, stale outputs, folders written whole or not at all.

Every case runs the CLI (`degusta_learn.cli.main`) and asserts the user-facing outcome: the exit code, the
one-line message (file, line, field), the output folder byte-for-byte untouched, no temp folder left.
"""

from __future__ import annotations

import json
import os
import pathlib

import pytest

from degusta_learn.cli import main
from degusta_learn.evaluate import plots as plots_module
from degusta_learn.evaluate import report as report_module
from degusta_learn.files import folders as outdir
from degusta_learn.scene import Prediction, load_dataset, make_episodes, write_episodes, write_predictions
from degusta_learn.synth import generate as generate_module

DEAD_PID = 2 ** 22 + 12345  # above Linux's default pid_max: never a live process


def snapshot(root: pathlib.Path) -> dict:
    """Every file and folder under `root` with its bytes (None for folders)."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def leftovers(folder: pathlib.Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp"))


def run(capsys, *argv) -> tuple[int, str]:
    capsys.readouterr()
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("degusta: error: "), err
    assert "Traceback" not in err
    return code, err


def perfect(ds, episodes, method="m"):
    return [Prediction(e.id, e.participant, e.target, method, list(ds.arrangement(e.participant, e.target).placements))
            for e in episodes]


@pytest.fixture
def world(small_dataset_dir, tmp_path):
    """A dataset, 10 episodes (context 2), a good predictions file and a previous evaluation folder."""
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")[:10]
    write_episodes(tmp_path / "eps.jsonl", eps)
    write_predictions(tmp_path / "good.jsonl", perfect(ds, eps))
    out = tmp_path / "eval"
    assert main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(tmp_path / "good.jsonl"),
                 "--out", str(out), "--bootstrap", "20"]) == 0
    return ds, eps, out


def _evaluate(capsys, dataset, preds_path, out, *extra):
    return run(capsys, "evaluate", "--dataset", dataset, "--predictions", preds_path, "--out", out,
               "--bootstrap", "20", *extra)


# --- item 7: predictions that lie -------------------------------------------------------------------------

def _lie(ds, eps, how):
    preds = perfect(ds, eps)
    p, e = preds[2], eps[2]
    if how == "participant":
        p.participant = next(x for x in ds.participants if x != e.participant)
    elif how == "target_is_context":
        p.target = e.context[0]  # the method was shown this arrangement
    elif how == "other_target":
        p.target = next(t.trial for t in ds.trials_of(e.participant) if t.trial not in (e.target, *e.context))
    elif how == "method":
        p.method, preds[5].method = "mm", "mm"  # a misspelt name on some lines
    elif how == "claimed_context":
        p.diagnostics = {"context": [e.target]}
    elif how == "custom_id":
        p.episode = "my-episode-7"
    elif how == "no_such_trial":
        p.episode, p.target = f"{e.participant}/t42/k2", 42
    elif how == "context_too_long":
        p.episode = f"{e.participant}/t{e.target}/k9"
    return preds


LIES = {  # how -> (field in the message, words of the message)
    "participant": ("participant", "names participant"),
    "target_is_context": ("target", "target trial"),
    "other_target": ("target", "target trial"),
    "method": ("method", "a predictions file holds one method"),
    "claimed_context": ("target", "context trials"),
    "custom_id": ("episode", "pass the episode set with --episodes"),
    "no_such_trial": ("target", "has no trial 42"),
    "context_too_long": ("episode", "asks for 9 context trials"),
}


@pytest.mark.parametrize("how", sorted(LIES))
def test_evaluate_refuses_records_that_contradict_their_episode(world, small_dataset_dir, tmp_path, capsys, how):
    ds, eps, out = world
    before = snapshot(out)
    path = tmp_path / "lie.jsonl"
    write_predictions(path, _lie(ds, eps, how))
    code, err = _evaluate(capsys, small_dataset_dir, path, out)
    field, words = LIES[how]
    assert code == 2 and f"lie.jsonl:3: field '{field}'" in err and words in err, err
    assert snapshot(out) == before and leftovers(tmp_path) == []


@pytest.mark.parametrize("how", ["participant", "target_is_context"])
def test_evaluate_with_episodes_names_file_line_and_field(world, small_dataset_dir, tmp_path, capsys, how):
    ds, eps, out = world
    before = snapshot(out)
    write_predictions(tmp_path / "lie.jsonl", _lie(ds, eps, how))
    code, err = _evaluate(capsys, small_dataset_dir, tmp_path / "lie.jsonl", out, "--episodes", tmp_path / "eps.jsonl")
    assert code == 2 and f"lie.jsonl:3: field '{'participant' if how == 'participant' else 'target'}'" in err
    assert "the episode set says" in err and snapshot(out) == before


@pytest.mark.parametrize("usage", [[1, 2], "lots", {"tokens": "many", "cost_usd": None}, {"tokens": None, "cost_usd": "0.5"},
                                   {"tokens": {"deep": [1]}, "cost_usd": -3}, {"tokens": True}, 7])
def test_malformed_usage_is_ignored_and_reported(world, small_dataset_dir, tmp_path, capsys, usage):
    ds, eps, _ = world
    preds = perfect(ds, eps)
    preds[0].diagnostics = {"usage": usage}
    preds[1].diagnostics = {"usage": {"tokens": 100, "cost_usd": 0.5}}
    write_predictions(tmp_path / "p.jsonl", preds)
    code, err = _evaluate(capsys, small_dataset_dir, tmp_path / "p.jsonl", tmp_path / "ev")
    assert code == 0, err
    assert "1 record(s) have a malformed `diagnostics.usage`" in (tmp_path / "ev" / "report.md").read_text()
    assert json.loads((tmp_path / "ev" / "metrics.json").read_text())["m"]["tokens_per_episode"] == 100.0


def test_every_prediction_failed_is_said_in_the_report(world, small_dataset_dir, tmp_path, capsys):
    ds, eps, _ = world
    write_predictions(tmp_path / "f.jsonl", [Prediction(e.id, e.participant, e.target, "m", [], True) for e in eps])
    assert _evaluate(capsys, small_dataset_dir, tmp_path / "f.jsonl", tmp_path / "ev")[0] == 0
    assert "Every prediction of m failed (10 of 10)" in (tmp_path / "ev" / "report.md").read_text()


# --- item 8: evaluate writes its folder whole or not at all ---------------------------------------------------

def test_evaluate_failure_while_writing_leaves_the_previous_report(world, small_dataset_dir, tmp_path, capsys,
                                                                  monkeypatch):
    ds, eps, out = world
    before = snapshot(out)
    write_predictions(tmp_path / "new.jsonl", perfect(ds, eps, "new"))

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report_module, "atomic_write_text", disk_full)  # report.md: after metrics.json and the csv
    code, err = _evaluate(capsys, small_dataset_dir, tmp_path / "new.jsonl", out)
    assert code == 2 and f"{out}: cannot write the evaluation report" in err and "No space left" in err
    assert snapshot(out) == before and leftovers(tmp_path) == []
    monkeypatch.setattr(report_module, "atomic_write_text", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    code, _ = _evaluate(capsys, small_dataset_dir, tmp_path / "new.jsonl", out)
    assert code == 130 and snapshot(out) == before and leftovers(tmp_path) == []


def test_evaluate_out_folder_cases(world, small_dataset_dir, tmp_path, capsys):
    ds, eps, out = world
    (tmp_path / "afile").write_text("mine")
    code, err = _evaluate(capsys, small_dataset_dir, tmp_path / "good.jsonl", tmp_path / "afile")
    assert code == 2 and "exists and is not a folder" in err and (tmp_path / "afile").read_text() == "mine"
    # A folder holding a user's files: they stay; the report files are replaced beside them.
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "notes.txt").write_text("keep me")
    (run_dir / "report.md").write_text("old")
    assert _evaluate(capsys, small_dataset_dir, tmp_path / "good.jsonl", run_dir)[0] == 0
    assert sorted(p.name for p in run_dir.iterdir()) == ["metrics.json", "notes.txt", "per_episode.csv", "report.md"]
    assert (run_dir / "notes.txt").read_text() == "keep me" and (run_dir / "report.md").read_text() != "old"
    assert leftovers(tmp_path) == []


def test_leftovers_of_a_killed_run_are_cleaned_or_restored(world, small_dataset_dir, tmp_path, capsys):
    ds, eps, out = world
    stale = tmp_path / f".eval.{DEAD_PID}-abcd1234.tmp"
    stale.mkdir()
    (stale / "metrics.json").write_text("{}")
    live = tmp_path / f".eval.{os.getpid()}-live0001.tmp"  # a run in progress (this process): left alone
    live.mkdir()
    foreign = tmp_path / ".eval.mine.tmp"  # not a name degusta makes
    foreign.mkdir()
    assert _evaluate(capsys, small_dataset_dir, tmp_path / "good.jsonl", out)[0] == 0
    assert leftovers(tmp_path) == sorted([live.name, foreign.name])
    live.rmdir()
    # A kill between the two renames of the swap: the previous folder is put back, not deleted.
    before = snapshot(out)
    out.rename(tmp_path / f".eval.{DEAD_PID}-abcd1234.old.tmp")
    outdir.clean_stale(out, outdir.OutputKind("evaluation report", ("*",)))
    assert snapshot(out) == before and leftovers(tmp_path) == [foreign.name]


# --- item 8: render ----------------------------------------------------------------------------------------

def test_render_failure_leaves_the_previous_render(small_dataset_dir, tmp_path, capsys, monkeypatch):
    out = tmp_path / "ep"
    args = ["render", "episode", small_dataset_dir, "--participant", "p001", "--target", 2, "--context", 2,
            "--method", "mogma", "--out", out, "--size", 64]
    assert run(capsys, *args)[0] == 0
    before = snapshot(out)
    calls = {"n": 0}
    real = pathlib.Path.write_bytes

    def sixth_write_fails(self, data):
        calls["n"] += 1
        if calls["n"] == 7:
            raise OSError(28, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(pathlib.Path, "write_bytes", sixth_write_fails)
    code, err = run(capsys, *args[:-1], 96)
    assert code == 2 and "cannot write the rendered episode" in err
    assert snapshot(out) == before and leftovers(tmp_path) == []
    monkeypatch.undo()
    # louma over the mogma render: exactly louma's files, no stale GoMO sheets beside them.
    assert run(capsys, *args[:7], "--context", 0, "--method", "louma", "--out", out, "--size", 64)[0] == 0
    assert sorted(p.name for p in out.iterdir()) == ["initial_state_1.png", "objects.json"]
    code, err = run(capsys, "render", "catalog", small_dataset_dir, "--out", out, "--size", 64)
    assert code == 2 and "is a folder" in err


# --- item 8: data generate -----------------------------------------------------------------------------------

def test_generate_overwrite_refuses_what_it_did_not_write(tmp_path, capsys):
    data = tmp_path / "data"
    assert run(capsys, "data", "generate", "simulated", "--out", data)[0] == 0
    (data / "notes.txt").write_text("a user's notes")
    before = snapshot(data)
    code, err = run(capsys, "data", "generate", "simulated", "--out", data, "--overwrite", "--seed", 2)
    assert code == 2 and "refusing to replace a folder that is not a dataset degusta wrote" in err
    assert "'notes.txt'" in err and snapshot(data) == before
    # Only degusta's file names, but a meta.json no generator of degusta wrote.
    other = tmp_path / "other"
    other.mkdir()
    (other / "meta.json").write_text('{"name": "my study"}')
    (other / "arrangements.jsonl").write_text("precious\n")
    before = snapshot(other)
    code, err = run(capsys, "data", "generate", "simulated", "--out", other, "--overwrite")
    assert code == 2 and "no degusta generator signature" in err and snapshot(other) == before
    (tmp_path / "f").write_text("x")
    assert "not a folder" in run(capsys, "data", "generate", "simulated", "--out", tmp_path / "f", "--overwrite")[1]
    assert leftovers(tmp_path) == []


def test_generate_interrupted_and_killed(tmp_path, capsys, monkeypatch):
    data = tmp_path / "data"
    assert run(capsys, "data", "generate", "simulated", "--out", data)[0] == 0
    before = snapshot(data)
    killed = tmp_path / f".data.{DEAD_PID}-zzzz0000.tmp"  # what a SIGKILL leaves
    killed.mkdir()
    (killed / "catalog.json").write_text("{")
    legacy = tmp_path / ".data.ab12cd34.tmp"  # what a SIGKILL of the previous version left
    legacy.mkdir()
    (legacy / "tables.json").write_text("[")

    def interrupted(*a, **k):
        raise KeyboardInterrupt  # Ctrl-C or SIGTERM while the folder is being written

    monkeypatch.setattr(generate_module, "write_styles", interrupted)
    code, _ = run(capsys, "data", "generate", "simulated", "--out", data, "--overwrite", "--seed", 1)
    assert code == 130 and snapshot(data) == before and leftovers(tmp_path) == []
    monkeypatch.undo()
    assert run(capsys, "data", "generate", "simulated", "--out", data, "--overwrite", "--seed", 1)[0] == 0
    assert snapshot(data) != before and leftovers(tmp_path) == []


# --- item 8: compare -----------------------------------------------------------------------------------------

def _compare_cfg(tmp_path, dataset, methods, out="cmp", extra=""):
    cfg = tmp_path / "cmp.yaml"
    lines = [f"dataset: {dataset}", f"out: {tmp_path / out}", f"episodes: {tmp_path / 'eps.jsonl'}",
             "n_bootstrap: 20", "qualitative: 0", "render_size: 64", "methods:"]
    lines += [f"  - {json.dumps(m)}" for m in methods]
    cfg.write_text("\n".join(lines) + "\n" + extra)
    return cfg


def test_compare_method_names_and_total_failure(world, small_dataset_dir, tmp_path, capsys):
    good = str(tmp_path / "good.jsonl")
    for name in ("../../escaped", "/abs", "a/b", ".hidden", "", "x" * 81):
        cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": name, "predictions": good}])
        code, err = run(capsys, "compare", "--config", cfg)
        assert code == 2 and "expected a safe name" in err, (name, err)
    assert not (tmp_path / "cmp").exists() and not (tmp_path.parent / "escaped").exists()
    # Every method fails: exit 2, no report that looks like a result, a previous report untouched.
    assert run(capsys, "compare", "--config", _compare_cfg(tmp_path, small_dataset_dir,
                                                            [{"name": "a", "predictions": good}]))[0] == 0
    before = snapshot(tmp_path / "cmp")
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"method: nope\ndataset: {small_dataset_dir}\nout: {tmp_path / 'x.jsonl'}\n")
    cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": "broken", "config": str(bad)},
                                                     {"name": "missing", "predictions": str(tmp_path / "no.jsonl")}])
    code, err = run(capsys, "compare", "--config", cfg)
    assert code == 2 and "every method failed, so no report was written" in err and "unknown method 'nope'" in err
    assert snapshot(tmp_path / "cmp") == before and leftovers(tmp_path) == []


def test_compare_refuses_lying_records_and_clashing_names(world, small_dataset_dir, tmp_path, capsys):
    ds, eps, _ = world
    write_predictions(tmp_path / "lie.jsonl", _lie(ds, eps, "target_is_context"))
    cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": "a", "predictions": str(tmp_path / "good.jsonl")},
                                                     {"name": "liar", "predictions": str(tmp_path / "lie.jsonl")}])
    code, err = run(capsys, "compare", "--config", cfg)
    assert code == 2 and "method 'liar'" in err and "lie.jsonl:3: field 'target'" in err
    rnd = tmp_path / "random.yaml"
    rnd.write_text(f"method: random\ndataset: {small_dataset_dir}\nout: {tmp_path / 'r.jsonl'}\n")
    cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": "r", "config": str(rnd)},
                                                     {"name": "r_episodes", "predictions": str(tmp_path / "good.jsonl")}])
    code, err = run(capsys, "compare", "--config", cfg)
    assert code == 2 and "would both write predictions/r_episodes.jsonl" in err
    assert not (tmp_path / "cmp").exists()


def test_compare_recomputes_stale_predictions(world, small_dataset_dir, tmp_path, capsys):
    rnd = tmp_path / "random.yaml"
    rnd.write_text(f"method: random\ndataset: {small_dataset_dir}\nout: {tmp_path / 'r.jsonl'}\nmax_objects: 8\n")
    cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": "r", "config": str(rnd)}])
    pred = tmp_path / "cmp" / "predictions" / "r_episodes.jsonl"
    assert run(capsys, "compare", "--config", cfg)[0] == 0
    assert json.loads(pred.with_name("r_episodes.fingerprint.json").read_text())["parts"].keys() == {
        "config", "files", "dataset", "episodes"}
    first = pred.read_bytes()
    capsys.readouterr()
    assert main(["compare", "--config", str(cfg)]) == 0
    assert "reusing" in capsys.readouterr().out and pred.read_bytes() == first
    rnd.write_text(rnd.read_text().replace("max_objects: 8", "max_objects: 3"))  # the method changed
    assert main(["compare", "--config", str(cfg)]) == 0
    assert "is stale (it was produced with another config): recomputing" in capsys.readouterr().out
    assert pred.read_bytes() != first
    assert all(len(json.loads(x)["placements"]) <= 3 for x in pred.read_text().splitlines())
    pred.write_text(pred.read_text().replace('"failed": false', '"failed": true', 1))  # edited by hand
    assert main(["compare", "--config", str(cfg)]) == 0
    assert "it was changed after it was produced" in capsys.readouterr().out
    assert leftovers(tmp_path) == [] and leftovers(tmp_path / "cmp") == []


def test_compare_never_recomputes_a_paid_method_silently(world, small_dataset_dir, tmp_path, capsys):
    ds, eps, _ = world
    paid = tmp_path / "gpt.yaml"
    paid.write_text(f"method: mogma\ndataset: {small_dataset_dir}\nout: {tmp_path / 'g.jsonl'}\n"
                    "backend: {name: openai}\nmodel: {name: gpt-4o}\n")
    pred = tmp_path / "cmp" / "predictions" / "gpt_episodes.jsonl"
    pred.parent.mkdir(parents=True)
    write_predictions(pred, perfect(ds, eps, "mogma"))  # from an older version: no fingerprint
    before = snapshot(tmp_path / "cmp")
    cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": "gpt", "config": str(paid)}])
    code, err = run(capsys, "compare", "--config", cfg)
    assert code == 2 and f"{pred}: not reused because there is no gpt_episodes.fingerprint.json" in err
    assert "calls a paid API" in err and "delete that file to recompute" in err and "not paid again" in err
    assert snapshot(tmp_path / "cmp") == before


def test_compare_failure_while_writing_keeps_report_and_predictions(world, small_dataset_dir, tmp_path, capsys,
                                                                    monkeypatch):
    cfg = _compare_cfg(tmp_path, small_dataset_dir, [{"name": "a", "predictions": str(tmp_path / "good.jsonl")}])
    assert run(capsys, "compare", "--config", cfg)[0] == 0
    before = snapshot(tmp_path / "cmp")
    assert "predictions/a.jsonl" in before and "report.md" in before

    def broken(*a, **k):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(plots_module, "_save", broken)
    code, err = run(capsys, "compare", "--config", cfg)
    assert code == 2 and "cannot write the comparison report" in err
    assert snapshot(tmp_path / "cmp") == before and leftovers(tmp_path) == []
    monkeypatch.undo()
    (tmp_path / "cmp" / "notes.txt").write_text("mine")  # a user's file in the report folder stays
    assert run(capsys, "compare", "--config", cfg)[0] == 0
    assert (tmp_path / "cmp" / "notes.txt").read_text() == "mine" and (tmp_path / "cmp" / "report.md").is_file()
    assert leftovers(tmp_path) == []


def test_placements_of_lying_records_are_never_scored(world, small_dataset_dir, tmp_path, capsys):
    """The trap of item 7: a record whose target is a context trial would score as a perfect copy."""
    ds, eps, _ = world
    e = eps[0]
    shown = ds.arrangement(e.participant, e.context[0])
    cheat = [Prediction(e.id, e.participant, e.context[0], "cheat", list(shown.placements))]
    write_predictions(tmp_path / "cheat.jsonl", cheat)
    code, err = _evaluate(capsys, small_dataset_dir, tmp_path / "cheat.jsonl", tmp_path / "ev")
    assert code == 2 and not (tmp_path / "ev").exists()
