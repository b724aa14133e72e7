"""benchmarks/analyze_answers.py: ids, types and counts of VLM answers, kept and free."""

import pytest
from benchmark_support import load_benchmark

from degusta_learn.prompting.answers import answer_items, format_answer
from degusta_learn.render.grid import Grid
from degusta_learn.scene.episodes import make_episodes, write_episodes
from degusta_learn.scene.predictions import write_predictions
from degusta_learn.scene.types import Prediction


@pytest.fixture(scope="module")
def analyze():
    return load_benchmark("analyze_answers")


def test_copying_a_context_table_and_a_free_answer_that_repeats(analyze, small_dataset, small_dataset_dir, tmp_path,
                                                                capsys):
    ds, grid = small_dataset, Grid(8, 8)
    episodes = make_episodes(ds, context=2)[:6]
    preds = []
    for ep in episodes:
        copied = list(ds.arrangement(ep.participant, ep.context[0]).placements)
        text = format_answer(answer_items(copied, ds.catalog, "grid", grid), "grid")
        first = format_answer(answer_items(copied[:1], ds.catalog, "grid", grid), "grid")[1:-1]
        free = f"[{first}, {first}, {first}]"  # the same object three times: one item survives the parser
        preds.append(Prediction(ep.id, ep.participant, ep.target, "mogma", copied, diagnostics={
            "responses": [text], "decoding": {"free_responses": [free], "repeat_stops": 1}}))
    r = analyze.analyze(ds, {e.id: e for e in episodes}, preds, grid)
    assert r["episodes"] == 6 and r["repeat_stops"] == 6
    assert r["pred_ids_in_context"] == 1.0  # every id copied from a context table
    assert r["kept"]["n_pred"] > 1 and r["free"]["n_pred"] == 1.0  # the repeats dropped, not placed
    assert r["kept"]["object_accuracy"] > r["free"]["object_accuracy"]
    # a null free answer (the grammar changed nothing) is the kept answer, not an unreadable one
    same = [Prediction(p.episode, p.participant, p.target, p.method, p.placements, diagnostics={
        "responses": p.diagnostics["responses"], "decoding": {"free_responses": [None]}}) for p in preds]
    r = analyze.analyze(ds, {e.id: e for e in episodes}, same, grid)
    for key in ("n_pred", "object_accuracy", "count_error"):  # (positions: the answer's cells, not the plan's x, y)
        assert r["free"][key] == r["kept"][key]
    assert r["free"]["n_pred"] > 1

    write_episodes(tmp_path / "episodes.jsonl", episodes)
    (tmp_path / "run" / "predictions").mkdir(parents=True)
    write_predictions(tmp_path / "run" / "predictions" / "m.jsonl", preds)
    assert analyze.main(["--dataset", str(small_dataset_dir), "--episodes", str(tmp_path / "episodes.jsonl"),
                         str(tmp_path / "run" / "predictions" / "m.jsonl")]) == 0
    assert "| run/m | 6 |" in capsys.readouterr().out


def test_a_missing_file_is_one_line_not_a_traceback(analyze, small_dataset_dir, tmp_path):
    with pytest.raises(SystemExit, match="analyze_answers: .*nope.jsonl"):
        analyze.main(["--dataset", str(small_dataset_dir), "--episodes", str(tmp_path / "nope.jsonl"),
                      str(tmp_path / "p.jsonl")])
