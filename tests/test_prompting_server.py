"""The zero-shot runner against a REAL HTTP server on loopback speaking OpenAI chat completions.

The server (http.server in a thread, started by each test) records every request and answers from a
script: canned well-formed and malformed answers, 429s with Retry-After, 500s, 401s. Checked: the
request shape (images as data URLs, n), retries, cache hits on a second run (zero requests), resume
after a stop half way (only the rest is requested), failure accounting, the dry run, and that the API
key is never written to any file.
"""

from __future__ import annotations

import base64
import json
import time

import pytest
import yaml
from conftest import make_small_dataset
from loopback import Loopback, chat_completion, json_reply

from degusta_learn.cli import main as cli_main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict
from degusta_learn.scene import read_predictions, save_dataset

FAKE_KEY = "sk-FAKE-degusta-key-0123456789abcdef"
GOOD = "Here you go:\n```python\n[{'type': 'plate', 'id': 75, 'position': ['D4', 'd5'], 'cardinal_direction': 'N'}," \
       " {'type': 'fork', 'id': 25, 'position': ['C4', 'C5'], 'direction': 'N'}]\n```"
BAD = "I would place a plate in the middle."


class FakeOpenAI(Loopback):
    """A loopback OpenAI-compatible server; `script` entries are consumed first, then `answer`."""

    def __init__(self, answer=lambda body, i: GOOD, max_choices: int | None = None):
        self.answer, self.max_choices = answer, max_choices
        super().__init__(lambda req: self.reply(req["body"]))

    def reply(self, body):
        k = body.get("n", 1) if self.max_choices is None else min(self.max_choices, body.get("n", 1))
        return json_reply(200, chat_completion(body["model"], [self.answer(body, i) for i in range(k)],
                                               prompt_tokens=1000))

    def error(self, status, message="error", headers=None):
        self.script.append(json_reply(status, {"error": {"message": message, "type": "x", "code": None}}, headers))


@pytest.fixture
def server():
    s = FakeOpenAI()
    yield s
    s.close()


@pytest.fixture
def dataset_dir(tmp_path):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path / "data")


def write_config(tmp_path, server, dataset_dir, **extra):
    cfg = {"method": "mogma", "dataset": str(dataset_dir), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "render_size": 64, "concurrency": 2, "backoff": 0.01,
           "backend": {"name": "openai", "base_url": server.url, "timeout": 10}, "model": {"name": "fake-model"},
           "decoding": {"n": 5, "temperature": 1.0}}
    for k in ("n", "temperature"):  # decoding keys given as keywords
        if k in extra:
            cfg["decoding"][k] = extra.pop(k)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(cfg.get(k), dict):
            cfg[k].update(v)
        else:
            cfg[k] = v
    path = tmp_path / "zeroshot.yaml"
    path.write_text("# degusta predict --config zeroshot.yaml\n" + yaml.safe_dump(cfg))
    return path


def read_ledger(tmp_path):
    return json.loads((tmp_path / "run" / "ledger.json").read_text())


def test_request_shape_and_predictions(tmp_path, server, dataset_dir, monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", FAKE_KEY)
    out = run_predict(write_config(tmp_path, server, dataset_dir, temperature=0.7,
                                   backend={"api_key_env": "OPENAI_API_KEY"}))
    assert len(server.requests) == 9  # 3 participants x 3 targets, n=5 in ONE request each
    req = server.requests[0]
    body = req["body"]
    assert req["path"] == "/v1/chat/completions" and req["headers"]["authorization"] == f"Bearer {FAKE_KEY}"
    assert body["model"] == "fake-model" and body["n"] == 5 and body["temperature"] == 0.7
    content = body["messages"][0]["content"]
    images = [c["image_url"]["url"] for c in content if c["type"] == "image_url"]
    texts = [c["text"] for c in content if c["type"] == "text"]
    assert len(images) == 5 + 2 + 1  # GoMO sheets, context GMAs, target table
    assert all(u.startswith("data:image/jpeg;base64,") for u in images)
    assert base64.b64decode(images[0].split(",", 1)[1])[:3] == b"\xff\xd8\xff"  # a real JPEG
    assert "final_state_2.jpg:" in texts and "initial_state_1.jpg:" in texts
    assert "cardinal_direction" in texts[-1]
    preds = read_predictions(out, make_small_dataset(3, 3).catalog)
    assert len(preds) == 9 and not any(p.failed for p in preds)
    assert [pl.object for pl in preds[0].placements] == [75, 25]
    assert preds[0].diagnostics["n_parsed"] == 5 and preds[0].diagnostics["failures"] == []
    ledger = read_ledger(tmp_path)
    assert ledger["requests"] == 9 and ledger["input_tokens"] == 9000 and ledger["output_tokens"] == 450
    assert ledger["cost_usd"] == 0  # a loopback server is free unless priced


def test_second_run_is_served_from_the_cache(tmp_path, server, dataset_dir):
    path = write_config(tmp_path, server, dataset_dir)
    first = (run_predict(path)).read_text()
    assert len(server.requests) == 9
    second = run_predict(path).read_text()
    assert len(server.requests) == 9, "a cached run must make zero requests"
    strip = [{**row, "diagnostics": {**row["diagnostics"], "cached": None}}
             for row in map(json.loads, first.splitlines())]
    assert strip == [{**row, "diagnostics": {**row["diagnostics"], "cached": None}}
                     for row in map(json.loads, second.splitlines())]
    assert json.loads(second.splitlines()[0])["diagnostics"]["cached"] == 5
    ledger = read_ledger(tmp_path)
    assert ledger["requests"] == 0 and ledger["samples_cached"] == 45


def test_retries_honour_retry_after_then_succeed(tmp_path, server, dataset_dir):
    server.error(429, "slow down", {"Retry-After": "0.3"})
    server.error(500, "oops")
    server.error(503, "overloaded")
    t0 = time.time()
    run_predict(write_config(tmp_path, server, dataset_dir, concurrency=1))
    assert time.time() - t0 >= 0.3
    ledger = read_ledger(tmp_path)
    assert ledger["retries"] == 3 and ledger["requests"] == 9 and len(server.requests) == 12


def test_failure_accounting(tmp_path, dataset_dir):
    # sample 0 malformed, sample 1 an unknown id, the rest good; one episode's request fails for good (400)
    answers = {0: BAD, 1: "[{'type': 'plate', 'id': 999, 'position': ['D4'], 'cardinal_direction': 'N'}]"}
    server = FakeOpenAI(answer=lambda body, i: answers.get(i, GOOD))
    try:
        server.error(400, "bad request")
        out = run_predict(write_config(tmp_path, server, dataset_dir, concurrency=1, max_retries=1))
    finally:
        server.close()
    preds = read_predictions(out, make_small_dataset(3, 3).catalog)
    first, rest = preds[0], preds[1:]
    assert first.failed and first.placements == [] and first.diagnostics["n_parsed"] == 0
    assert all(f["reason"].startswith("request failed: openai: HTTP 400") for f in first.diagnostics["failures"])
    for p in rest:
        assert not p.failed and p.diagnostics["n_parsed"] == 3
        reasons = {f["sample"]: f["reason"] for f in p.diagnostics["failures"]}
        assert "no list of objects" in reasons[0] and "unknown object id 999" in reasons[1]
        assert p.diagnostics["responses"][0] == BAD
    ledger = read_ledger(tmp_path)
    assert ledger["failed_requests"] == 1 and ledger["episodes_failed"] == 1


def test_budget_stop_then_resume_requests_only_the_rest(tmp_path, server, dataset_dir):
    # $1 per output token; the server bills 10 tokens a sample, the estimate is 10 a sample too
    extra = {"concurrency": 1, "prices": {"fake-model": [0, 1_000_000]}, "est_output_tokens": 10}
    path = write_config(tmp_path, server, dataset_dir, budget_usd=220, **extra)
    with pytest.raises(DegustaError, match="budget") as e:
        run_predict(path)
    assert "re-run" in str(e.value)
    assert len(server.requests) == 4  # 4 x $50 = $200; a 5th would pass $220
    assert not (tmp_path / "run" / "predictions.jsonl").exists()
    ledger = read_ledger(tmp_path)
    assert ledger["cost_usd"] == 200 and ledger["stopped"].startswith("budget") and ledger["episodes_done"] == 4
    path = write_config(tmp_path, server, dataset_dir, **extra)
    out = run_predict(path)
    assert len(server.requests) == 9, "the resumed run asks only for the 5 unfinished episodes"
    assert read_ledger(tmp_path)["samples_cached"] == 20 and out.exists()


def test_fatal_error_half_way_stops_and_resumes(tmp_path, server, dataset_dir, monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", FAKE_KEY)
    path = write_config(tmp_path, server, dataset_dir, concurrency=1)  # the OpenAI key is not sent here
    server.script = [server.reply({"n": 5, "model": "m"})] * 3
    server.error(401, f"Incorrect API key provided: {FAKE_KEY}")
    with pytest.raises(DegustaError) as e:
        run_predict(path)
    assert "401" in str(e.value) and FAKE_KEY not in str(e.value)
    assert len(server.requests) == 4
    run_predict(path)
    assert len(server.requests) == 4 + 6


def test_server_that_ignores_n_is_asked_again(tmp_path, dataset_dir):
    server = FakeOpenAI(max_choices=1)  # like Ollama's OpenAI endpoint
    try:
        out = run_predict(write_config(tmp_path, server, dataset_dir, n=3, concurrency=1))
    finally:
        server.close()
    assert [r["body"]["n"] for r in server.requests[:3]] == [3, 2, 1]
    assert [r["body"]["seed"] for r in server.requests[:3]] == [0, 1, 2]  # not the same sample thrice
    assert len(server.requests) == 27 and out.exists()


def test_dry_run_calls_nothing_and_writes_nothing(tmp_path, server, dataset_dir, capsys):
    path = write_config(tmp_path, server, dataset_dir, prices={"fake-model": [2.5, 10]})
    assert cli_main(["predict", "--config", str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "requests: 9 for 45 samples" in out and "estimated cost: USD" in out and "nothing written" in out
    assert server.requests == [] and not (tmp_path / "run").exists()


def test_the_api_key_is_never_written(tmp_path, server, dataset_dir, monkeypatch, capsys):
    monkeypatch.setenv("MY_VLM_KEY", FAKE_KEY)
    server.error(500, f"internal error for key {FAKE_KEY}")
    path = write_config(tmp_path, server, dataset_dir, max_retries=0, backend={"api_key_env": "MY_VLM_KEY"})
    assert cli_main(["predict", "--config", str(path)]) == 2  # one episode unanswered: incomplete run
    assert server.requests[0]["headers"]["authorization"] == f"Bearer {FAKE_KEY}"
    server.error(401, f"Incorrect API key provided: {FAKE_KEY}")
    assert cli_main(["predict", "--config", str(path), "--set", "cache=off"]) == 2
    captured = capsys.readouterr()
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert any(p.suffix == ".sqlite" for p in written) and any(p.name == "ledger.json" for p in written)
    for p in written:
        assert FAKE_KEY.encode() not in p.read_bytes(), f"the API key leaked into {p}"
    assert FAKE_KEY not in captured.out + captured.err
