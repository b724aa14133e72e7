"""`text_llm` against a REAL OpenAI-compatible HTTP server on 127.0.0.1 (tests/loopback.py): two text-only requests
an episode with the summary fed into the second, both cached (a second run asks nothing), both in the ledger and
under `budget_usd`, a malformed placement answer and a refused summary request counted as failures (never a
crash), and the dry run counting what the cache holds."""

from __future__ import annotations

import hashlib
import json

import pytest
import yaml
from conftest import make_small_dataset
from loopback import Loopback, chat_completion, json_reply

from degusta_learn.cli import main as cli_main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict
from degusta_learn.scene import read_predictions, save_dataset
from degusta_learn.task.text_llm_prompt import SUMMARY_LINE, SUMMARY_TASK

SUMMARY = "Blue ceramic plate centred, metal fork to its left pointing north; cup top right."
PLATE = "{'type': 'plate', 'id': 75, 'position': [0.5, 0.55], 'rotation': 0}"
FORK = "{'type': 'fork', 'id': 25, 'position': [0.35, 0.55], 'rotation': 10}"
GOOD = f"Here is the plan:\n[{PLATE}, {FORK}]"
BAD = "I would place a plate in the middle."
CAT = make_small_dataset(3, 3).catalog


def texts(body) -> str:
    content = body["messages"][0]["content"]
    return "\n\n".join(c["text"] for c in content if c["type"] == "text")


def is_summary(body) -> bool:
    return SUMMARY_TASK in texts(body)


def summary_for(body) -> str:
    """The fake model's summary of a summary prompt: SUMMARY tagged with a digest of the prompt (each person's own)."""
    return f"{SUMMARY} [{hashlib.sha256(texts(body).encode()).hexdigest()[:8]}]"


class FakeLLM(Loopback):
    """An OpenAI-compatible chat server: a summary request gets `summary_for` it, a placement request
    `placement(i)`; every answer is billed 10 output tokens, every request 1000 input tokens."""

    def __init__(self, placement=lambda i: GOOD):
        self.placement = placement
        super().__init__(self.reply)

    def reply(self, req):
        body = req["body"]
        answers = [summary_for(body)] if is_summary(body) else [self.placement(i) for i in range(body.get("n", 1))]
        return json_reply(200, chat_completion(body["model"], answers, prompt_tokens=1000))


@pytest.fixture
def server():
    s = FakeLLM()
    yield s
    s.close()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path_factory.mktemp("ds") / "data")


def config(tmp_path, server, data, **extra):
    cfg = {"method": "text_llm", "dataset": str(data), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "concurrency": 1, "backoff": 0, "max_retries": 1,
           "backend": {"name": "openai", "base_url": server.url, "timeout": 10}, "model": {"name": "fake-llm"},
           "decoding": {"n": 3, "temperature": 1.0}, "summary": {"max_new_tokens": 300}}
    cfg.update(extra)
    path = tmp_path / "text_llm.yaml"
    path.write_text("# degusta predict --config text_llm.yaml\n" + yaml.safe_dump(cfg))
    return path


def ledger(tmp_path):
    return json.loads((tmp_path / "run" / "ledger.json").read_text())


def test_two_text_requests_an_episode_with_the_summary_fed_into_the_second(tmp_path, server, data):
    out = run_predict(config(tmp_path, server, data))
    bodies = [r["body"] for r in server.requests]
    assert len(bodies) == 2 * 9  # 9 episodes: a summary, then the placements
    for body in bodies:
        assert all(c["type"] == "text" for c in body["messages"][0]["content"])  # no image anywhere
    summaries, placements = [b for b in bodies if is_summary(b)], [b for b in bodies if not is_summary(b)]
    assert len(summaries) == len(placements) == 9
    assert all(b["n"] == 1 and b["temperature"] == 0 and b["max_tokens"] == 300 for b in summaries)
    assert all(b["n"] == 3 and b["temperature"] == 1.0 and b["max_tokens"] == 1024 for b in placements)
    given = {summary_for(b) for b in summaries}
    assert len(given) == 9 and {next(s for s in given if SUMMARY_LINE + s in texts(b)) for b in placements} == given
    assert all("Placement order in table setting 2" in texts(b) for b in summaries)
    assert not any("Placement order in" in texts(b) for b in placements)
    preds = read_predictions(out, CAT)
    assert len(preds) == 9 and not any(p.failed for p in preds)
    for p in preds:
        assert [q.object for q in p.placements] == [75, 25]
        d = p.diagnostics
        assert d["summary"] in given and d["summary_cached"] is False and d["summary_failure"] is None
        assert d["backend"] == "openai" and d["model"] == "fake-llm" and d["n"] == 3 and d["n_parsed"] == 3
        assert d["responses"] == [GOOD] * 3 and d["split"] == "all" and d["choices"]["method"] == "text_llm"
    led = ledger(tmp_path)
    assert led["requests"] == 18 and led["samples_received"] == 9 * 4
    assert led["input_tokens"] == 18 * 1000 and led["output_tokens"] == 9 * 10 + 9 * 30
    assert led["steps"]["summary"] == {"samples_received": 9, "samples_cached": 0, "input_tokens": 9000,
                                       "output_tokens": 90, "episodes_failed": 0, "episodes_without_context": 0}
    assert led["steps"]["placement"]["samples_received"] == 27 and led["modality"] == "text"


def test_a_second_run_is_answered_from_the_cache(tmp_path, server, data, capsys):
    path = config(tmp_path, server, data)
    run_predict(path)
    first = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert len(server.requests) == 18
    run_predict(path)
    assert len(server.requests) == 18  # both steps cached: nothing asked again
    again = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert [p.placements for p in again] == [p.placements for p in first]
    assert all(p.diagnostics["summary_cached"] is True and p.diagnostics["cached"] == 3 for p in again)
    led = ledger(tmp_path)
    assert led["requests"] == 0 and led["samples_cached"] == 9 * 4 and led["cost_usd"] == 0
    assert led["reused_from_cache"]["input_tokens"] == 18 * 1000  # every cached answer's share of its request
    assert led["reused_from_cache"]["output_tokens"] == 9 * 10 + 9 * 30
    assert led["steps"]["summary"]["samples_cached"] == 9 and led["steps"]["placement"]["samples_cached"] == 27
    # the dry run sees the cache: nothing left to ask
    assert cli_main(["predict", "--config", str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "(0 still to run)" in out and "0 requests for 0 summaries (9 already cached)" in out
    assert "0 requests for 0 samples (27 already cached)" in out


def test_a_malformed_placement_answer_is_a_counted_failure(tmp_path, data, capsys):
    server = FakeLLM(placement=lambda i: BAD)
    try:
        code = cli_main(["predict", "--config", str(config(tmp_path, server, data))])
    finally:
        server.close()
    assert code == 0, capsys.readouterr().err
    assert "text_llm: 9 episodes, 9 failed (100.0%); samples: 27 of 27 failed (100.0%)" in capsys.readouterr().out
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    for p in preds:
        assert p.failed and p.placements == [] and p.diagnostics["summary"].startswith(SUMMARY)
        assert all(f["reason"] == "unparseable answer: no list of objects found in the answer"
                   for f in p.diagnostics["failures"])
    assert ledger(tmp_path)["episodes_failed"] == 9


def test_a_refused_summary_request_fails_only_its_episode(tmp_path, server, data):
    server.script.append(json_reply(400, {"error": {"message": "context too long", "type": "x", "code": None}}))
    out = run_predict(config(tmp_path, server, data))
    first, *rest = read_predictions(out, CAT)
    assert first.failed and first.diagnostics["summary"] is None
    assert first.diagnostics["summary_failure"].startswith("request failed: openai: HTTP 400")
    assert all(f["reason"].startswith("no summary: request failed") for f in first.diagnostics["failures"])
    assert not any(p.failed for p in rest)
    assert len(server.requests) == 1 + 2 * 8  # no placement request for the episode without a summary
    assert ledger(tmp_path)["steps"]["summary"]["episodes_failed"] == 1


def test_the_budget_counts_both_steps_and_a_rerun_asks_only_the_rest(tmp_path, server, data):
    # $1 per output token, 10 tokens an answer, estimated at 10 too: a summary costs $10, the placements $30
    prices = {"prices": {"fake-llm": [0, 1_000_000]}, "est_output_tokens": 10}
    path = config(tmp_path, server, data, budget_usd=135, summary={"est_output_tokens": 10}, **prices)
    with pytest.raises(DegustaError, match="budget") as e:
        run_predict(path)
    assert "re-run" in str(e.value)
    assert len(server.requests) == 7  # 3 episodes ($120), then the 4th's summary: its placements would pass $135
    led = ledger(tmp_path)
    assert led["cost_usd"] == 130 and led["stopped"].startswith("budget") and led["episodes_done"] == 3
    assert led["steps"]["summary"]["samples_received"] == 4 and led["steps"]["placement"]["samples_received"] == 9
    assert not (tmp_path / "run" / "predictions.jsonl").exists()
    run_predict(config(tmp_path, server, data, summary={"est_output_tokens": 10}, **prices))
    assert len(server.requests) == 7 + 1 + 2 * 5  # the 4th's placements, then the 5 untouched episodes
    assert ledger(tmp_path)["samples_cached"] == 3 * 4 + 1
