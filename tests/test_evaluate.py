"""`degusta evaluate`: metrics.json keys, per-episode rows and the report, on hand-made predictions."""

import csv
import json

import pytest

from degusta_learn.cli import main
from degusta_learn.evaluate.summary import rank_methods
from degusta_learn.metrics import SET_PENALTY
from degusta_learn.scene import (
    Placement,
    Prediction,
    load_dataset,
    make_episodes,
    write_episodes,
    write_predictions,
)


def _predictions(ds, episodes, method, shift=0.0, fail_every=0):
    out = []
    for i, e in enumerate(episodes):
        gt = ds.arrangement(e.participant, e.target)
        failed = bool(fail_every) and i % fail_every == 0
        placements = [] if failed else [Placement(p.object, min(p.x + shift, 1.0), p.y, p.rotation) for p in gt.placements]
        out.append(Prediction(e.id, e.participant, e.target, method, placements, failed))
    return out


def test_perfect_and_shifted_and_failing_methods(small_dataset_dir, tmp_path, capsys):
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    write_predictions(tmp_path / "perfect.jsonl", _predictions(ds, eps, "perfect"))
    write_predictions(tmp_path / "shifted.jsonl", _predictions(ds, eps, "shifted", shift=0.05, fail_every=5))
    out = tmp_path / "eval"
    code = main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(tmp_path / "perfect.jsonl"),
                 str(tmp_path / "shifted.jsonl"), "--episodes", str(tmp_path / "eps.jsonl"), "--out", str(out),
                 "--bootstrap", "200"])
    assert code == 0, capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    perfect, shifted = metrics["perfect"], metrics["shifted"]
    assert set(perfect) >= {"n_episodes", "failure_rate", "object_accuracy", "rmsd", "rmsd_unregistered",
                            "count_error", "set_rmsd", "acceptable_at", "degenerate", "frac_le2_matched"}
    assert set(perfect["rmsd"]) == set(perfect["set_rmsd"]) == {"mean", "ci_low", "ci_high"}
    assert perfect["set_rmsd"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert (perfect["degenerate"], perfect["frac_le2_matched"]) == (False, 0.0)
    # Failed predictions are left out of the Kabsch RMSD mean but count as c in the set RMSD mean.
    assert shifted["set_rmsd"]["mean"] == pytest.approx(0.2 * SET_PENALTY, abs=0.01)
    assert shifted["set_rmsd"]["ci_low"] <= shifted["set_rmsd"]["mean"] <= shifted["set_rmsd"]["ci_high"]
    assert perfect["object_accuracy"]["mean"] == pytest.approx(1.0)
    assert perfect["rmsd"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert perfect["acceptable_at"] == {"0.01": 1.0, "0.05": 1.0, "0.10": 1.0}
    # A rigid shift is registered away by Kabsch but not by the unregistered RMSD.
    assert shifted["rmsd"]["mean"] < 0.02 < shifted["rmsd_unregistered"]["mean"]
    assert shifted["failure_rate"] == pytest.approx(0.2)
    assert shifted["object_accuracy"]["mean"] == pytest.approx(0.8)
    assert shifted["acceptable_at"]["0.10"] == pytest.approx(0.8)
    rows = list(csv.DictReader((out / "per_episode.csv").open()))
    assert len(rows) == 2 * len(eps)
    assert {float(r["set_rmsd"]) for r in rows if r["failed"] == "True"} == {SET_PENALTY}
    report = (out / "report.md").read_text()
    assert "SYNTHETIC" in report and "| perfect |" in report and "N = 1 gives RMSD 0" in report


def test_refuses_unknown_episode_and_missing_predictions(small_dataset_dir, tmp_path, capsys):
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    write_predictions(tmp_path / "few.jsonl", _predictions(ds, eps[:3], "few"))
    args = ["evaluate", "--dataset", str(small_dataset_dir), "--episodes", str(tmp_path / "eps.jsonl"),
            "--out", str(tmp_path / "eval")]
    assert main([*args, "--predictions", str(tmp_path / "few.jsonl")]) == 2
    assert "episodes have no prediction" in capsys.readouterr().err
    bad = _predictions(ds, eps, "bad")
    bad[0].episode = "nobody/t0/k2"
    write_predictions(tmp_path / "bad.jsonl", bad)
    assert main([*args, "--predictions", str(tmp_path / "bad.jsonl")]) == 2
    assert "bad.jsonl:1: field 'episode': unknown episode 'nobody/t0/k2'" in capsys.readouterr().err
    assert not (tmp_path / "eval").exists()


def test_one_object_predictions_are_flagged(small_dataset_dir, tmp_path):
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    preds = _predictions(ds, eps, "lonely", shift=0.3)
    for p in preds:
        p.placements = p.placements[:1]
    write_predictions(tmp_path / "lonely.jsonl", preds)
    write_predictions(tmp_path / "shifted.jsonl", _predictions(ds, eps, "shifted", shift=0.05))
    assert main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(tmp_path / "lonely.jsonl"),
                 str(tmp_path / "shifted.jsonl"), "--out", str(tmp_path / "ev"), "--bootstrap", "50"]) == 0
    summary = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    metrics = summary["lonely"]
    assert metrics["rmsd"]["mean"] == pytest.approx(0.0) and metrics["few_objects_rate"] == 1.0
    assert metrics["degenerate"] is True and metrics["frac_le2_matched"] == 1.0
    assert metrics["degenerate_reasons"] == ["too few"] and metrics["degenerate_fractions"]["too few"] == 1.0
    assert summary["shifted"]["degenerate"] is False and summary["shifted"]["degenerate_reasons"] == []
    # Count bias: one object of the ground truth's n on every episode, so exactly mean(1 - n_gt).
    rows = [r for r in csv.DictReader((tmp_path / "ev" / "per_episode.csv").open()) if r["method"] == "lonely"]
    assert metrics["count_bias"]["mean"] == pytest.approx(sum(1 - int(r["n_gt"]) for r in rows) / len(rows), abs=1e-6)
    assert summary["shifted"]["count_bias"]["mean"] == 0.0
    # 3-5 ground-truth objects, one predicted: at least sqrt(2/3) * c, never ~0.
    assert metrics["set_rmsd"]["mean"] >= (2 / 3) ** 0.5 * SET_PENALTY - 1e-9
    assert list(summary) == ["shifted", "lonely"]  # metrics.json in rank order, though lonely was given first
    report = (tmp_path / "ev" / "report.md").read_text()
    assert "Warning: lonely matches at most 2 objects in 100%" in report
    assert "| 1 | shifted |" in report and "| 2 | lonely (degenerate: too few objects) |" in report
    assert "(degenerate: too few objects): most of its scored predictions have at most 0.5 x" in report
    assert "ranked by mean set RMSD" in report and "paper's metrics" in report


def test_rank_methods_puts_degenerate_methods_last():
    def entry(mean, degenerate=False):
        return {"set_rmsd": {"mean": mean}, "degenerate": degenerate}

    summary = {"one_object": entry(0.01, True), "bad": entry(0.19), "good": entry(0.05), "none": entry(None),
               "tie": entry(0.05), "two_objects": entry(0.15, True)}
    assert rank_methods(summary) == ["good", "tie", "bad", "none", "one_object", "two_objects"]
