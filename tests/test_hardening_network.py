"""Network hardening of the zero-shot backends (docs/reliability.md, "Network"), against real loopback servers
that misbehave below JSON (tests/loopback.py):

1. Deadlines: every request of every remote backend (openai, anthropic, gemini) ends `backend.timeout` after it
   starts, whatever the server trickles (status line, headers, body byte by byte, an endless chunked body, nothing);
   the run retries it, then fails with one line; Ctrl-C / SIGTERM never wait on a stalled request.
2. Sizes: a reply is at most MAX_REPLY_BYTES on the wire and decoded (gzip / deflate bombs, double encodings, a
   Content-Length lie, an endless body, an encoding not asked for: refused before being held), honest compressed
   replies still decode; an answer longer than the parser reads is stored cut with a note and counted failed; a
   predictions line always fits what `read_predictions` reads.
3. Signals: SIGTERM (143) / Ctrl-C (130) during a paid run, with requests stalled, end at once with the ledger of
   the requests already paid and their answers cached.
4. Compare: two paid methods keep one ledger each, and each one's cost (USD, requests) is in metrics.json and the
   report.
5. Empty completions (no choices, a null message, empty or blank text, for each backend's reply shape) are server
   faults: retried with the backoff, counted in the ledger, then an unanswered episode, never a failed sample.

Every case is bounded by the test itself (`bounded`, timeouts on subprocesses): there is no pytest-timeout plugin.
"""

from __future__ import annotations

import _thread
import gzip
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import tracemalloc
import zlib
from pathlib import Path

import pytest
import yaml
from conftest import make_small_dataset
from loopback import (
    Loopback,
    chat_completion,
    compressed,
    endless_chunks,
    gzip_bomb,
    json_reply,
    stall,
    trickle_body,
    trickle_headers,
    trickle_status,
)

from degusta_learn.cli import main as cli_main
from degusta_learn.prompting.backends.base import BackendError, backend_config, make_backend
from degusta_learn.prompting.backends.transport import MAX_REPLY_BYTES, environment_proxies, guarded_client
from degusta_learn.vlm.settings import ModelSettings
from degusta_learn.prompting.runner import LINE_BUDGET, cut_answer, fit_line
from degusta_learn.scene import Prediction, default_catalog, make_episodes, read_predictions, save_dataset
from degusta_learn.task.answers import MAX_CHARS
from degusta_learn.task.prompt import Prompt

CAT = default_catalog()
GOOD = ("[{'type': 'plate', 'id': 75, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}, "
        "{'type': 'fork', 'id': 25, 'position': ['C4'], 'cardinal_direction': 'N'}]")
T = 0.3  # backend.timeout of the deadline cases, seconds
LIMIT = 15.0  # no case may take longer: a hang fails the test instead of holding the suite
BACKENDS = ("openai", "anthropic", "gemini")
PROMPT = Prompt(method="louma", parts=["Set the table."])


@pytest.fixture(autouse=True)
def keys(monkeypatch):
    monkeypatch.setenv("ANTHROPIC_API_KEY", "test-key-anthropic")
    monkeypatch.setenv("GEMINI_API_KEY", "test-key-gemini")
    for var in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(var, raising=False)


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path_factory.mktemp("ds") / "data")


def bounded(fn, limit: float = LIMIT) -> dict:
    """Run fn() in a daemon thread: {"value" or "error", "seconds"}; fails the test (never hangs) past `limit`."""
    box: dict = {}

    def go():
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: B036 (the case's outcome, whatever it is)
            box["error"] = e
    thread = threading.Thread(target=go, daemon=True)
    start = time.monotonic()
    thread.start()
    thread.join(limit)
    assert not thread.is_alive(), f"still running after {limit} s: a hang"
    box["seconds"] = time.monotonic() - start
    return box


# ----------------------------------------------------------------------------- each backend's reply shapes

def good_body(backend: str, texts: list[str]) -> dict:
    if backend == "openai":
        return chat_completion("m", texts, prompt_tokens=100)
    if backend == "anthropic":
        return {"id": "msg", "type": "message", "role": "assistant", "model": "m", "stop_reason": "end_turn",
                "content": [{"type": "text", "text": texts[0]}], "usage": {"input_tokens": 100, "output_tokens": 10}}
    return {"candidates": [{"content": {"parts": [{"text": texts[0]}], "role": "model"}, "finishReason": "STOP"}],
            "usageMetadata": {"promptTokenCount": 100, "candidatesTokenCount": 10}}


EMPTY = {  # 200 replies without an answer, in each backend's reply shape
    "openai": {"choices []": {"choices": [], "usage": {"prompt_tokens": 100, "completion_tokens": 0}},
               "message null": {"choices": [{"index": 0, "message": None, "finish_reason": "stop"}]},
               "no message": {"choices": [{"index": 0, "finish_reason": "stop"}]},
               "content empty": chat_completion("m", [""]),
               "content blank": chat_completion("m", [" \n\t"]),
               "content null": {"choices": [{"index": 0, "message": {"role": "assistant", "content": None}}]}},
    "anthropic": {"content []": {"id": "x", "type": "message", "role": "assistant", "model": "m", "content": []},
                  "text empty": {"id": "x", "type": "message", "role": "assistant", "model": "m",
                                 "content": [{"type": "text", "text": ""}]},
                  "content null": {"id": "x", "type": "message", "role": "assistant", "model": "m", "content": None},
                  "no content": {"id": "x", "type": "message", "role": "assistant", "model": "m"}},
    "gemini": {"candidates []": {"candidates": []},
               "no candidates": {"usageMetadata": {"promptTokenCount": 100}},
               "parts []": {"candidates": [{"content": {"parts": [], "role": "model"}}]},
               "text empty": {"candidates": [{"content": {"parts": [{"text": ""}], "role": "model"}}]},
               "content null": {"candidates": [{"content": None, "finishReason": "SAFETY"}]}},
}


def base_url(backend: str, srv: Loopback) -> str:
    return srv.url if backend == "openai" else srv.root


class Server(Loopback):
    """Answers every backend's request shape with a good answer (one choice per `n`), after its `script`."""

    def __init__(self, backend: str = "openai", text: str = GOOD):
        self.backend, self.text = backend, text
        super().__init__(lambda req: json_reply(200, good_body(
            self.backend, [self.text] * ((req["body"] or {}).get("n") or 1))))


def client(backend: str, srv: Loopback, timeout: float = T):
    return make_backend(backend_config(backend, base_url=base_url(backend, srv), timeout=timeout), ModelSettings(name="m"))


def complete(backend: str, reply, timeout: float = T) -> dict:
    srv = Loopback(lambda req: reply)
    try:
        be = client(backend, srv, timeout)
        return bounded(lambda: be.complete(PROMPT, 1, 1.0, 64))
    finally:
        srv.close()


# ----------------------------------------------------------------------------- 1. deadlines

TRICKLES = {
    "status line a byte at a time": lambda: trickle_status(0.02),
    "a header that never ends": lambda: trickle_headers(0.02),
    "the body a byte at a time": lambda: trickle_body(json.dumps(good_body("openai", [GOOD])).encode(), 0.02),
    "an endless chunked body, slowly": lambda: endless_chunks(b" " * 8, 0.02),
    "no byte at all": lambda: stall(),
}


@pytest.mark.parametrize("case", list(TRICKLES))
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_request_ends_at_its_deadline_whatever_the_server_trickles(backend, case):
    got = complete(backend, TRICKLES[case]())
    assert got["seconds"] < T + 1.5, got
    e = got.get("error")
    assert isinstance(e, BackendError) and e.retryable and not e.fatal, got
    assert f"within the {T:g} s deadline" in str(e) and len(str(e).splitlines()) == 1, str(e)


@pytest.mark.parametrize("case", ["status line a byte at a time", "the body a byte at a time",
                                  "an endless chunked body, slowly"])
def test_a_run_against_a_trickling_server_retries_then_stops_with_one_line(tmp_path, dataset_dir, capsys, case):
    srv = Loopback(lambda req: TRICKLES[case]())
    try:
        got = bounded(lambda: predict(config(tmp_path, srv.url, dataset_dir), capsys))
    finally:
        srv.close()
    code, out, err = got["value"]
    assert code == 2 and got["seconds"] < 10, (got["seconds"], err)
    line = one_line_error(err)
    assert "episodes in a row got no answer" in line and "deadline" in line, line
    led = ledger(tmp_path)
    assert led["retries"] >= 3 and led["failed_requests"] >= 3 and led["requests"] == 0
    assert not (tmp_path / "run" / "predictions.jsonl").exists()


@pytest.mark.parametrize("fault", ["status line a byte at a time", "the body a byte at a time", "gzip bomb"])
def test_a_fault_cut_at_the_deadline_is_retried_on_a_fresh_connection(tmp_path, dataset_dir, capsys, fault):
    srv = Server()
    srv.script.append(compressed(gzip_bomb(256), "gzip") if fault == "gzip bomb" else TRICKLES[fault]())
    try:
        got = bounded(lambda: predict(config(tmp_path, srv.url, dataset_dir), capsys))
    finally:
        srv.close()
    code, out, err = got["value"]
    assert code == 0, err
    assert ledger(tmp_path)["retries"] == 1 and len(srv.requests) == 10
    assert not any(p.failed for p in read_predictions(tmp_path / "run" / "predictions.jsonl", CAT))


def test_redirects_share_one_deadline():
    hops = []

    def reply(req):
        hops.append(req["path"])
        return 307, "text/plain", b"", {"Location": f"/v1/hop{len(hops)}"}
    srv = Loopback(reply)
    try:
        srv.respond = lambda req: (hops.append(req["path"]), time.sleep(0.05),
                                   (307, "text/plain", b"", {"Location": f"/v1/hop{len(hops)}"}))[-1]
        http = guarded_client(0.4)
        got = bounded(lambda: http.get(srv.url + "/start"))
    finally:
        srv.close()
    assert "deadline" in str(got.get("error")) and got["seconds"] < 1.5, got  # 20 redirects would take 1 s + each


# ----------------------------------------------------------------------------- 2. sizes

def _twice_gzipped() -> bytes:
    return gzip.compress(gzip_bomb(1024), 1)


BOMBS = {
    "gzip bomb (1 GiB inflated)": lambda: compressed(gzip_bomb(1024, 31), "gzip"),
    "deflate bomb, zlib-wrapped": lambda: compressed(gzip_bomb(1024, 15), "deflate"),
    "deflate bomb, raw": lambda: compressed(gzip_bomb(1024, -15), "deflate"),
    "gzip inside gzip": lambda: compressed(_twice_gzipped(), "gzip, gzip"),
    "an endless chunked body, fast": lambda: endless_chunks(b" " * 65536),
    "Content-Length of 10 GiB": lambda: compressed(b"{}", "identity", content_length=10 << 30),
    "plain 40 MiB body": lambda: compressed(b" " * (40 << 20), "identity"),
    "an encoding not asked for (br)": lambda: compressed(b"\x1b\x00garbage", "br"),
}


@pytest.mark.parametrize("case", list(BOMBS))
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_reply_too_big_is_refused_before_it_is_held(backend, case):
    reply = BOMBS[case]()
    srv = Loopback(lambda req: reply)
    try:
        be = client(backend, srv, timeout=10)  # the client library imported and built before memory is traced
        tracemalloc.start()
        try:
            got = bounded(lambda: be.complete(PROMPT, 1, 1.0, 64))
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    finally:
        srv.close()
    e = got.get("error")
    assert isinstance(e, BackendError) and e.retryable and not e.fatal, got
    assert "refused" in str(e) and len(str(e).splitlines()) == 1, str(e)
    assert got["seconds"] < 5 and peak < 3 * MAX_REPLY_BYTES, (got["seconds"], peak)


@pytest.mark.parametrize("encoding", ["gzip", "deflate (zlib)", "deflate (raw)", "gzip, gzip", "identity"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_honest_compressed_replies_still_decode(backend, encoding):
    body = json.dumps(good_body(backend, [GOOD])).encode()
    wire = {"gzip": lambda b: gzip.compress(b), "deflate (zlib)": zlib.compress,
            "deflate (raw)": lambda b: (lambda c: c.compress(b) + c.flush())(zlib.compressobj(6, zlib.DEFLATED, -15)),
            "gzip, gzip": lambda b: gzip.compress(gzip.compress(b)), "identity": lambda b: b}[encoding](body)
    got = complete(backend, compressed(wire, encoding.split(" (")[0]))
    assert [c.text for c in got.get("value", [])] == [GOOD], got


def test_an_answer_longer_than_the_parser_reads_is_stored_cut_and_counted_failed(tmp_path, dataset_dir, capsys):
    long = GOOD + " lorem" * 300_000  # 1.8 M characters: a reply well under MAX_REPLY_BYTES
    srv = Server(text=long)
    try:
        code, out, err = predict(config(tmp_path, srv.url, dataset_dir), capsys)
        assert code == 0, err
        assert predict(config(tmp_path, srv.url, dataset_dir), capsys)[0] == 0 and len(srv.requests) == 9  # cached
    finally:
        srv.close()
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)  # the toolkit reads its own file
    for p in preds:
        assert p.failed and len(p.diagnostics["responses"][0]) < MAX_CHARS + 100
        assert p.diagnostics["responses"][0].endswith(f"{len(long)} characters in all, the first {MAX_CHARS} kept]")
        assert p.diagnostics["failures"] == [{"sample": 0, "reason": f"unparseable answer: {len(long)} characters "
                                              f"long (at most {MAX_CHARS} are read; the first are kept in the "
                                              "responses)"}]
    db = sqlite3.connect(tmp_path / "run" / "responses_cache.sqlite")
    assert db.execute("SELECT max(length(text)) FROM responses").fetchone()[0] < MAX_CHARS + 100  # cut before kept
    db.close()


def test_a_replayed_answer_is_cut_the_same_way_and_an_empty_one_stays_a_counted_failure(tmp_path, dataset_dir,
                                                                                        capsys):
    from degusta_learn.scene import load_dataset

    eps = make_episodes(load_dataset(dataset_dir), 2, "all")
    rec = tmp_path / "answers.jsonl"
    rec.write_text("".join(json.dumps({"episode": e.id, "sample": 0, "text": GOOD + " " * (3 << 20) if i % 2 else ""})
                           + "\n" for i, e in enumerate(eps)))
    code, out, err = predict(config(tmp_path, None, dataset_dir, backend={"name": "replay", "path": str(rec)},
                                    model={"name": "replay"}), capsys)
    assert code == 0, err
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert all(p.failed for p in preds)  # a local / recorded empty answer is the model's: no retry
    assert all(len(p.diagnostics["responses"][0]) < MAX_CHARS + 100 for p in preds)
    assert ledger(tmp_path)["retries"] == 0 and ledger(tmp_path)["empty_answers"] == 0


def test_a_prediction_line_always_fits_what_read_predictions_reads(tmp_path):
    astral = "\U0001F37D" * 100_000  # 12 bytes a character once JSON-escaped
    diag = {"responses": [GOOD + astral] * 12, "greedy_response": GOOD + astral,
            "item_errors": [{"sample": 0, "reason": "x" * 200}] * 5000, "n_item_errors": 5000}
    pred = Prediction("p000/t2/k2", "p000", 2, "mogma", [], failed=True, diagnostics=diag)
    budget = 4 << 20
    fitted = fit_line(pred, budget=budget)
    assert len(json.dumps(fitted.to_json())) <= budget
    d = fitted.diagnostics
    assert d["line_cut"]["bytes_before"] > budget and d["n_item_errors"] == 5000 and len(d["item_errors"]) == 100
    assert all(r.endswith("kept]") and f"{len(GOOD) + 100_000} characters in all" in r for r in d["responses"])
    assert LINE_BUDGET * 2 <= 64 * 2**20  # the real budget leaves read_predictions' bound room
    assert cut_answer(cut_answer("a" * 500, 100), 10).startswith("a" * 10 + "\n[degusta: answer cut here; 500 ")


# ----------------------------------------------------------------------------- 5. empty completions

@pytest.mark.parametrize("backend, shape", [(b, s) for b in BACKENDS for s in EMPTY[b]])
def test_an_empty_completion_is_a_server_fault_retried_with_the_backoff(tmp_path, dataset_dir, capsys, monkeypatch,
                                                                        backend, shape):
    from degusta_learn.prompting import runner
    waits = []
    monkeypatch.setattr(runner.ZeroShotRun, "sleep", lambda self, s: waits.append(s))
    srv = Server(backend)
    srv.script.append(json_reply(200, EMPTY[backend][shape]))
    try:
        got = bounded(lambda: predict(config(tmp_path, base_url(backend, srv), dataset_dir, backoff=0.5,
                                             backend={"name": backend}), capsys))
    finally:
        srv.close()
    code, out, err = got["value"]
    assert code == 0, err
    assert len(waits) == 1 and 0.25 <= waits[0] <= 0.75  # the backoff, as for any server fault
    led = ledger(tmp_path)
    assert led["retries"] == 1 and led["empty_answers"] == 1 and led["requests"] == 10 and len(srv.requests) == 10
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert not any(p.failed or p.diagnostics["failures"] for p in preds)


@pytest.mark.parametrize("shape", ["choices []", "message null", "content blank"])
def test_a_server_that_only_answers_empty_gives_exit_2_and_no_predictions(tmp_path, dataset_dir, capsys, shape):
    srv = Loopback(lambda req: json_reply(200, EMPTY["openai"][shape]))
    try:
        got = bounded(lambda: predict(config(tmp_path, srv.url, dataset_dir), capsys))
    finally:
        srv.close()
    code, out, err = got["value"]
    assert code == 2
    line = one_line_error(err)
    assert "episodes in a row got no answer" in line and "answered 200 with" in line and "server fault" in line
    led = ledger(tmp_path)
    assert led["failed_requests"] >= 3 and led["empty_answers"] >= 6 and led["episodes_unanswered"] >= 3
    assert not (tmp_path / "run" / "predictions.jsonl").exists()


def test_empty_choices_among_good_ones_are_asked_again(tmp_path, dataset_dir, capsys):
    def reply(req):  # of n > 1 choices, the last one empty
        n = req["body"]["n"]
        return json_reply(200, chat_completion("m", [GOOD] * (n - 1) + [""] if n > 1 else [GOOD]))
    srv = Loopback(reply)
    try:
        code, out, err = predict(config(tmp_path, srv.url, dataset_dir, decoding={"n": 3}), capsys)
    finally:
        srv.close()
    assert code == 0, err
    assert [r["body"]["n"] for r in srv.requests] == [3, 1] * 9  # the empty one asked again, alone
    led = ledger(tmp_path)
    assert led["empty_answers"] == 9 and led["retries"] == 0 and led["samples_received"] == 27
    preds = read_predictions(tmp_path / "run" / "predictions.jsonl", CAT)
    assert all(p.diagnostics["n_parsed"] == 3 and not p.diagnostics["failures"] for p in preds)


# ----------------------------------------------------------------------------- 3. signals

PRICES = {"m": [1000.0, 2000.0]}  # USD per 1M tokens: a loopback model priced like a paid one
PER_REQUEST = 100 * 1000 / 1e6 + 10 * 2000 / 1e6  # chat_completion's usage (100 in, 10 out) at PRICES


def answers_then_stalls(k: int) -> Loopback:
    """Answers the first `k` requests, then holds every later one without a byte (until the test ends)."""
    srv = Loopback(lambda req: json_reply(200, chat_completion("m", [GOOD] * req["body"]["n"], prompt_tokens=100))
                   if len(srv.requests) <= k else stall())
    return srv


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_during_a_paid_run_exits_at_once_with_the_ledger_of_what_was_paid(tmp_path, dataset_dir, sig,
                                                                                   status):
    srv = answers_then_stalls(2)
    path = config(tmp_path, srv.url, dataset_dir, concurrency=2, prices=PRICES, backend={"timeout": 60})
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "degusta_learn.cli", "predict", "--config", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 60
        while len(srv.requests) < 4 and time.monotonic() < deadline and proc.poll() is None:  # 2 paid, 2 stalled
            time.sleep(0.05)
        assert len(srv.requests) == 4, f"the run never reached its stalled requests ({len(srv.requests)})"
        time.sleep(0.2)
        proc.send_signal(sig)
        start = time.monotonic()
        out, err = proc.communicate(timeout=10)
        took = time.monotonic() - start
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        srv.close()
    assert proc.returncode == status and took < 5, (proc.returncode, took, err[-500:])
    assert err.strip().splitlines()[-1].startswith("degusta: ") and "Traceback" not in err, err[-500:]
    led = ledger(tmp_path)
    assert led["requests"] == 2 and led["samples_received"] == 2
    assert led["cost_usd"] == pytest.approx(2 * PER_REQUEST)
    assert led["stopped"] == ("terminated (SIGTERM)" if sig == signal.SIGTERM else "interrupted")
    db = sqlite3.connect(tmp_path / "run" / "responses_cache.sqlite")
    assert db.execute("SELECT count(*) FROM responses").fetchone()[0] == 2  # the paid answers, kept
    db.close()
    assert not (tmp_path / "run" / "predictions.jsonl").exists()


def test_ctrl_c_in_process_does_not_wait_on_a_stalled_worker(tmp_path, dataset_dir, capsys):
    srv = answers_then_stalls(1)
    path = config(tmp_path, srv.url, dataset_dir, concurrency=1, prices=PRICES, backend={"timeout": 60})

    def interrupt_when_stalled():
        deadline = time.monotonic() + 30
        while len(srv.requests) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.2)
        _thread.interrupt_main()
    threading.Thread(target=interrupt_when_stalled, daemon=True).start()
    start = time.monotonic()
    try:
        code, out, err = predict(path, capsys)  # in the main thread, where Ctrl-C lands
    finally:
        srv.close()
    took = time.monotonic() - start
    assert code == 130 and took < 20, (code, took, err)
    assert ledger(tmp_path)["requests"] == 1 and ledger(tmp_path)["stopped"] == "interrupted"


# ----------------------------------------------------------------------------- 4. compare: one ledger per method

def test_compare_keeps_one_ledger_per_paid_method_and_reports_each_cost(tmp_path, dataset_dir, capsys):
    srv = Server()
    fail = Loopback(lambda req: json_reply(500, {"error": {"message": "down"}}))
    try:
        methods = []
        for name, method, url in [("paid_a", "mogma", srv.url), ("paid_b", "logma", srv.url),
                                  ("paid_down", "mogma", fail.url)]:
            cfg = config(tmp_path / name, url, dataset_dir, method=method, prices=PRICES)
            methods.append({"name": name, "config": str(cfg)})
        cmp = tmp_path / "cmp.yaml"
        cmp.write_text(yaml.safe_dump({"dataset": str(dataset_dir), "out": str(tmp_path / "report"), "contexts": [2],
                                       "split": "all", "n_bootstrap": 50, "qualitative": 0, "render_size": 64,
                                       "methods": methods}))
        got = bounded(lambda: (cli_main(["compare", "--config", str(cmp)]), capsys.readouterr()), limit=60)
        code, _ = got["value"]
        assert code == 3  # paid_down failed; the others are reported
        preds = tmp_path / "report" / "predictions"
        assert not (preds / "ledger.json").exists()
        for name, method, requests in [("paid_a", "mogma", 9), ("paid_b", "logma", 9)]:
            led = json.loads((preds / f"{name}_k2.ledger.json").read_text())
            assert led["method"] == method and led["requests"] == requests
        down = json.loads((preds / "paid_down_k2.ledger.json").read_text())  # a failed run's spend is kept too
        assert down["requests"] == 0 and down["failed_requests"] >= 3
        for rerun in (False, True):  # the second compare reuses both files: their ledgers still say what they cost
            metrics = json.loads((tmp_path / "report" / "metrics.json").read_text())["methods"]
            for name in ("paid_a", "paid_b"):
                assert metrics[name]["cost_usd_total"] == pytest.approx(9 * PER_REQUEST)
                assert metrics[name]["requests"] == 9 and metrics[name]["cost"]["cost_usd"] == pytest.approx(1.08)
            report = (tmp_path / "report" / "report.md").read_text()
            assert "| requests |" in report and report.count(f"| {9 * PER_REQUEST:g} | 9 |") == 2
            if not rerun:
                before = len(srv.requests)
                assert bounded(lambda: (cli_main(["compare", "--config", str(cmp)]), capsys.readouterr()),
                               limit=60)["value"][0] == 3
                assert len(srv.requests) == before  # nothing paid twice
    finally:
        srv.close()
        fail.close()


# ----------------------------------------------------------------------------- the client itself

def test_environment_proxies_are_honoured_and_no_proxy_bypasses_them(monkeypatch):
    srv = Loopback(lambda req: json_reply(200, {"ok": True}))
    try:
        monkeypatch.setenv("HTTP_PROXY", "http://127.0.0.1:9")  # nothing listens there: a request through it fails
        monkeypatch.setenv("NO_PROXY", "example.com,127.0.0.1")
        assert environment_proxies()["all://127.0.0.1"] is None
        assert guarded_client(2).get(srv.url + "/x").json() == {"ok": True}
        monkeypatch.setenv("NO_PROXY", "example.com")
        got = bounded(lambda: guarded_client(2).get(srv.url + "/x"))
        assert "error" in got and srv.requests[1:] == []  # went to the (dead) proxy, not to the server
    finally:
        srv.close()


# ----------------------------------------------------------------------------- helpers

def config(tmp_path: Path, url, dataset_dir, **extra) -> Path:
    cfg = {"method": "mogma", "dataset": str(dataset_dir), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "render_size": 64, "concurrency": 1, "backoff": 0,
           "max_retries": 1, "backend": {"name": "openai", "base_url": url, "timeout": T}, "model": {"name": "m"},
           "decoding": {"n": 1, "temperature": 1.0}}
    for k, v in extra.items():
        cfg[k] = {**cfg[k], **v} if isinstance(v, dict) and isinstance(cfg.get(k), dict) else v
    if cfg["backend"]["name"] == "replay":
        cfg["backend"] = {k: v for k, v in cfg["backend"].items() if k in ("name", "path")}
    elif cfg["backend"].get("base_url") is None and url is not None:
        cfg["backend"]["base_url"] = url
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "zeroshot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def predict(path, capsys):
    code = cli_main(["predict", "--config", str(path)])
    out, err = capsys.readouterr()
    return code, out, err


def ledger(tmp_path) -> dict:
    return json.loads((tmp_path / "run" / "ledger.json").read_text())


def one_line_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("degusta: error: ") and "Traceback" not in err, err
    return lines[0]
