"""A constrained row says what it is: predictions record what decoding did (budget closes, the free answer
behind each constrained one), the predict summary counts it, and reports label the row "+ grammar" with
its free-decoding parse rate beside the constrained one."""

from __future__ import annotations

from pathlib import Path

from finetune_support import GRID, dataset, tiny_dir

from degusta_learn.evaluate.report import answer_table
from degusta_learn.evaluate.scoring import score_predictions
from degusta_learn.evaluate.summary import GRAMMAR_MARK, label, summarize
from degusta_learn.scene import Prediction, make_episodes, read_predictions, save_dataset, write_episodes
from degusta_learn.task.aggregate import decoding_diagnostics, failure_summary
from degusta_learn.task.prompt import Completion

CONFIGS = Path(__file__).parent.parent / "configs"
GOOD = "[{'type': 'cup', 'id': 3, 'position': ['A1'], 'cardinal_direction': 'N'}]"


def constrained(changed: bool, free_text: str | None = None, forced: bool = False, repeat: bool = False) -> Completion:
    return Completion(GOOD, 10, 20, {"constrained": True, "forced_close": forced, "grammar_changed": changed,
                                     "repeat_stop": repeat, "free_text": free_text, "free_cut": False})


def test_decoding_diagnostics_count_closes_and_free_parses():
    cat = dataset().catalog
    samples = [constrained(False), constrained(True, "Sure! " + GOOD), constrained(True, "no list here", True),
               constrained(True, None, repeat=True), None]
    d = decoding_diagnostics(samples, "grid", cat, GRID)
    assert d["constrained"] and d["known"] == 4 and d["forced_closes"] == 1 and d["grammar_changed"] == 3
    assert d["repeat_stops"] == 1 and "substitutions" not in d
    swapped = Completion(GOOD, 10, 20, {**constrained(True).decoding, "substituted": [[1, 3, 4], [2, 3, None]]})
    sd = decoding_diagnostics([swapped, swapped, constrained(False)], "grid", cat, GRID)
    assert sd["substitutions"] == 2 and sd["substituted"] == [[[1, 3, 4], [2, 3, None]]] * 2 + [None]
    # unchanged: its own free answer (parses); changed with a free text: parsed; changed without: unknown
    assert (d["free_known"], d["free_parsed"]) == (3, 2)
    assert (d["free_items"], d["free_item_errors"]) == (2, 0)  # one item in each free answer that parses
    bad_item = "[{'type': 'plate', 'id': 3, 'position': ['A1'], 'cardinal_direction': 'N'}, " + GOOD[1:]
    assert decoding_diagnostics([constrained(True, bad_item)], "grid", cat, GRID)["free_item_errors"] == 1
    assert d["free_responses"] == [None, "Sure! " + GOOD, "no list here", None, None]
    free = [Completion("x", decoding={"constrained": False, "cut": True}), Completion(GOOD, decoding={"constrained": False, "cut": False})]
    assert decoding_diagnostics(free, "grid", cat, GRID) == {"constrained": False, "known": 2, "forced_closes": 1}
    assert decoding_diagnostics([Completion(GOOD), None], "grid", cat, GRID) == {}  # remote / cached: nothing claimed
    # decoding.report_unconstrained: false: no free answers were decoded, so none is claimed (not even the unchanged)
    off = [Completion(GOOD, 10, 20, {**c.decoding, "free_pass": False}) for c in (constrained(False), constrained(True))]
    d = decoding_diagnostics(off, "grid", cat, GRID)
    assert d["grammar_changed"] == 1 and (d["free_known"], d["free_parsed"]) == (0, 0)


def _prediction(ep, decoding: dict | None, n=4, parsed=4, **diagnostics) -> Prediction:
    gt = dataset().arrangement(ep.participant, ep.target)
    diag = {"n_responses": n, "n_parsed": parsed, **({"decoding": decoding} if decoding else {}), **diagnostics}
    return Prediction(ep.id, ep.participant, ep.target, "mogma", list(gt.placements), False, diag)


def test_summary_line_labels_and_answer_table():
    eps = make_episodes(dataset(), 2, "test", 0)[:3]
    dec = {"constrained": True, "known": 4, "forced_closes": 1, "grammar_changed": 3, "free_known": 4, "free_parsed": 1,
           "free_items": 5, "free_item_errors": 1}
    preds = [_prediction(ep, dec) for ep in eps]
    line = failure_summary(preds)
    assert "3 of 12 answers closed early by the token budget (25.0%);" in line and "named an object again" not in line
    line = failure_summary([_prediction(ep, {**dec, "repeat_stops": 2}) for ep in eps])
    assert "(25.0%), 6 ended where the model named an object again;" in line
    line = failure_summary([_prediction(ep, {**dec, "substitutions": 2}) for ep in eps])
    assert "(25.0%), 6 items naming an object again given another id;" in line
    assert "without the grammar 3 of 12 would parse (25.0%; the grammar changed 9; 3 of their 15 items dropped" in line
    items = [Prediction(p.episode, p.participant, p.target, p.method, p.placements, False,
                        {**p.diagnostics, "n_items": 10, "n_item_errors": 3, "n_item_repeats": 2}) for p in preds]
    assert "items: 9 of 30 dropped (30.0%; 6 of them named an object again);" in failure_summary(items)
    assert "items: 9 of 30 dropped (30.0%);" in failure_summary(  # older predictions: no repeat count
        [Prediction(p.episode, p.participant, p.target, p.method, p.placements, False,
                    {k: v for k, v in p.diagnostics.items() if k != "n_item_repeats"}) for p in items])
    unmeasured = failure_summary([_prediction(ep, {**dec, "free_known": 0, "free_parsed": 0}) for ep in eps])
    assert unmeasured.endswith("the grammar changed 9 (their free answers not decoded: decoding.report_unconstrained "
                               "is false)") and "would parse" not in unmeasured
    free = [_prediction(ep, {"constrained": False, "known": 4, "forced_closes": 2}, parsed=3) for ep in eps]
    assert "6 of 12 answers cut off by the token budget (50.0%)" in failure_summary(free)

    rows = score_predictions(dataset(), preds, {e.id: e for e in eps})
    rows += [r.__class__(**{**r.to_row(), "method": "free"}) for r in score_predictions(dataset(), free)]
    rows += [r.__class__(**{**r.to_row(), "method": "api"})
             for r in score_predictions(dataset(), [_prediction(ep, None, parsed=2) for ep in eps])]
    # how the answers were combined, from the diagnostics: a known name, else not recorded (untrusted input)
    for name, how in (("voted", "greedy_votes_pooled"), ("hostile", "<script>"), ("greedy", "steps")):
        rows += [r.__class__(**{**r.to_row(), "method": name}) for r in score_predictions(
            dataset(), [_prediction(ep, None, n=1 if name == "greedy" else 5, parsed=1, aggregation=how)
                        for ep in eps])]
    rows += [r.__class__(**{**r.to_row(), "method": "mixed"}) for r in score_predictions(  # files put together
        dataset(), [_prediction(ep, None, n=n, parsed=1, aggregation=how)
                    for ep, n, how in zip(eps, (1, 5, 5), ("steps", "greedy_votes_pooled", "steps"))])]
    summary = summarize(rows, n_bootstrap=50)
    s = summary["mogma"]
    assert s["constrained"] and s["parse_rate"] == 1.0 and s["parse_rate_free"] == 0.25 and s["forced_close_rate"] == 0.25
    assert label("mogma", s) == "mogma" + GRAMMAR_MARK and label("free", summary["free"]) == "free"
    assert summary["free"]["constrained"] is False and "parse_rate_free" not in summary["free"]
    assert "constrained" not in summary["api"] and summary["api"]["parse_rate"] == 0.5
    table = "\n".join(answer_table(summary))
    assert "| mogma + grammar | answer grammar | 4, not recorded | 1.000 | 0.250 | 0.250 |" in table
    assert "| free | free | 4, not recorded | 0.750 | 0.750 | 0.500 |" in table
    assert "| api | not recorded | 4, not recorded | 0.500 | - | - |" in table
    assert "| voted | not recorded | 5, greedy_votes_pooled | 0.200 | - | - |" in table
    assert "| hostile | not recorded | 5, not recorded | 0.200 |" in table and "script" not in table.split("|---|")[-1]
    assert "| greedy | not recorded | 1 | 1.000 |" in table  # one answer: nothing combined
    assert "| mixed | not recorded | 1-5, greedy_votes_pooled + steps |" in table



def test_predict_with_the_grammar_records_and_reports_it(tmp_path, one_torch_thread):
    """`degusta predict` with the shipped constrained zero-shot config (max_new_tokens: auto) on the tiny model,
    then `degusta evaluate`: the diagnostics, the summary line and the report all say "+ grammar"."""
    from degusta_learn.evaluate import evaluate_files
    from degusta_learn.methods import run_predict
    from degusta_learn.prompting.backends.hf import HFBackend

    data = save_dataset(dataset(), tmp_path / "data")
    episodes = tmp_path / "episodes.jsonl"
    write_episodes(episodes, make_episodes(dataset(), 2, "test", 0)[:1])
    lines: list[str] = []
    out = run_predict(CONFIGS / "predict_hf_tiny_zeroshot.yaml", [
        f"dataset={data}", f"episodes={episodes}", "context=2", f"out={tmp_path / 'pred' / 'predictions.jsonl'}",
        f"model.name={tiny_dir('idefics3')}", "render_size=128"], log=lines.append)
    preds = read_predictions(out, dataset().catalog)
    budget = HFBackend(str(tiny_dir("idefics3")), constrained=True, device="cpu", grid=GRID,
                       catalog=dataset().catalog).token_budget(dataset(), "mogma")["max_new_tokens"]
    for p in preds:
        d = p.diagnostics["decoding"]
        assert d["constrained"] and d["known"] == 1 and d["max_new_tokens"] == budget
        assert d["grammar_changed"] == 1 and d["free_known"] == 1 and d["free_parsed"] == 0  # random weights
        assert isinstance(d["free_responses"][0], str)
    assert any("decoded inside the answer grammar" in line for line in lines), lines
    report = evaluate_files(data, [out], tmp_path / "eval", n_bootstrap=50)
    text = (Path(report) / "report.md").read_text()
    # (random weights write one object again and again: on_repeat skip keeps it once, degenerate, to the budget)
    assert "mogma + grammar" in text and " | answer grammar | 1 | 1.000 | 0.000 | 1.000 |" in text
    # decoding.report_unconstrained: false: the same answer, no free answer decoded, and the summary says so
    lines.clear()
    off = run_predict(CONFIGS / "predict_hf_tiny_zeroshot.yaml", [
        f"dataset={data}", f"episodes={episodes}", "context=2", f"out={tmp_path / 'off' / 'predictions.jsonl'}",
        f"model.name={tiny_dir('idefics3')}", "render_size=128", "decoding.report_unconstrained=false"],
        log=lines.append)
    (p_off,) = read_predictions(off, dataset().catalog)
    assert p_off.diagnostics["responses"] == preds[0].diagnostics["responses"]
    assert p_off.diagnostics["decoding"]["free_known"] == 0 and p_off.diagnostics["decoding"]["free_responses"] == [None]
    assert any("their free answers not decoded: decoding.report_unconstrained is false" in line for line in lines), lines
