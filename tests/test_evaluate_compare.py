"""`degusta compare`: same numbers as `evaluate`, every linked file present, mismatches refused."""

import json
import re

import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry, compare
from degusta_learn.scene import Placement, Prediction, load_dataset, make_episodes, write_episodes, write_predictions


def _write(ds, episodes, method, path, shift=0.0):
    preds = []
    for e in episodes:
        gt = ds.arrangement(e.participant, e.target)
        preds.append(Prediction(e.id, e.participant, e.target, method,
                                [Placement(p.object, min(p.x + shift, 0.74), p.y, p.rotation) for p in gt.placements]))
    write_predictions(path, preds)
    return path


@pytest.fixture
def setup(small_dataset_dir, tmp_path):
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    a = _write(ds, eps, "a", tmp_path / "a.jsonl")
    b = _write(ds, eps, "b", tmp_path / "b.jsonl", shift=0.03)
    return ds, eps, a, b


def test_compare_matches_evaluate_and_links_resolve(setup, small_dataset_dir, tmp_path):
    ds, eps, a, b = setup
    cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp_path / "cmp"), episodes=str(tmp_path / "eps.jsonl"),
                        methods=[MethodEntry("a", predictions=str(a)), MethodEntry("b", predictions=str(b))],
                        n_bootstrap=200, qualitative=1, image_size=128)
    out = compare(cfg, log=lambda m: None)
    assert main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(a), str(b),
                 "--out", str(tmp_path / "ev"), "--bootstrap", "200"]) == 0
    cmp_metrics = json.loads((out / "metrics.json").read_text())["methods"]
    ev_metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    for m in ("a", "b"):
        for key in ("object_accuracy", "rmsd", "rmsd_unregistered", "count_error", "acceptable_at", "failure_rate"):
            assert cmp_metrics[m][key] == ev_metrics[m][key], (m, key)
    report = (out / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert any(link.startswith("plots/") for link in links) and any(link.startswith("qualitative/") for link in links)
    for link in links:
        assert (out / link).is_file(), link
    html = (out / "report.html").read_text()
    assert "<table>" in html and "qualitative/" in html
    assert (out / "per_episode.csv").is_file()


def test_compare_refuses_different_episode_sets(setup, small_dataset_dir, tmp_path):
    ds, eps, a, _ = setup
    fewer = _write(ds, eps[:-3], "c", tmp_path / "c.jsonl")
    cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp_path / "cmp"), episodes=str(tmp_path / "eps.jsonl"),
                        methods=[MethodEntry("a", predictions=str(a)), MethodEntry("c", predictions=str(fewer))])
    with pytest.raises(DegustaError, match=r"method 'c' was predicted on a different episode set: 3 episodes missing"):
        compare(cfg, log=lambda m: None)


def test_a_failing_method_is_reported_and_the_rest_written(setup, small_dataset_dir, tmp_path):
    _, _, a, _ = setup
    bad_cfg = tmp_path / "bad.yaml"
    bad_cfg.write_text(f"method: nope\ndataset: {small_dataset_dir}\nout: {tmp_path / 'x.jsonl'}\n")
    cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp_path / "cmp"), episodes=str(tmp_path / "eps.jsonl"),
                        methods=[MethodEntry("a", predictions=str(a)), MethodEntry("broken", config=str(bad_cfg))],
                        n_bootstrap=100, qualitative=0, image_size=96)
    out = compare(cfg, log=lambda m: None)
    metrics = json.loads((out / "metrics.json").read_text())
    assert "broken" in metrics["failed_methods"] and "a" in metrics["methods"]
    assert "unknown method 'nope'" in (out / "report.md").read_text()
