"""`degusta evaluate` and `degusta compare` with the task-plan metrics and participant-clustered intervals: the new
columns and their counts, the line saying what was resampled, predictions without rotations scored on what they
have (with a note), per-episode resampling as an option, and paired tests whose bold and p agree."""

import csv
import json
import re

import numpy as np
import pytest

from degusta_learn.evaluate import evaluate_files, paired_comparisons, score_predictions, summarize
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry, compare
from degusta_learn.evaluate.compare_report import paired_cells
from degusta_learn.evaluate.scoring import CSV_COLUMNS, EpisodeRow
from degusta_learn.evaluate.summary import METRICS, PLAN_METRICS
from degusta_learn.metrics import bootstrap_ci, symmetry_order
from degusta_learn.scene import Placement, Prediction, load_dataset, make_episodes, write_episodes, write_predictions


def _predictions(ds, episodes, method, shift=0.0, turn=0.0, reverse=False):
    out = []
    for e in episodes:
        gt = ds.arrangement(e.participant, e.target)
        placements = [Placement(p.object, min(p.x + shift, 0.74), p.y, (p.rotation + turn) % 360) for p in gt.placements]
        out.append(Prediction(e.id, e.participant, e.target, method, placements[::-1] if reverse else placements))
    return out


@pytest.fixture
def files(small_dataset_dir, tmp_path):
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    write_predictions(tmp_path / "perfect.jsonl", _predictions(ds, eps, "perfect"))
    write_predictions(tmp_path / "turned.jsonl", _predictions(ds, eps, "turned", shift=0.03, turn=30.0, reverse=True))
    # An older file: the same placements as perfect, written without rotations.
    lines = []
    for p in _predictions(ds, eps, "norot"):
        record = p.to_json()
        for item in record["placements"]:
            del item["rotation"]
        lines.append(json.dumps(record))
    (tmp_path / "norot.jsonl").write_text("\n".join(lines) + "\n")
    return ds, eps, tmp_path


def test_evaluate_reports_the_plan_metrics_clustered(files):
    ds, eps, tmp = files
    out = evaluate_files(tmp / "small", [tmp / "perfect.jsonl", tmp / "turned.jsonl", tmp / "norot.jsonl"],
                         tmp / "ev", episodes=tmp / "eps.jsonl", n_bootstrap=200)
    metrics = json.loads((out / "metrics.json").read_text())
    perfect, turned, norot = metrics["perfect"], metrics["turned"], metrics["norot"]
    n_people = len({e.participant for e in eps})
    assert perfect["resampling"] == {"unit": "participant", "n_units": n_people, "n_resamples": 200, "seed": 0}
    for name in PLAN_METRICS:
        assert set(perfect[name]) == {"mean", "ci_low", "ci_high"}, name
    assert perfect["order_tau"]["mean"] == 1.0 and turned["order_tau"]["mean"] == -1.0  # listed in reverse
    assert perfect["rotation_error"]["mean"] == 0.0
    # A 30 degree turn is 30 off for an object without symmetry, a square or oval plate, 15 for an octagonal one
    # (it looks the same every 45), not scored for a round plate.
    def expected(e):
        errors = [{1: 30.0, 2: 30.0, 4: 30.0, 8: 15.0}[s] for s in
                  (symmetry_order(ds.catalog[p.object]) for p in ds.arrangement(e.participant, e.target).placements)
                  if s]
        return np.mean(errors) if errors else np.nan
    assert turned["rotation_error"]["mean"] == pytest.approx(np.nanmean([expected(e) for e in eps]), abs=1e-6)
    assert perfect["object_precision"]["mean"] == perfect["object_f1"]["mean"] == 1.0
    assert perfect["set_rmsd_unregistered"]["mean"] == 0.0 and turned["set_rmsd_unregistered"]["mean"] > 0.02
    assert perfect["off_table_rate"]["mean"] == 0.0 and perfect["ground_truth"]["off_table_rate"] == 0.0
    assert perfect["n_scored"]["order_tau"] == len(eps) and perfect["n_scored"]["off_table_rate"] == len(eps)
    # Without rotations: rotation error and footprint overlap (which needs the turn) not scored nor counted, every
    # other metric as for the same placements with their rotations.
    for name in ("rotation_error", "overlap_rate"):
        assert norot[name]["mean"] is None and norot["n_scored"][name] == 0
    assert norot["missing_fields"] == {"rotation": len(eps)}
    for name in METRICS:
        if name not in ("rotation_error", "overlap_rate"):
            assert norot[name] == perfect[name], name
    rows = list(csv.DictReader((out / "per_episode.csv").open()))
    assert set(CSV_COLUMNS) <= set(rows[0]) and {r["missing"] for r in rows if r["method"] == "norot"} == {"rotation"}
    assert {r["rotation_error"] for r in rows if r["method"] == "norot"} == {""}  # empty, not 0
    report = (out / "report.md").read_text()
    assert "**Task plan**" in report and "| order τ | n | rotation error (°) | n |" in report
    assert "object precision | object F1 | set RMSD (unreg.) |" in report and "(paper)" in report
    assert report.count(f"bootstrap over participants (200 resamples of the {n_people} participants") == 2
    assert "Intervals are 95% bootstrap intervals over participants." in report
    n = len(eps)
    assert (f"norot: {n} of {n} predictions have placements without `rotation`; their rotation error and "
            "overlapping pairs are not scored") in report.replace("\\", "")
    assert f"norot.jsonl: {n} record(s) have placements without `rotation`" in report.replace("\\", "")


def test_clustered_by_default_and_per_episode_as_an_option(files):
    ds, eps, tmp = files
    ep_map = {e.id: e for e in eps}
    rows = score_predictions(ds, _predictions(ds, eps, "turned", shift=0.03, turn=30.0), ep_map)
    clustered, per_episode = summarize(rows, 300, 1)["turned"], summarize(rows, 300, 1, cluster=None)["turned"]
    people = [r.participant for r in rows]
    for name in ("set_rmsd", "rmsd", "order_tau", "object_f1"):
        values = [getattr(r, name) for r in rows]
        _, lo, hi = bootstrap_ci(values, n_resamples=300, seed=1, clusters=people)
        assert (clustered[name]["ci_low"], clustered[name]["ci_high"]) == (round(lo, 6), round(hi, 6))
        _, lo, hi = bootstrap_ci(values, n_resamples=300, seed=1)  # the old, per-episode interval
        assert (per_episode[name]["ci_low"], per_episode[name]["ci_high"]) == (round(lo, 6), round(hi, 6))
    assert per_episode["resampling"]["unit"] == "episode" and per_episode["resampling"]["n_units"] == len(rows)
    out = evaluate_files(tmp / "small", [tmp / "turned.jsonl"], tmp / "ev1", n_bootstrap=100, cluster=None)
    report = (out / "report.md").read_text()
    assert "bootstrap over episodes (100 resamples, episodes drawn one by one" in report
    with pytest.raises(Exception, match="cluster"):
        summarize(rows, 10, cluster="table")


def test_paired_comparisons_resample_participants_and_agree(files):
    ds, eps, _ = files
    ep_map = {e.id: e for e in eps}
    rows = score_predictions(ds, _predictions(ds, eps, "a"), ep_map)
    rows += score_predictions(ds, _predictions(ds, eps, "b", shift=0.03), ep_map)
    rows += score_predictions(ds, _predictions(ds, eps, "c", shift=0.031), ep_map)
    paired = paired_comparisons(rows, ["a", "b", "c"], n_bootstrap=500, seed=2)
    assert [(e["a"], e["b"]) for e in paired] == [("a", "b"), ("a", "c"), ("b", "c")]
    assert paired[0]["resampling"]["unit"] == "participant"
    for e in paired:
        for metric in ("set_rmsd", "object_accuracy", "rmsd"):
            r = e[metric]
            if r is None or r["lo"] is None or np.isnan(r["lo"]):
                continue
            bold = paired_cells(r, 500)[0].startswith("**")
            assert bold == (r["p_value"] < 0.05) == (r["lo"] > 0 or r["hi"] < 0), (e["a"], e["b"], metric, r)
    per_episode = paired_comparisons(rows, ["a", "b"], n_bootstrap=500, seed=2, cluster=None)
    assert per_episode[0]["resampling"]["unit"] == "episode"
    assert per_episode[0]["set_rmsd"]["diff"] == paired[0]["set_rmsd"]["diff"]
    assert paired_cells({"diff": 0.1, "lo": 0.05, "hi": 0.2, "p_value": 0.0}, 1000) == ["**+0.100 [+0.050, +0.200]**",
                                                                                       "<0.001"]


def test_compare_report_shows_plan_and_clustered_paired(files, small_dataset_dir):
    ds, eps, tmp = files
    cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp / "cmp"), episodes=str(tmp / "eps.jsonl"),
                        methods=[MethodEntry("perfect", predictions=str(tmp / "perfect.jsonl")),
                                 MethodEntry("turned", predictions=str(tmp / "turned.jsonl"))],
                        n_bootstrap=100, qualitative=0)
    out = compare(cfg, log=lambda m: None).out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["methods"]["perfect"]["resampling"]["unit"] == "participant"
    assert metrics["paired"][0]["resampling"]["unit"] == "participant"
    report = (out / "report.md").read_text()
    assert "**Task plan**" in report and "Intervals and the paired tests: 95% percentile bootstrap over participants" \
        in report
    row = next(line for line in report.splitlines() if line.startswith("| perfect | turned |"))
    cells = [c.strip() for c in row.strip("|").split("|")][2:]
    for text, p in zip(cells[0::2], cells[1::2]):
        if text != "-" and p != "-":
            assert text.startswith("**") == (p.startswith("<") or float(p) < 0.05), row
    assert re.search(r"Intervals are 95% bootstrap intervals over participants", report)


def test_episode_rows_keep_working_without_the_new_fields():
    # Rows built by other code with only the original fields still summarize (the new metrics are nan there).
    row = EpisodeRow("m", "p/t1/k1", "p", 1, 1, "reconstruction", False, 3, 3, 3, 1.0, 0.0, 0.0, 0, 0.0)
    s = summarize([row, EpisodeRow(**{**row.to_row(), "participant": "q", "episode": "q/t1/k1"})], 20)["m"]
    assert s["order_tau"]["mean"] is None and s["n_scored"]["order_tau"] == 0 and s["set_rmsd"]["mean"] == 0.0
