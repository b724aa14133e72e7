"""benchmarks/bench_base_route.py: seed-averaged rows, participant-clustered pairs, and the record a rebuilt base's
card shows (its protocol, its validation rows, the one test look)."""

import json

import pytest
from benchmark_support import load_benchmark
from conftest import make_small_dataset

from degusta_learn.pretrain.export import BASE_META, SELECTION, write_card
from degusta_learn.scene import Prediction, make_episodes, save_dataset, write_predictions
from degusta_learn.shipped import BASE_DIR

bench = load_benchmark("bench_base_route")


@pytest.fixture
def route(tmp_path):
    """A dataset of 30 participants and three predictions files on its test episodes: exact, one object, exact."""
    ds = make_small_dataset(n_participants=30)
    data = save_dataset(ds, tmp_path / "data")
    episodes = make_episodes(ds, 4, "test", 0)

    def file(name, keep):
        preds = [Prediction(e.id, e.participant, e.target, "m", keep(ds.arrangement(e.participant, e.target).placements))
                 for e in episodes]
        write_predictions(tmp_path / f"{name}.jsonl", preds)
        return tmp_path / f"{name}.jsonl"

    return data, file("exact", list), file("one", lambda p: p[:1]), file("exact2", list)


def _run(data, rows, *extra):
    argv = ["--dataset", str(data), "--split", "test", "--n-bootstrap", "200"]
    for row in rows:
        argv += ["--row", row]
    return bench.main(argv + list(extra))


def test_a_rows_score_is_the_mean_over_its_seeds_and_pairs_are_clustered(route, capsys):
    data, exact, one, _ = route
    ds_rows = {"exact": [exact], "one": [one], "mixed": [exact, one]}
    from degusta_learn.scene import load_dataset
    ds = load_dataset(data)
    episodes = {e.id: e for e in make_episodes(ds, 4, "test", 0)}
    result = bench.measure(ds, episodes, ds_rows, [("exact", "one")], 200)
    row = {r["name"]: r for r in result["rows"]}
    assert row["exact"]["set_rmsd"][0] == 0.0 and row["exact"]["object_accuracy"][0] == 1.0
    assert row["one"]["set_rmsd"][0] > 0.05
    # linear in the seeds: the mean of per-episode means is the mean of the two rows
    assert row["mixed"]["set_rmsd"][0] == pytest.approx((row["exact"]["set_rmsd"][0] + row["one"]["set_rmsd"][0]) / 2,
                                                        abs=1e-4)
    assert result["participants"] == len({e.participant for e in episodes.values()}) >= 5
    pair = result["pairs"][0]["set_rmsd"]
    assert pair["diff"] < 0 and pair["hi"] < 0 and pair["p_value"] < 0.05
    _run(data, [f"exact={exact}", f"one={one}"], "--pair", "exact", "one")
    out = capsys.readouterr().out
    assert "| exact | 1 | 0.000" in out and "exact minus one: set_rmsd -" in out


def test_the_record_keeps_one_test_look_and_the_card_shows_it(route, tmp_path):
    data, exact, one, exact2 = route
    base = tmp_path / "base"
    base.mkdir()
    (base / BASE_META).write_text((BASE_DIR / BASE_META).read_text())
    protocol = "One build of the recipe, its seed fixed in advance, shipped as it came."
    _run(data, [f"images + text={exact},{exact2}", f"one={one}"], "--pair", "images + text", "one",
         "--record", str(base), "--section", "test", "--protocol", protocol)
    sel = json.loads((base / SELECTION).read_text())
    assert sel["protocol"] == protocol and sel["test"]["rows"][0]["files"] == 2 and sel["test"]["split"] == "test"
    card = write_card(base).read_text()
    assert "## How this build was chosen" in card and protocol in card
    assert "The test split, looked at once" in card and "| images + text | 2 | 0.000 [0.000, 0.000]" in card
    assert "- images + text minus one: set rmsd -" in card
    with pytest.raises(SystemExit, match="measured already"):  # the test split is looked at once
        _run(data, [f"one={one}"], "--record", str(base), "--section", "test")
    _run(data, [f"one={one}"], "--record", str(base), "--section", "test", "--replace-test", "a bug in the scorer")
    sel = json.loads((base / SELECTION).read_text())
    assert sel["withdrawn_test_looks"][0]["withdrawn_because"] == "a bug in the scorer"
    assert [r["name"] for r in sel["test"]["rows"]] == ["one"] and sel["protocol"] == protocol
    assert "was withdrawn: a bug in the scorer" in write_card(base).read_text()


def test_a_card_without_a_record_has_no_selection_section(tmp_path):
    (tmp_path / BASE_META).write_text((BASE_DIR / BASE_META).read_text())
    assert "How this build was chosen" not in write_card(tmp_path).read_text()


@pytest.mark.parametrize("extra, message", [
    (["--section", "validation", "--record", "X"], "the section names the split"),
    (["--record", "X"], "needs --section"),
    (["--pair", "exact", "nope"], "is not a --row name"),
])
def test_bad_arguments_are_one_line(route, capsys, extra, message):
    data, exact, *_ = route
    with pytest.raises(SystemExit):
        _run(data, [f"exact={exact}"], *extra)
    assert message in capsys.readouterr().err


def test_a_file_that_misses_episodes_is_refused(route, tmp_path):
    data, exact, *_ = route
    lines = exact.read_text().splitlines()
    short = tmp_path / "short.jsonl"
    short.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(SystemExit, match="1 of the .* episodes have no prediction"):
        _run(data, [f"short={short}"])
    with pytest.raises(SystemExit, match="no such file"):
        _run(data, [f"gone={tmp_path / 'gone.jsonl'}"])
