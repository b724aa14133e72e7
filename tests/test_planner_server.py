"""`degusta serve`'s app over a real loopback socket (uvicorn in a thread, port 0): a valid request, malformed ones (4xx
with the CLI's line, the server keeps serving), oversized bodies (413 before parsing), 8 concurrent clients, a planner
fault (500, one line), /health and the OpenAPI description."""

from __future__ import annotations

import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import jsonschema
import pytest
from conftest import make_small_dataset

from degusta_learn.cli import main
from degusta_learn.planner import MAX_REQUEST_BYTES, Planner
from degusta_learn.planner.schema import PLAN_SCHEMA
from degusta_learn.planner.server import create_app
from degusta_learn.scene import make_episodes, save_dataset

TIMEOUT = httpx.Timeout(30.0, connect=5.0)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    import uvicorn

    root = save_dataset(make_small_dataset(), tmp_path_factory.mktemp("serve") / "data")
    planner = Planner.from_config(None, ["method=consensus", f"dataset={root}"], read_paths=False)
    server = uvicorn.Server(uvicorn.Config(create_app(planner), host="127.0.0.1", port=0, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
        time.sleep(0.02)
    port = server.servers[0].sockets[0].getsockname()[1]
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=TIMEOUT) as client:
        yield client, planner, root
    server.should_exit = True
    thread.join(10)


def _request(planner, i: int) -> dict:
    ep = make_episodes(planner.dataset, 2, "all")[i]
    return {"participant": ep.participant, "trials": list(ep.context),
            "table": planner.dataset.arrangement(ep.participant, ep.target).table}


def test_a_valid_request_gets_the_plan(served):
    client, planner, _ = served
    r = client.post("/plan", json=_request(planner, 0))
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    jsonschema.validate(r.json(), PLAN_SCHEMA)
    assert r.json() == json.loads(json.dumps(planner.plan(_request(planner, 0)).to_json()))
    assert r.json()["method"] == "consensus" and r.json()["steps"]


def test_a_malformed_request_gets_400_with_the_line_the_cli_prints(served, tmp_path, capsys):
    client, _, root = served
    cases = [b'{"table": {"width": 10, "height": 10, "surface": [[0, 0], [1, 0], [1, 1], [2, 0]]}}',
             b'{"table": 0, "objects": [4242]}', b'{"table": 0, "n_objects": NaN}', b'{"table": ', b'[1, 2]',
             b'{"table": 0, "participant": "p000", "dataset": "/etc"}']
    for body in cases:
        r = client.post("/plan", content=body)
        assert r.status_code == 400, (body, r.text)
        line = r.json()["detail"]
        assert line.startswith("request") and "\n" not in line and "Traceback" not in r.text
        request = tmp_path / "request.json"
        request.write_bytes(body)
        code = main(["plan", "--config", "baseline_consensus", "--set", f"dataset={root}", "--request",
                     str(request), "--out", str(tmp_path / "plan")])
        err = capsys.readouterr().err
        if b"/etc" in body:  # the CLI may read a dataset folder; the server never does
            continue
        assert code == 2 and err == f"degusta: error: {request}: {line}\n"  # the CLI names the file first
    assert client.get("/health").json()["status"] == "ok"  # still serving


def test_an_oversized_body_is_refused_before_it_is_read(served):
    client, planner, _ = served
    r = client.post("/plan", content=b" " * (MAX_REQUEST_BYTES + 1024))
    assert r.status_code == 413
    assert r.json()["detail"] == (f"request: {MAX_REQUEST_BYTES + 1024:,} bytes, over the limit of "
                                  f"{MAX_REQUEST_BYTES:,} bytes a plan request may take")

    def chunks():  # no Content-Length: refused once the body read passes the limit
        for _ in range(2 * MAX_REQUEST_BYTES // 65536):
            yield b" " * 65536

    r = client.post("/plan", content=chunks())
    assert r.status_code == 413 and r.json()["detail"].startswith(f"request: more than {MAX_REQUEST_BYTES:,} bytes")
    r = client.post("/plan", json={"table": 0, "objects": list(range(1001))})
    assert r.status_code == 400 and r.json()["detail"].startswith("request.objects: 1001 objects, over the limit")
    assert client.post("/plan", json=_request(planner, 1)).status_code == 200  # still serving


def test_eight_concurrent_clients_each_get_their_own_plan(served):
    client, planner, _ = served
    requests = [_request(planner, i) for i in range(0, 40, 5)]
    expected = [json.loads(json.dumps(planner.plan(r).to_json())) for r in requests]
    assert len({json.dumps(e["steps"]) for e in expected}) > 1  # different answers, so a mix-up would show

    def ask(r):
        with httpx.Client(base_url=str(client.base_url), timeout=TIMEOUT) as c:
            return c.post("/plan", json=r)

    with ThreadPoolExecutor(8) as pool:
        replies = list(pool.map(ask, requests * 2))
    assert all(r.status_code == 200 for r in replies)
    assert [r.json() for r in replies] == expected * 2


def test_a_fault_of_the_planner_is_500_with_one_line_and_the_server_goes_on(served, monkeypatch):
    client, planner, _ = served

    def broken(request):
        raise RuntimeError("a bug\nwith a second line")

    monkeypatch.setattr(planner, "plan", broken)
    r = client.post("/plan", json={"table": 0})
    assert r.status_code == 500 and r.json() == {
        "detail": "internal error of the planner (RuntimeError); the server's log has the traceback"}
    monkeypatch.undo()
    assert client.post("/plan", json={"table": 0}).status_code == 200


def test_health_and_openapi(served):
    client, planner, _ = served
    health = client.get("/health").json()
    assert health["method"] == "consensus" and health["config_sha256"] == planner.config_sha256
    assert health["limits"]["request_bytes"] == MAX_REQUEST_BYTES
    spec = client.get("/openapi.json").json()
    post = spec["paths"]["/plan"]["post"]
    assert post["requestBody"]["content"]["application/json"]["schema"]["title"] == "PlanRequest"
    assert post["responses"]["200"]["content"]["application/json"]["schema"]["title"] == "Plan"
    assert {"400", "413", "500"} <= set(post["responses"])
    assert client.get("/plan").status_code == 405 and client.get("/nope").status_code == 404


def test_degusta_serve_binds_localhost_answers_and_stops_on_sigterm(served, tmp_path):
    import signal
    import socket
    import subprocess
    import sys

    _, _, root = served
    with socket.socket() as s:  # a free port (released just before the server binds it)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "degusta_learn.cli", "serve", "--config", "baseline_consensus",
                             "--set", f"dataset={root}", "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
                break
            except httpx.TransportError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else ""
                time.sleep(0.2)
        assert health.json()["method"] == "consensus"
        assert httpx.post(f"http://127.0.0.1:{port}/plan", json={"table": 1}, timeout=30).status_code == 200
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert f"on http://127.0.0.1:{port}: POST /plan" in out
    assert proc.returncode == 143 and "terminated (SIGTERM)" in err
