"""benchmarks/choose_decoding.py: every way of combining one greedy_votes_pooled run's stored answers, scored from the
same answers, and the choice made on a score that a short answer cannot game."""

import sys

import pytest
from benchmark_support import load_benchmark

from degusta_learn.render.grid import Grid
from degusta_learn.scene import Prediction, load_dataset, make_episodes, write_predictions
from degusta_learn.task.aggregate import aggregate, anchored_votes, combine
from degusta_learn.task.answer_format import answer_items, format_answer

bench = load_benchmark("choose_decoding")
G = Grid(8, 8)


def _run(ds, split: str, answers) -> list[Prediction]:
    """A greedy_votes_pooled predictions file: per episode the greedy answer and five samples, as `answers(truth)` says."""
    out = []
    for e in make_episodes(ds, 4, split, 0):
        truth = answer_items(ds.arrangement(e.participant, e.target).placements, ds.catalog, "grid", G)
        greedy, samples = answers(truth)
        out.append(Prediction(e.id, e.participant, e.target, "mogma", [], diagnostics={
            "responses": [format_answer(s, "grid") for s in samples], "greedy_response": format_answer(greedy, "grid")}))
    return out


def test_each_way_is_the_librarys_aggregation_of_the_stored_answers(small_dataset):
    e = make_episodes(small_dataset, 4, "test", 0)[0]
    truth = answer_items(small_dataset.arrangement(e.participant, e.target).placements, small_dataset.catalog, "grid", G)
    samples = [truth[:1], truth[::-1], truth[1:], truth]
    pred = Prediction(e.id, e.participant, e.target, "mogma", [], diagnostics={
        "responses": [format_answer(s, "grid") for s in samples] + ["not an answer"],
        "greedy_response": format_answer(truth[:2], "grid")})
    ways = bench.decodings(pred, small_dataset.catalog, G)
    assert tuple(ways) == bench.WAYS == ("greedy", "steps", "greedy_votes_pooled")
    assert ways["steps"] == aggregate(samples + [None], "grid", G)[0] == combine(samples, "grid", G)[0]
    assert ways["greedy_votes_pooled"] == anchored_votes(truth[:2], samples, "grid", G)[0] == combine(
        samples, "grid", G, how="greedy_votes_pooled", anchor=truth[:2])[0]
    assert [p.object for p in ways["greedy"]] == [it.id for it in truth[:2]]


def test_the_choice_is_made_on_the_set_score_not_on_short_answers(small_dataset_dir, tmp_path, monkeypatch, capsys):
    ds = load_dataset(small_dataset_dir)
    # the greedy answers are the truth; the samples name its first object alone (Kabsch RMSD 0 by construction)
    path = tmp_path / "val.jsonl"
    write_predictions(path, _run(ds, "val", lambda t: (t, [t[:1]] * 5)))
    monkeypatch.setattr(sys, "argv", ["choose_decoding.py", str(path), "--dataset", str(small_dataset_dir),
                                      "--split", "val"])
    bench.main()
    out = capsys.readouterr().out
    assert "chosen by set_rmsd (mean over the files): greedy\n" in out
    steps = next(line for line in out.splitlines() if line.startswith("| steps |"))
    assert steps.split(" | ")[5] == "1.00"  # one object an answer
    monkeypatch.setattr(sys, "argv", ["choose_decoding.py", str(path), "--dataset", str(small_dataset_dir),
                                      "--split", "test", "--only", "greedy"])
    with pytest.raises(SystemExit, match=r"lacks \d+ of the \d+ test episodes"):
        bench.main()


def test_samples_combines_the_first_k_stored_answers_as_a_run_with_that_n_would(small_dataset):
    e = make_episodes(small_dataset, 4, "test", 0)[0]
    truth = answer_items(small_dataset.arrangement(e.participant, e.target).placements, small_dataset.catalog, "grid", G)
    samples = [truth, truth, truth[:1], truth[:1], truth[:1]]  # median length: the table (first 3), 1 (all 5)
    pred = Prediction(e.id, e.participant, e.target, "mogma", [], diagnostics={
        "responses": [format_answer(s, "grid") for s in samples], "greedy_response": format_answer(truth[:1], "grid")})
    assert len(truth) > 1
    first3 = bench.decodings(pred, small_dataset.catalog, G, samples=3)
    assert first3["greedy_votes_pooled"] == anchored_votes(truth[:1], samples[:3], "grid", G)[0]
    assert len(first3["greedy_votes_pooled"]) == len(truth)
    assert len(bench.decodings(pred, small_dataset.catalog, G)["greedy_votes_pooled"]) == 1
    with pytest.raises(SystemExit, match=r"5 sampled answers stored, --samples 6 asked"):
        bench.decodings(pred, small_dataset.catalog, G, samples=6)
