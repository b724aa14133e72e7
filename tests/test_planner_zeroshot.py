"""The planner with the zero-shot methods: an API backend (a loopback OpenAI-compatible server) plans with its cost,
its response cache and its ledger in the planner's workdir, its backend built once; the hf backend (the shipped tiny
base, slow) loads its model once for many plans."""

from __future__ import annotations

import pytest
from conftest import make_small_dataset
from test_prompting_server import FAKE_KEY, FakeOpenAI

from degusta_learn.planner import Planner
from degusta_learn.prompting import runner
from degusta_learn.scene import make_episodes, save_dataset


@pytest.fixture
def dataset_dir(tmp_path):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path / "data")


def test_an_api_method_plans_with_its_cost_cache_and_ledger(tmp_path, dataset_dir, monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", FAKE_KEY)
    server = FakeOpenAI()  # every answer: plate 75, fork 25 (tests/test_prompting_server.py GOOD)
    built = []
    make = runner.make_backend
    monkeypatch.setattr(runner, "make_backend", lambda *a, **k: built.append(a) or make(*a, **k))
    try:
        sets = ["method=mogma", f"dataset={dataset_dir}", "render_size=64", "backend.name=openai",
                f"backend.base_url={server.url}", "backend.timeout=10", "model.name=fake-model", "decoding.n=2",
                "decoding.temperature=1.0", "prices={fake-model: [1000.0, 2000.0]}"]
        workdir = tmp_path / "plans"
        planner = Planner.from_config(None, sets, workdir=workdir)
        request = {"participant": "p000", "trials": [0, 1], "table": 2}
        plan = planner.plan(request)
        assert [(s.type, s.object) for s in plan.steps] == [("plate", 75), ("fork", 25)]
        assert len(server.requests) == 1 and server.requests[0]["body"]["n"] == 2
        # 1000 prompt tokens at $1000 / 1M + 20 completion tokens at $2000 / 1M
        assert plan.diagnostics["cost_usd"] == pytest.approx(1.0 + 0.04)
        assert plan.diagnostics["method"]["n_parsed"] == 2 and plan.diagnostics["failures"] == []
        assert {p.name for p in workdir.iterdir()} >= {"ledger.json", "responses_cache.sqlite"}
        again = planner.plan(request)  # the same request: answered from the cache, nothing paid
        assert len(server.requests) == 1 and again.steps == plan.steps and again.diagnostics["cost_usd"] == 0
        planner.plan({**request, "table": 1, "objects": [76, 25, 3]})  # another table: asked; plate 75 replaced
        assert len(server.requests) == 2
        assert len(built) == 1, "the backend must be built once for all plans"
        assert runner.make_backend.__name__ == "<lambda>"  # the planner put the runner's own builder back
    finally:
        server.close()


def test_text_llm_plans_like_the_prompting_methods(tmp_path, dataset_dir, monkeypatch):
    """text_llm's two requests an episode (summary, placements) go through the same kept backend, and the plan says
    what they cost; a server that answers nothing is 'unavailable', as for the four prompting methods."""
    from degusta_learn.planner.planner import BackendUnavailable

    monkeypatch.setenv("OPENAI_API_KEY", FAKE_KEY)
    server = FakeOpenAI()
    built = []
    make = runner.make_backend
    monkeypatch.setattr(runner, "make_backend", lambda *a, **k: built.append(a) or make(*a, **k))
    try:
        sets = ["method=text_llm", f"dataset={dataset_dir}", "backend.name=openai", f"backend.base_url={server.url}",
                "backend.timeout=10", "model.name=fake-model", "decoding.n=1", "decoding.temperature=0",
                "prices={fake-model: [1000.0, 2000.0]}", "max_retries=1", "backoff=0.01"]
        planner = Planner.from_config(None, sets, workdir=tmp_path / "plans")
        plan = planner.plan({"participant": "p000", "trials": [0, 1], "table": 2})
        assert len(server.requests) == 2  # the summary, then the placements
        assert plan.diagnostics["cost_usd"] > 0
        planner.plan({"participant": "p001", "trials": [0, 1], "table": 2})
        # its summary is asked; the fake server summarises everyone alike, so the placement prompt (that summary,
        # the same table) is the first plan's, answered from the cache
        assert len(server.requests) == 3 and len(built) == 1, "the backend must be built once for all plans"
        for _ in range(4):
            server.error(500, "overloaded")
        with pytest.raises(BackendUnavailable, match="^zero-shot run incomplete"):
            planner.plan({"participant": "p002", "trials": [0, 1], "table": 2})
    finally:
        server.close()


@pytest.mark.slow
def test_the_hf_backend_loads_its_model_once(tmp_path, dataset_dir, monkeypatch):
    """The shipped tiny base VLM, zero-shot (offline): 6-30 s on one CPU core (by load), most of it the first load."""
    from degusta_learn.vlm import load

    loads = []
    real = load.load_vlm
    monkeypatch.setattr(load, "load_vlm", lambda *a, **k: loads.append(a) or real(*a, **k))
    planner = Planner.from_config("predict_hf_base_zeroshot", [f"dataset={dataset_dir}"], workdir=tmp_path / "w")
    ds = planner.dataset
    for ep in make_episodes(ds, 2, "all")[:2]:
        plan = planner.plan({"participant": ep.participant, "trials": list(ep.context),
                             "table": ds.arrangement(ep.participant, ep.target).table})
        assert plan.method == "mogma" and plan.diagnostics["cost_usd"] is None
        assert all(0 <= s.rotation < 360 and plan.table.table.contains(s.x, s.y) for s in plan.steps)
    assert len(loads) == 1


def test_a_backend_that_gives_no_answer_is_unavailable_not_a_bad_request(tmp_path, dataset_dir, monkeypatch):
    from degusta_learn.planner.planner import BackendUnavailable

    monkeypatch.setenv("OPENAI_API_KEY", FAKE_KEY)
    server = FakeOpenAI()
    try:
        for _ in range(3):
            server.error(500, "overloaded")
        planner = Planner.from_config(None, ["method=mouma", f"dataset={dataset_dir}", "render_size=64",
                                             "backend.name=openai", f"backend.base_url={server.url}",
                                             "model.name=fake-model", "max_retries=1", "backoff=0.01",
                                             "cache=off"], workdir=tmp_path / "plans")
        with pytest.raises(BackendUnavailable, match="^zero-shot run incomplete: 1 of 1 episodes got no answer"):
            planner.plan({"table": 0})
        assert len(server.requests) == 2  # the request and its one retry
    finally:
        server.close()
