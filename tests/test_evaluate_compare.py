"""`degusta compare`: same numbers as `evaluate`, every linked file present, mismatches refused."""

import json
import re

import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate import plots
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry, compare
from degusta_learn.evaluate.summary import DEGENERATE_MARK
from degusta_learn.scene import (
    Placement,
    Prediction,
    load_dataset,
    make_episodes,
    write_episodes,
    write_predictions,
)


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
                        n_bootstrap=200, qualitative=1, render_size=128)
    result = compare(cfg, log=lambda m: None)
    out = result.out
    assert result.failures == {} and result.failure_summary() == ""
    assert main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(a), str(b),
                 "--out", str(tmp_path / "ev"), "--bootstrap", "200"]) == 0
    cmp_metrics = json.loads((out / "metrics.json").read_text())["methods"]
    ev_metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    for m in ("a", "b"):
        for key in ("object_accuracy", "rmsd", "rmsd_unregistered", "count_error", "set_rmsd", "acceptable_at",
                    "acceptable_at_paper", "failure_rate", "degenerate", "frac_le2_matched"):
            assert cmp_metrics[m][key] == ev_metrics[m][key], (m, key)
    report = (out / "report.md").read_text()
    acceptability = report.split("## Acceptability", 1)[1].split("\n## ", 1)[0]
    assert acceptability.count("| error threshold t |") == 1  # one table: the people's row beside every method's
    for m in ("a", "b"):  # each method like for like and the paper's variant, labelled
        assert f"| {m}: unregistered set RMSD <= t |" in acceptability
        assert f"| {m}: Kabsch RMSD <= t (paper) |" in acceptability
    assert acceptability.count("% of ratings with drop < 0.2") == 1 and "rating drop is below 0.2" in acceptability
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
                        n_bootstrap=100, qualitative=0, render_size=96)
    result = compare(cfg, log=lambda m: None)
    out = result.out
    assert result.failed == ["broken"] and "unknown method 'nope'" in result.failures["broken"]
    assert result.failure_summary().startswith("1 of 2 methods failed: broken;")
    metrics = json.loads((out / "metrics.json").read_text())
    assert "broken" in metrics["failed_methods"] and "a" in metrics["methods"]
    assert "unknown method 'nope'" in (out / "report.md").read_text()


def test_a_one_object_method_is_marked_and_never_ranked_first(setup, small_dataset_dir, tmp_path, monkeypatch):
    ds, eps, a, b = setup
    # "lonely" puts one object exactly where it belongs: Kabsch RMSD 0 and acc@0.01 = 1 on every episode.
    lonely = []
    for e in eps:
        gt = ds.arrangement(e.participant, e.target)
        lonely.append(Prediction(e.id, e.participant, e.target, "lonely", list(gt.placements[:1])))
    write_predictions(tmp_path / "lonely.jsonl", lonely)
    # "mostly_failed" fails 9 episodes in 10 (set RMSD ~0.9 c, worse than lonely's) but is not degenerate.
    mostly = [Prediction(e.id, e.participant, e.target, "mostly_failed",
                         list(ds.arrangement(e.participant, e.target).placements) if i % 10 == 0 else [], i % 10 != 0)
              for i, e in enumerate(eps)]
    write_predictions(tmp_path / "mostly.jsonl", mostly)
    seen = []  # every plot's legend entries and tick labels, captured before the figure is saved

    def spy(fig, path):
        texts = [t.get_text() for ax in fig.axes for t in ax.get_xticklabels()]
        texts += [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
        seen.append((path.name, texts, fig.texts[0].get_text() if fig.texts else ""))
        return save(fig, path)

    save = plots._save
    monkeypatch.setattr(plots, "_save", spy)
    cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp_path / "cmp"), episodes=str(tmp_path / "eps.jsonl"),
                        methods=[MethodEntry("lonely", predictions=str(tmp_path / "lonely.jsonl")),
                                 MethodEntry("mostly_failed", predictions=str(tmp_path / "mostly.jsonl")),
                                 MethodEntry("b", predictions=str(b)), MethodEntry("a", predictions=str(a))],
                        n_bootstrap=100, qualitative=1, render_size=96)
    out = compare(cfg, log=lambda m: None).out
    metrics = json.loads((out / "metrics.json").read_text())
    m = metrics["methods"]
    assert m["lonely"]["degenerate"] is True and m["lonely"]["frac_le2_matched"] == 1.0
    assert not any(m[k]["degenerate"] for k in ("a", "b", "mostly_failed"))
    # The trap: lonely beats every method on Kabsch RMSD and the paper's acceptability, and mostly_failed on set
    # RMSD (acceptability like for like charges its missing objects: never acceptable) ...
    assert m["lonely"]["rmsd"]["mean"] == 0.0 and m["lonely"]["acceptable_at_paper"]["0.01"] == 1.0
    assert m["lonely"]["acceptable_at"]["0.01"] == 0.0
    assert m["lonely"]["set_rmsd"]["mean"] < m["mostly_failed"]["set_rmsd"]["mean"]
    # ... yet it is ranked last, after every non-degenerate method (those by set RMSD).
    assert metrics["ranking"] == ["a", "b", "mostly_failed", "lonely"] == list(m)
    assert [(p["a"], p["b"]) for p in metrics["paired"]][:3] == [("a", "b"), ("a", "mostly_failed"), ("a", "lonely")]
    assert all(p["set_rmsd"] is not None for p in metrics["paired"])
    by_pair = {(p["a"], p["b"]): p for p in metrics["paired"]}
    gap = m["lonely"]["set_rmsd"]["mean"] - m["a"]["set_rmsd"]["mean"]  # Δ is b - a, as the report says
    assert by_pair[("a", "lonely")]["set_rmsd"]["diff"] == pytest.approx(gap, abs=1e-6) and gap > 0.1
    report = (out / "report.md").read_text()
    main_rows = [line for line in report.splitlines() if re.match(r"\| \d \| ", line)]
    lonely_mark = " (degenerate: too few objects)"
    assert main_rows[0].startswith("| 1 | a |") and main_rows[-1].startswith(f"| 4 | lonely{lonely_mark} |")
    assert "ranked by mean set RMSD" in report and "paper's metrics" in report and "Δ set RMSD" in report
    # Every table row naming lonely marks it (main, Table 1, cost, paired).
    table_mentions = [line for line in report.splitlines() if line.startswith("|") and "lonely" in line]
    assert len(table_mentions) >= 6
    assert all(line.count("lonely") == line.count("lonely" + lonely_mark) for line in table_mentions)
    assert "lonely" + lonely_mark in (out / "report.html").read_text()
    assert "best of a (top-ranked)" in report
    # Every plot marks it: legend suffix or tick label, and the bars say how they are ranked.
    by_name = {name: (texts, title) for name, texts, title in seen}
    assert set(by_name) >= {"metrics.png", "acceptability.png"}
    bars, title = by_name["metrics.png"]
    assert bars[:4] == ["a", "b", "mostly_failed", "lonely\n(degenerate: too few objects)"]
    assert "ranked by set RMSD" in title
    legend = [t for t in by_name["acceptability.png"][0] if "error <= t" in t]
    assert legend == ["a: error <= t", "b: error <= t", "mostly_failed: error <= t", f"lonely{DEGENERATE_MARK}: error <= t"]
