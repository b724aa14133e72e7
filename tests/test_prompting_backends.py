"""Backends: registry, key handling, missing extras, replay of a recorded run, the estimate and price table."""

from __future__ import annotations

import importlib
import json
import sys

import pytest
from conftest import make_small_dataset

from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.methods import get_method, run_predict
from degusta_learn.vlm.settings import ModelSettings
from degusta_learn.prompting.backends.base import (
    BACKENDS,
    BackendConfig,
    backend_class,
    backend_config,
    make_backend,
    redact,
)
from degusta_learn.prompting.costs import Ledger, price
from degusta_learn.render.grid import Grid
from degusta_learn.scene import make_episodes, read_predictions, save_dataset

GOOD = "[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]"


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_backend_class_has_the_protocol(name):
    module, attr = BACKENDS[name].split(":")
    if name == "hf" and importlib.util.find_spec(module) is None:
        pytest.skip("the hf backend file is written by the fine-tuning part")
    cls = getattr(importlib.import_module(module), attr)
    assert callable(cls.from_config) and callable(cls.complete) and cls.name == name


def test_config_names_the_bad_key():
    with pytest.raises(DegustaError, match="backend.name: unknown backend 'gpt'"):
        BackendConfig(name="gpt")
    spec = get_method("mogma")
    with pytest.raises(DegustaError, match="decoding.n: expected a value from 1 to 1,000, got 0"):
        from_dict(spec.config_cls, {"method": "mogma", "dataset": "d", "out": "o", "decoding": {"n": 0}})
    with pytest.raises(DegustaError, match="unknown key 'backend.modle'"):
        from_dict(spec.config_cls, {"method": "mogma", "dataset": "d", "out": "o", "backend": {"modle": "x"}})


def test_keys_come_only_from_the_environment(monkeypatch):
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    with pytest.raises(DegustaError, match="OPENAI_API_KEY is not set"):
        make_backend(backend_config("openai"), ModelSettings(name="gpt-4o"))
    # a local server needs none, and never gets the OpenAI key unless asked to
    monkeypatch.setenv("OPENAI_API_KEY", "sk-real-openai-key-000")
    backend = make_backend(backend_config("openai", base_url="http://127.0.0.1:8000/v1"), ModelSettings(name="q"))
    assert backend.client.api_key == "not-needed"
    monkeypatch.setenv("LOCAL_KEY", "local-secret-123")
    backend = make_backend(backend_config("openai", base_url="http://127.0.0.1:8000/v1", api_key_env="LOCAL_KEY"),
                           ModelSettings(name="q"))
    assert backend.client.api_key == "local-secret-123"
    monkeypatch.delenv("ANTHROPIC_API_KEY", raising=False)
    with pytest.raises(DegustaError, match="ANTHROPIC_API_KEY is not set"):
        make_backend(backend_config("anthropic"), ModelSettings(name="claude-3-haiku-20240307"))


def test_redact_scrubs_keys(monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", "abc-secret-value-42")
    assert redact("bad key abc-secret-value-42 and sk-proj-AbC123xyz") == "bad key *** and ***"


def test_missing_extras_say_what_to_install(monkeypatch):
    monkeypatch.setenv("GEMINI_API_KEY", "x")
    monkeypatch.setitem(sys.modules, "google.genai", None)  # as if google-genai were not installed
    with pytest.raises(DegustaError, match=r"pip install degusta_learn\[gemini\]"):
        make_backend(backend_config("gemini"), ModelSettings(name="gemini-1.5-pro"))
    monkeypatch.setenv("ANTHROPIC_API_KEY", "x")
    monkeypatch.setitem(sys.modules, "anthropic", None)
    with pytest.raises(DegustaError, match=r"pip install degusta_learn\[anthropic\]"):
        make_backend(backend_config("anthropic"), ModelSettings(name="claude-3-haiku-20240307"))


def test_replay_reproduces_a_run_without_calls(tmp_path):
    ds = make_small_dataset(n_participants=3, n_trials=3)
    data = save_dataset(ds, tmp_path / "data")
    episodes = make_episodes(ds, 2, "all")
    answers = tmp_path / "answers.jsonl"
    rows = [{"episode": ep.id, "sample": i, "text": GOOD} for ep in episodes for i in range(3)]
    rows[0]["text"] = "no idea"
    answers.write_text("".join(json.dumps(r) + "\n" for r in rows))
    base = [f"dataset={data}", "context=2", "split=all", "decoding.n=3", "render_size=64", "method=mogma",
            "backend.name=replay"]
    out1 = run_predict(None, base + [f"backend.path={answers}", f"out={tmp_path / 'r1' / 'predictions.jsonl'}"])
    p1 = read_predictions(out1, ds.catalog)
    assert p1[0].diagnostics["n_parsed"] == 2 and p1[0].placements[0].object == 75
    assert not (tmp_path / "r1" / "responses_cache.sqlite").exists()  # replay is not cached
    # a predictions.jsonl of a run is itself a replay file
    out2 = run_predict(None, base + [f"backend.path={out1}", f"out={tmp_path / 'r2' / 'predictions.jsonl'}"])
    p2 = read_predictions(out2, ds.catalog)
    assert [p.placements for p in p2] == [p.placements for p in p1]
    # an answer missing from the file is a counted failure
    answers.write_text(json.dumps({"episode": episodes[0].id, "sample": 0, "text": GOOD}) + "\n")
    out3 = run_predict(None, base + [f"backend.path={answers}", f"out={tmp_path / 'r3' / 'predictions.jsonl'}"])
    p3 = read_predictions(out3, ds.catalog)
    assert p3[0].diagnostics["failures"] == [{"sample": 1, "reason": "no recorded answer"},
                                             {"sample": 2, "reason": "no recorded answer"}]
    assert all(p.failed for p in p3[1:])
    ledger = json.loads((tmp_path / "r3" / "ledger.json").read_text())
    assert ledger["cost_usd"] == 0


def test_predict_aggregates_by_steps_from_the_same_answers(tmp_path):
    """`aggregation: steps` through predict: three recorded answers naming the same objects in other orders; the
    paper's per-step modes lose one; the aggregation is recorded; a misspelt or removed choice (votes) is refused
    naming the key."""
    ds = make_small_dataset(n_participants=3, n_trials=3)
    data = save_dataset(ds, tmp_path / "data")
    episodes = make_episodes(ds, 2, "all")
    cup, plate, fork = (ds.catalog.of_type(t)[0].id for t in ("cup", "plate", "fork"))

    def item(type_, oid, cell):
        return f"{{'type': '{type_}', 'id': {oid}, 'position': ['{cell}'], 'cardinal_direction': 'N'}}"

    orders = [[("cup", cup, "A1"), ("plate", plate, "B2"), ("fork", fork, "C3")],
              [("plate", plate, "B2"), ("cup", cup, "A1"), ("fork", fork, "C3")],
              [("plate", plate, "B2"), ("fork", fork, "C3"), ("cup", cup, "A1")]]
    answers = tmp_path / "answers.jsonl"
    answers.write_text("".join(json.dumps({"episode": ep.id, "sample": i,
                                           "text": "[" + ", ".join(item(*it) for it in order) + "]"}) + "\n"
                               for ep in episodes for i, order in enumerate(orders)))
    base = [f"dataset={data}", "context=2", "split=all", "decoding.n=3", "render_size=64", "method=mogma",
            "backend.name=replay", f"backend.path={answers}"]
    got = {}
    for how in ("steps",):
        out = run_predict(None, base + [f"decoding.aggregation={how}", f"out={tmp_path / how / 'predictions.jsonl'}"])
        got[how] = read_predictions(out, ds.catalog)
        assert all(p.diagnostics["aggregation"] == how for p in got[how])
        assert json.loads((tmp_path / how / "ledger.json").read_text())["aggregation"] == how
    assert [p.object for p in got["steps"][0].placements] == [plate, fork]  # step 1's tie: the plate again
    with pytest.raises(DegustaError, match="aggregation"):
        run_predict(None, base + ["decoding.aggregation=votes", f"out={tmp_path / 'bad' / 'predictions.jsonl'}"])
    assert not (tmp_path / "bad").exists()


def test_predict_lengthens_the_greedy_answer_by_votes(tmp_path):
    """`aggregation: greedy_votes_pooled` through predict: the greedy answer (recorded as sample "greedy", asked at
    temperature 0) keeps its one object, lengthened to the samples' median length (3) by their most named objects,
    each object placed from every answer naming it; its text is kept in the diagnostics, so a predictions file
    replays the same plan; temperature 0 is refused."""
    ds = make_small_dataset(n_participants=3, n_trials=3)
    data = save_dataset(ds, tmp_path / "data")
    episodes = make_episodes(ds, 2, "all")
    cup, plate, fork = (ds.catalog.of_type(t)[0].id for t in ("cup", "plate", "fork"))

    def answer(*items):
        return "[" + ", ".join(f"{{'type': '{t}', 'id': {i}, 'position': ['{c}'], 'cardinal_direction': 'N'}}"
                               for t, i, c in items) + "]"

    samples = [answer(("cup", cup, "A1"), ("plate", plate, "B2"), ("fork", fork, "C3")),
               answer(("plate", plate, "B3"), ("cup", cup, "A1"), ("fork", fork, "C3")),
               answer(("plate", plate, "B2"), ("cup", cup, "A2"))]
    rows = [{"episode": ep.id, "sample": i, "text": t} for ep in episodes for i, t in enumerate(samples)]
    rows += [{"episode": ep.id, "sample": "greedy", "text": answer(("fork", fork, "H8"))} for ep in episodes]
    answers = tmp_path / "answers.jsonl"
    answers.write_text("".join(json.dumps(r) + "\n" for r in rows))
    base = [f"dataset={data}", "context=2", "split=all", "decoding.n=3", "render_size=64", "method=mogma", "decoding.temperature=0.5",
            "backend.name=replay", "decoding.aggregation=greedy_votes_pooled"]
    first = run_predict(None, base + [f"backend.path={answers}", f"out={tmp_path / 'a' / 'predictions.jsonl'}"])
    got = read_predictions(first, ds.catalog)
    assert [p.object for p in got[0].placements] == [fork, plate, cup]  # the greedy fork, then 3 and 3 votes
    # the greedy fork placed from its own answer (H8) and the two samples naming it (C3)
    assert got[0].placements[0].x == pytest.approx(Grid(8, 8).decode_weighted([["H8"], ["C3"], ["C3"]])[0])
    assert got[0].diagnostics["greedy_response"].startswith("[{'type': 'fork'")
    assert [a["id"] for a in got[0].diagnostics["added"]] == [plate, cup]
    again = run_predict(None, base + [f"backend.path={first}", f"out={tmp_path / 'b' / 'predictions.jsonl'}"])
    assert [p.placements for p in read_predictions(again, ds.catalog)] == [p.placements for p in got]
    with pytest.raises(DegustaError, match="decoding.aggregation: greedy_votes_pooled lengthens a greedy answer"):
        run_predict(None, base + ["decoding.temperature=0", f"backend.path={answers}",
                                  f"out={tmp_path / 'c' / 'predictions.jsonl'}"])
    assert not (tmp_path / "c").exists()


def test_prices_and_image_tokens():
    assert price("gpt-4o") == (2.5, 10.0) and price("gpt-4o-2024-08-06") == (2.5, 10.0)
    assert price("gpt-4o-mini-2024-07-18") == (0.15, 0.6)        # longest prefix wins
    assert price("my-local-model") is None and price("m", {"m": [1, 2]}) == (1, 2)
    # OpenAI's published examples: 1024x1024 high detail = 765 tokens; 2048x4096 = 1105; low = 85
    tokens, openai, low = backend_class("openai").image_tokens, backend_config("openai"), backend_config(detail="low")
    gpt4o = ModelSettings(name="gpt-4o")
    assert tokens(1024, 1024, openai, gpt4o) == 765 and tokens(2048, 4096, openai, gpt4o) == 1105
    assert tokens(448, 448, low, gpt4o) == 85 and tokens(448, 448, openai, gpt4o) == 255
    # (1000 x 1000) / 750, rounded up
    assert backend_class("anthropic").image_tokens(1000, 1000, backend_config("anthropic"), gpt4o) == 1334
    # the paper's anchor at its 2024 GPT-4o price: 8,035 in + 6,250 out ~ USD 0.13 (reported 0.15, rounded up per column)
    ledger = Ledger(price("gpt-4o-2024-05-13"))
    ledger.record(8035, 6250, 5, fallback=(0, 0))
    assert ledger.summary()["cost_usd"] == pytest.approx(0.040175 + 0.09375)


def test_anthropic_temperature_reaches_clients_with_and_without_the_keyword():
    """anthropic 2.x dropped `temperature` from messages.create: it then travels in extra_body."""
    from degusta_learn.prompting.backends.anthropic import sampling_arguments

    def old_create(*, model, max_tokens, messages, temperature=1.0, **kw):
        return None

    def new_create(*, model, max_tokens, messages, extra_body=None, **kw):
        return None

    assert sampling_arguments(old_create, 0.3) == {"temperature": 0.3}
    assert sampling_arguments(new_create, 0.3) == {"extra_body": {"temperature": 0.3}}


def test_redact_removes_credentials_inside_urls():
    from degusta_learn.prompting.backends.base import redact

    assert redact("http://alice:s3cret@127.0.0.1:8000/v1") == "http://***@127.0.0.1:8000/v1"
    assert redact('{"base_url": "https://h/v1?key=s3cret&x=1"}') == '{"base_url": "https://h/v1?key=***&x=1"}'
    assert redact("GET /v1/models?token=abc123") == "GET /v1/models?token=***"
    assert redact("see https://example.com/a@b") == "see https://example.com/a@b"  # a path, not credentials
