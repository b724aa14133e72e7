"""Hardening of the zero-shot path (issue 12, items 1-4, 8 (cache file), 12): hostile model answers,
server faults, leaked keys, a user's file named as the cache, and a kill between answer and cache.

Every case asserts the user-facing outcome: no exception but AnswerParseError out of the parser (with a
short reason), `degusta predict` exit 2 with one line naming the file / error, the output untouched, and
a re-run asking for exactly what is missing. Servers are real HTTP servers on 127.0.0.1; retries wait 0 s
(`backoff: 0`), so the file runs in seconds.
"""

from __future__ import annotations

import json
import socket
import sqlite3

import pytest
import yaml
from conftest import make_small_dataset
from loopback import Loopback, chat_completion, json_reply

from degusta_learn.cli import main as cli_main
from degusta_learn.prompting.backends.anthropic import AnthropicBackend
from degusta_learn.prompting.backends.base import BACKENDS, Completion, redact
from degusta_learn.prompting.cache import ResponseCache
from degusta_learn.render.grid import Grid
from degusta_learn.scene import default_catalog, read_predictions, save_dataset
from degusta_learn.task.answers import AnswerParseError, parse_answer, read_answer

CAT = default_catalog()
G = Grid(8, 8)
KEY = "degusta-test-secret-Zq81x0FfG7"  # no sk- prefix: only the configured variable's value finds it
PLATE = "{'type': 'plate', 'id': 75, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}"
FORK = "{'type': 'fork', 'id': 25, 'position': ['C4'], 'cardinal_direction': 'N'}"
GOOD = f"[{PLATE}, {FORK}]"

# Model texts that used to raise (or could): each must end as an AnswerParseError or a valid answer.
HOSTILE = {
    "dict with a list as key": "[{['type']: 'plate', 'id': 75}]",
    "dict with a dict as key": "[{{'a': 1}: 'plate'}]",
    "deeply nested brackets": "[" * 50_000 + "]" * 50_000,
    "deeply nested in an item": "[{'type': " + "[" * 5000 + "]" * 5000 + "}]",
    "unclosed nesting": "[{" * 50_000,
    "5,000-digit id": "[{'type': 'plate', 'id': " + "9" * 5000 + ", 'position': ['D4'], 'cardinal_direction': 'N'}]",
    "5,000-digit id string": "[{'type': 'plate', 'id': '" + "7" * 5000 + "', 'position': ['D4'], 'cardinal_direction': 'N'}]",
    "400-digit coordinate": "[{'type': 'plate', 'id': 75, 'position': [" + "9" * 400 + ", 0.5], 'rotation': 0}]",
    "400-digit rotation": "[{'type': 'plate', 'id': 75, 'position': [0.5, 0.5], 'rotation': " + "1" * 400 + "}]",
    "NaN": "[{'type': 'plate', 'id': 75, 'position': [NaN, 0.5], 'rotation': 0}]",
    "inf": "[{'type': 'plate', 'id': 75, 'position': [1e999, 0.5], 'rotation': -1e999}]",
    "huge text": "Sure. " * 100_000,
    "huge string value": "[{'type': '" + "a" * 150_000 + "', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]",
    "wrong types everywhere": "[{'type': 75, 'id': ['x'], 'position': {'a': 1}, 'cardinal_direction': 7}]",
    "number as key": "[{1: 'plate', 'id': 75}]",
    "item that is a list": "[{'type': 'plate'}, [1, 2], 'text']",
    "too many cells": "[{'type': 'plate', 'id': 75, 'position': [" + ", ".join(["'A1'"] * 5000) + "], 'cardinal_direction': 'N'}]",
    "long cell": "[{'type': 'plate', 'id': 75, 'position': ['" + "A" * 10_000 + "1'], 'cardinal_direction': 'N'}]",
    "repeated key": "[{'type': 'plate', 'id': 75, 'id': 76, 'position': ['D4'], 'cardinal_direction': 'N'}]",
    "bool id": "[{'type': 'plate', 'id': true, 'position': ['D4'], 'cardinal_direction': 'N'}]",
    "null byte and control chars": "[{'type': 'plate\x00', 'id': 75, 'position': ['D4\x07'], 'cardinal_direction': 'N'}]",
    "code": "[{'type': 'plate', 'id': __import__('os').system('true'), 'position': ['D4'], 'cardinal_direction': 'N'}]",
    "lone surrogate": "[{'type': '\udcff', 'id': 75}]",
    "empty": "",
}


@pytest.mark.parametrize("kind", ["grid", "unmarked"])
@pytest.mark.parametrize("name", list(HOSTILE))
def test_hostile_answers_are_counted_failures_never_exceptions(name, kind):
    try:
        answer = read_answer(HOSTILE[name], kind, CAT, G)
    except AnswerParseError as e:
        reason = str(e)
        assert reason and len(reason) <= 200 and "\n" not in reason, reason
    else:
        assert all(len(r) <= 200 for r in answer.item_errors)


@pytest.mark.parametrize("text", [None, 17, b"[]", ["a"], {"x": 1}])
def test_an_answer_that_is_not_text_is_a_failure(text):
    with pytest.raises(AnswerParseError, match="not text"):
        parse_answer(text, "grid", CAT, G)


def test_item_policy_drops_bad_items_and_keeps_the_rest():
    text = ("[" + PLATE + ", {'type': 'cup', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'},"  # id of a plate
            " {'type': 'cup', 'id': 999, 'position': ['A1'], 'cardinal_direction': 'N'},"  # unknown id
            " {'type': 'plate', 'id': 'seventy', 'position': ['A1'], 'cardinal_direction': 'N'},"  # id of another type
            " " + PLATE + ","  # duplicate id
            " {'type': 'cup', 'id': 0, 'position': ['Z9'], 'cardinal_direction': 'N'},"  # bad cell
            " {'type': 'cup', 'id': 0, 'position': ['A1'], 'cardinal_direction': 'up'}, " + FORK + "]")  # direction
    answer = read_answer(text, "grid", CAT, G)
    assert [it.id for it in answer.items] == [75, 25]
    assert answer.n_read == 8
    assert answer.item_errors == [
        "item 1: id 75 is a plate, not a cup", "item 2: unknown object id 999",
        "item 3: id must be an integer, got 'seventy'", "item 4: id 75 was already placed by an earlier item",
        "item 5: 'Z9' is not a cell of the 8x8 grid",
        "item 6: unknown cardinal direction 'up' (expected one of N, NE, E, SE, S, SW, W, NW)"]
    with pytest.raises(AnswerParseError, match=r"^no valid item \(item 0: unknown object id 999; item 1: "):
        read_answer("[{'type': 'cup', 'id': 999, 'position': ['A1'], 'cardinal_direction': 'N'}, "
                    "{'type': 'cup', 'id': 75, 'position': ['A1'], 'cardinal_direction': 'N'}]", "grid", CAT, G)
    assert read_answer("[]", "grid", CAT, G).items == []  # an empty list still places nothing, validly
    for nested in (HOSTILE["deeply nested brackets"], "[[[]]]", "{'a': []}"):  # but not one inside garbage
        with pytest.raises(AnswerParseError, match="no list of objects"):
            read_answer(nested, "grid", CAT, G)


# ----------------------------------------------------------------------------- a scriptable loopback server

class Server(Loopback):
    """HTTP on 127.0.0.1 speaking OpenAI chat completions. `script` entries (status, content_type, body
    bytes or a callable(request) -> bytes[, headers]) are consumed first, then `answer(request, i)` for
    choice i. Each request records its path, body and headers."""

    def __init__(self, answer=lambda req, i: GOOD):
        self.answer = answer
        super().__init__(self.reply)

    def reply(self, req):
        body = req["body"]
        texts = [self.answer(req, i) for i in range(body.get("n", 1))]
        return json_reply(200, chat_completion(body["model"], texts, completion_tokens=10))

    def fail(self, status, body=b'{"error": {"message": "oops"}}', ctype="application/json", times=1, headers=None):
        self.script += [(status, ctype, body, headers or {})] * times


@pytest.fixture
def server():
    s = Server()
    yield s
    s.close()


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path_factory.mktemp("ds") / "data")


def config(tmp_path, url, dataset_dir, **extra):
    cfg = {"method": "mogma", "dataset": str(dataset_dir), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "render_size": 64, "concurrency": 1, "backoff": 0,
           "max_retries": 2, "backend": {"name": "openai", "base_url": url, "timeout": 5},
           "model": {"name": "fake-model"}, "decoding": {"n": 3, "temperature": 1.0}}
    for k, v in extra.items():
        cfg[k] = {**cfg[k], **v} if isinstance(v, dict) and isinstance(cfg.get(k), dict) else v
    path = tmp_path / "zeroshot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def predict(path, capsys, *sets):
    code = cli_main(["predict", "--config", str(path), *[a for s in sets for a in ("--set", s)]])
    out, err = capsys.readouterr()
    return code, out, err


def ledger(tmp_path):
    return json.loads((tmp_path / "run" / "ledger.json").read_text())


def one_line_error(err):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("degusta: error: "), err
    assert "Traceback" not in err
    return lines[0]


# ----------------------------------------------------------------------------- item 1 + 2 end to end

def test_hostile_answers_through_a_run_and_its_cached_resume(tmp_path, dataset_dir, capsys):
    # the lone surrogate first; not the empty answer: a server's empty reply is a server fault, retried
    # (test_hardening_network.py), and a local model's a counted failure (test_hostile_answers_are_counted_...)
    texts = [t for t in list(HOSTILE.values())[::-1] if t]
    partial = f"[{PLATE}, {{'type': 'cup', 'id': 999, 'position': ['A1'], 'cardinal_direction': 'N'}}]"
    # each request gets 3 answers: two hostile ones and one with a bad item among good ones
    srv = Server(answer=lambda req, i: partial if i == 2 else texts[((len(srv.requests) - 1) * 2 + i) % len(texts)])
    try:
        path = config(tmp_path, srv.url, dataset_dir)
        code, out, err = predict(path, capsys)
        assert code == 0, err
        assert len(srv.requests) == 9
        preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
        for p in preds:
            d = p.diagnostics
            assert not p.failed and d["n_parsed"] >= 1 and d["n_items"] >= 2
            assert {"sample": 2, "reason": "item 1: unknown object id 999"} in d["item_errors"]
            assert d["n_item_errors"] == len(d["item_errors"])
            assert all(len(f["reason"]) < 250 for f in d["failures"])
        assert "mogma: 9 episodes, 0 failed (0.0%); samples: " in out and "items: " in out and "dropped" in out
        first = (tmp_path / "run" / "predictions.jsonl").read_text()
        led = ledger(tmp_path)
        assert led["item_errors"] >= 9 and led["items_read"] >= 18
        # resume: every answer (hostile ones included) comes from the cache, nothing is asked again
        code, out, err = predict(path, capsys)
        assert code == 0 and len(srv.requests) == 9, err
        strip = [{**json.loads(x), "diagnostics": {**json.loads(x)["diagnostics"], "cached": 0}} for x in
                 first.splitlines()]
        again = (tmp_path / "run" / "predictions.jsonl").read_text().splitlines()
        assert strip == [{**json.loads(x), "diagnostics": {**json.loads(x)["diagnostics"], "cached": 0}}
                         for x in again]
    finally:
        srv.close()


def test_answers_cached_before_this_version_resume_as_counted_failures(tmp_path, dataset_dir, capsys, server):
    """A cache filled with answers that once crashed `parse_answer`: resuming counts them, asks nothing."""
    path = config(tmp_path, server.url, dataset_dir, decoding={"n": 1})
    server.answer = lambda req, i: HOSTILE["5,000-digit id"]
    assert predict(path, capsys)[0] == 0 and len(server.requests) == 9
    db = sqlite3.connect(tmp_path / "run" / "responses_cache.sqlite")
    db.execute("UPDATE responses SET text = ?", ("[{'a': " * 5000,))  # a RecursionError before
    db.commit()
    db.close()
    code, out, err = predict(path, capsys)
    assert code == 0 and len(server.requests) == 9, err
    assert "9 episodes, 9 failed (100.0%); samples: 9 of 9 failed (100.0%)" in out
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert all(p.failed and p.diagnostics["failures"][0]["reason"].startswith("unparseable answer: ") for p in preds)


# ----------------------------------------------------------------------------- item 3: server faults

HTML = b"<html><body><h1>502 Bad Gateway</h1></body></html>"


@pytest.mark.parametrize("status, ctype, body", [
    (200, "text/html", HTML),                           # a proxy's page with status 200
    (200, "application/json", b'{"choices": [{"mess'),  # truncated JSON
    (200, "application/json", b'{"hello": "world"}'),   # JSON of another shape
    (200, "application/json", b'{"choices": [1, 2]}'),  # choices of the wrong type
    (502, "text/html", HTML),
    (429, "application/json", b'{"error": {"message": "slow down"}}'),
    (408, "application/json", b"{}"),
    (409, "application/json", b"{}"),
])
def test_transient_faults_are_retried(tmp_path, dataset_dir, server, capsys, status, ctype, body):
    server.fail(status, body, ctype)
    code, out, err = predict(config(tmp_path, server.url, dataset_dir), capsys)
    assert code == 0, err
    assert len(server.requests) == 10 and ledger(tmp_path)["retries"] == 1
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert not any(p.failed for p in preds)


def test_a_garbled_retry_after_header_is_ignored(tmp_path, dataset_dir, server, capsys):
    for value in ("Mon, 99 Foo 2024 99:99:99 GMT", "nan", "-5", "1e999"):
        server.fail(429, headers={"Retry-After": value, "retry-after-ms": value})
    code, out, err = predict(config(tmp_path, server.url, dataset_dir, max_retries=4), capsys)
    assert code == 0, err
    assert ledger(tmp_path)["retries"] == 4


def test_a_server_that_always_fails_gives_exit_2_and_no_result(tmp_path, dataset_dir, server, capsys):
    out_file = tmp_path / "run" / "predictions.jsonl"
    out_file.parent.mkdir()
    out_file.write_text("an earlier result\n")
    server.fail(500, b'{"error": {"message": "internal"}}', times=10_000)
    code, out, err = predict(config(tmp_path, server.url, dataset_dir), capsys)
    assert code == 2
    line = one_line_error(err)
    assert "episodes in a row got no answer" in line and "HTTP 500" in line and str(out_file) in line
    assert "re-run the same command" in line
    assert out_file.read_text() == "an earlier result\n", "the output must be left untouched"
    # it stops after 3 episodes in a row (1 + 2 retries each; the next one may have started meanwhile)
    assert 3 * 3 <= len(server.requests) <= 4 * 3
    led = ledger(tmp_path)
    assert led["episodes_done"] == 0 and led["stopped"].startswith("server: ") and led["failed_requests"] >= 3


def test_unreachable_server_gives_exit_2_and_writes_no_predictions(tmp_path, dataset_dir, capsys):
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()  # nothing listens there
    code, out, err = predict(config(tmp_path, f"http://127.0.0.1:{port}/v1", dataset_dir, max_retries=1), capsys)
    assert code == 2
    line = one_line_error(err)
    assert "cannot reach the server" in line and "got no answer" in line
    assert not (tmp_path / "run" / "predictions.jsonl").exists()


def test_a_rerun_asks_exactly_the_unanswered_episodes(tmp_path, dataset_dir, server, capsys):
    # episode 2's request fails 3 times (1 + 2 retries), then episode 6's: two unanswered episodes
    server.script = [server.reply({"body": {"n": 3, "model": "m"}})] + [(500, "application/json", b"{}")] * 3 + \
        [server.reply({"body": {"n": 3, "model": "m"}})] * 3 + [(503, "text/html", HTML)] * 3
    path = config(tmp_path, server.url, dataset_dir)
    code, out, err = predict(path, capsys)
    assert code == 2
    line = one_line_error(err)
    assert "zero-shot run incomplete: 2 of 9 episodes got no answer from the server after 2 retries" in line
    assert "ask only for the 2 unfinished episodes" in line
    assert not (tmp_path / "run" / "predictions.jsonl").exists()
    asked = [r["body"]["messages"][0]["content"] for r in server.requests]
    n_first = len(server.requests)
    code, out, err = predict(path, capsys)
    assert code == 0, err
    again = [r["body"]["messages"][0]["content"] for r in server.requests[n_first:]]
    assert len(again) == 2 and again == [asked[1], asked[7]]
    assert ledger(tmp_path)["samples_cached"] == 7 * 3


def test_a_permanent_refusal_is_a_counted_failure_not_a_server_fault(tmp_path, dataset_dir, server, capsys):
    server.fail(400, b'{"error": {"message": "context too long"}}')
    code, out, err = predict(config(tmp_path, server.url, dataset_dir), capsys)
    assert code == 0, err
    assert "9 episodes, 1 failed (11.1%)" in out
    assert len(server.requests) == 9  # a 400 is not retried


def test_retry_waits_are_bounded_and_injectable(tmp_path, dataset_dir, server, monkeypatch, capsys):
    from degusta_learn.prompting import runner
    waits = []
    monkeypatch.setattr(runner.ZeroShotRun, "sleep", lambda self, s: waits.append(s))
    server.fail(503, times=3)
    path = config(tmp_path, server.url, dataset_dir, backoff=10, backoff_max=30, max_retries=3)
    assert predict(path, capsys)[0] == 0
    assert len(waits) == 3 and 5 <= waits[0] <= 15 and 10 <= waits[1] <= 30 and waits[2] <= 30


# ----------------------------------------------------------------------------- item 4: secrets

def test_an_echoed_key_is_never_written(tmp_path, dataset_dir, capsys, monkeypatch):
    monkeypatch.setenv("MY_VLM_KEY", KEY)

    def echo(req):  # the answer text carries every request header, the key included
        return json.dumps({"note": f"x-api-key: {KEY}; api-key={KEY}", "headers": req["headers"]})
    srv = Server(answer=lambda req, i: GOOD + "\n" + echo(req))
    try:
        srv.fail(500, lambda req: json.dumps({"error": {"message": echo(req)}}).encode())
        srv.fail(400, lambda req: json.dumps({"error": {"message": echo(req)}}).encode())
        path = config(tmp_path, srv.url, dataset_dir, backend={"api_key_env": "MY_VLM_KEY"})
        code, out, err = predict(path, capsys)
        assert code == 0, err
        sent = {k.lower(): v for k, v in srv.requests[0]["headers"].items()}
        assert sent["authorization"] == f"Bearer {KEY}"
        srv.fail(500, lambda req: json.dumps({"error": {"message": echo(req)}}).encode(), times=10_000)  # then a failed run: the message echoes too
        code, out2, err2 = predict(path, capsys, "decoding.n=4")
        assert code == 2 and "***" in err2
        written = [p for p in tmp_path.rglob("*") if p.is_file()]
        assert {"responses_cache.sqlite", "ledger.json", "predictions.jsonl"} <= {p.name for p in written}
        for p in written:
            assert KEY.encode() not in p.read_bytes(), f"the API key leaked into {p}"
        assert KEY not in out + err + out2 + err2
        cache = ResponseCache(tmp_path / "run" / "responses_cache.sqlite", readonly=True)
        texts = [c.text for c in cache.get_many(_all_keys(cache)).values()]
        cache.close()
        assert texts and all('"authorization": "bearer ***"' in t.lower() for t in texts)
    finally:
        srv.close()


def _all_keys(cache):
    return [k for (k,) in cache._db.execute("SELECT key FROM responses")]


def test_redact_covers_header_forms(monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", KEY)
    assert redact(f"Authorization: Bearer {KEY}") == "Authorization: Bearer ***"
    assert redact("{'x-api-key': 'abcdef123'}") == "{'x-api-key': '***'}"
    assert redact('"api-key": "zzz-9"') == '"api-key": "***"'
    assert redact("GET /v1?key=1&api_key=Q7w&x=2") == "GET /v1?key=***&api_key=***&x=2"  # a key= query value too
    assert redact(f"the key is {KEY}.") == "the key is ***."
    assert redact("sk-ant-api03-abcdEFGH") == "***"
    assert redact("an answer without secrets: [1, 2]") == "an answer without secrets: [1, 2]"
    assert redact(None) is None


# ----------------------------------------------------------------------------- item 8: the cache file

@pytest.mark.parametrize("what", ["one byte", "text file", "folder", "other sqlite"])
def test_a_path_that_is_not_our_cache_is_refused_untouched(tmp_path, dataset_dir, server, capsys, what):
    target = tmp_path / "mine.sqlite"
    if what == "one byte":
        target.write_bytes(b"x")
    elif what == "text file":
        target.write_text("my notes\n" * 100)
    elif what == "folder":
        target.mkdir()
    else:
        db = sqlite3.connect(target)
        db.execute("CREATE TABLE notes (x)")
        db.commit()
        db.close()
    before = target.read_bytes() if target.is_file() else None
    path = config(tmp_path, server.url, dataset_dir, cache=str(target))
    for dry in ([], ["--dry-run"]):
        code = cli_main(["predict", "--config", str(path), *dry])
        line = one_line_error(capsys.readouterr().err)
        assert code == 2 and f"cache: {target}" in line and "left untouched" in line
    assert server.requests == []
    if before is not None:
        assert target.read_bytes() == before
    assert not (tmp_path / "run" / "predictions.jsonl").exists()


# ----------------------------------------------------------------------------- item 12: kill window

def test_an_answer_is_committed_before_it_is_parsed(tmp_path, dataset_dir, server, monkeypatch, capsys):
    """A crash (here Ctrl-C) right after the answer arrives, before parsing: the re-run does not pay again."""
    from degusta_learn.prompting import runner
    real = runner.read_answer
    calls = {"n": 0}

    def dies_on_first(*a, **k):
        calls["n"] += 1
        if calls["n"] == 1:
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(runner, "read_answer", dies_on_first)
    path = config(tmp_path, server.url, dataset_dir)
    assert predict(path, capsys)[0] == 130
    first = len(server.requests)
    assert first >= 1
    db = sqlite3.connect(tmp_path / "run" / "responses_cache.sqlite")
    assert db.execute("SELECT count(*) FROM responses").fetchone()[0] == 3 * first
    db.close()
    assert predict(path, capsys)[0] == 0
    assert len(server.requests) == 9, "no episode may be asked twice"


class PerSample(AnthropicBackend):
    """A one-answer-per-request backend (like anthropic / gemini) that checks the cache between calls."""

    name, calls = "anthropic", []
    cache_path = None

    @classmethod
    def from_config(cls, cfg, model, decoding=None, grid=None, catalog=None):
        obj = cls.__new__(cls)
        obj.model = model.name
        return obj

    def complete(self, prompt, n, temperature, max_tokens, seed=None):
        db = sqlite3.connect(PerSample.cache_path)
        stored = db.execute("SELECT count(*) FROM responses").fetchone()[0]
        db.close()
        PerSample.calls.append((n, stored))
        return [Completion(GOOD, 100, 10)]


def test_per_sample_backends_cache_each_answer_at_once(tmp_path, dataset_dir, monkeypatch, capsys):
    monkeypatch.setitem(BACKENDS, "anthropic", "test_hardening_prompting:PerSample")
    PerSample.calls = []
    PerSample.cache_path = tmp_path / "run" / "responses_cache.sqlite"
    path = config(tmp_path, None, dataset_dir, backend={"name": "anthropic", "base_url": None}, model={"name": "fake"})
    code, out, err = predict(path, capsys)
    assert code == 0, err
    assert PerSample.calls == [(1, i) for i in range(27)]  # one sample a request, each cached before the next


class Broken(PerSample):
    """A backend whose client library raises something of its own (or a local model runs out of memory)."""

    name = "openai"

    def complete(self, prompt, n, temperature, max_tokens, seed=None):
        raise RuntimeError("CUDA out of memory")


def test_an_unexpected_backend_exception_stops_the_run_with_one_line(tmp_path, dataset_dir, monkeypatch, capsys):
    monkeypatch.setitem(BACKENDS, "openai", "test_hardening_prompting:Broken")
    code, out, err = predict(config(tmp_path, "http://127.0.0.1:9/v1", dataset_dir), capsys)
    assert code == 2
    line = one_line_error(err)
    assert "openai: RuntimeError: CUDA out of memory" in line and "re-run the same command" in line
    assert not (tmp_path / "run" / "predictions.jsonl").exists()
