"""Structured outputs for the zero-shot backends (issue 13, item 5): `backend.structured_output: true`.

Loopback HTTP servers check every request body against the provider's documented shape and answer with
JSON that conforms to the schema they were sent (a random instance: the worst a schema-constrained model
can do):
- OpenAI chat completions (also vLLM / SGLang / Ollama): `response_format` json_schema, `strict: true`, every
  object with `additionalProperties: false` and all its properties required, only strict-mode keywords;
- Anthropic Messages: one tool whose `input_schema` is the schema, `tool_choice` forcing it; the answer is
  the tool_use block's `input` (wire test when the `anthropic` client is installed, a fake client always);
- Gemini generateContent: `generationConfig.responseMimeType` + `responseSchema` (wire test when
  `google-genai` is installed; the OpenAPI conversion always).
Also: a server that ignores the schema (free text: parsed as usual, or a counted failure), one that refuses
it (one line naming `backend.structured_output`), cache separation between the two modes, the hf backend's
one-line refusal, and the measured failure rate over 50 episodes (`-s` prints it).
"""

from __future__ import annotations

import json
import random
import re
from types import SimpleNamespace

import jsonschema
import pytest
import yaml
from conftest import make_small_dataset
from loopback import Loopback, chat_completion, json_reply

from degusta_learn.cli import main as cli_main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict
from degusta_learn.prompting.backends.base import BackendConfig, backend_config
from degusta_learn.prompting.backends.gemini import gemini_schema
from degusta_learn.render.grid import DIRECTIONS, Grid
from degusta_learn.scene import default_catalog, read_predictions, save_dataset
from degusta_learn.task.answer_format import answer_items, answer_schema, format_answer_json
from degusta_learn.task.answers import STRUCTURED_KEY, STRUCTURED_NAME, read_answer

CAT = default_catalog()
G = Grid(8, 8)
FREE = "[{'type': 'plate', 'id': 75, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}]"
STRICT_KEYWORDS = {"type", "properties", "required", "additionalProperties", "items", "anyOf", "enum",
                   "description", "minItems", "maxItems", "minimum", "maximum", "pattern"}


# ----------------------------------------------------------------------------- schema helpers

def check_strict(schema: dict) -> None:
    """OpenAI strict mode's rules: an object root, every object closed and with all properties required,
    only supported keywords."""
    assert schema["type"] == "object" and "anyOf" not in schema

    def walk(node):
        if isinstance(node, list):
            for n in node:
                walk(n)
            return
        if not isinstance(node, dict):
            return
        assert set(node) <= STRICT_KEYWORDS, set(node) - STRICT_KEYWORDS
        if node.get("type") == "object":
            assert node["additionalProperties"] is False
            assert node["required"] == list(node["properties"])
        for key in ("properties",):
            for sub in node.get(key, {}).values():
                walk(sub)
        walk(node.get("items"))
        walk(node.get("anyOf"))

    walk(schema)


def sample(schema: dict, rng: random.Random, max_len: int = 6):
    """A random instance of `schema` (our subset): what a schema-constrained decoder may emit."""
    if "anyOf" in schema:
        return sample(rng.choice(schema["anyOf"]), rng, max_len)
    if "enum" in schema:
        return rng.choice(schema["enum"])
    t = schema["type"]
    if t == "object":
        return {k: sample(v, rng, max_len) for k, v in schema["properties"].items()}
    if t == "array":
        lo, hi = schema.get("minItems", 0), min(schema.get("maxItems", max_len), max_len)
        return [sample(schema["items"], rng, max_len) for _ in range(rng.randint(lo, hi))]
    if t == "number":
        return round(rng.uniform(schema.get("minimum", -1e3), schema.get("maximum", 1e3)), 4)
    if t == "integer":
        return rng.randint(schema["minimum"], schema["maximum"])
    raise AssertionError(f"no sampler for {schema}")


# ----------------------------------------------------------------------------- a loopback server

def serve(reply):
    """A loopback server answering JSON from `reply(path, body) -> (status, payload)`; a failed shape check
    (an AssertionError in `reply`: a malformed request) is answered as a 400."""
    def respond(req):
        try:
            status, payload = reply(req["path"], req["body"])
        except AssertionError as e:
            status, payload = 400, {"error": {"message": f"shape check failed: {e}", "type": "x"}}
        return json_reply(status, payload)
    return Loopback(respond)


def run_served(reply, tmp_path, dataset_dir, prefix="", **extra):
    """`run_predict` against a server answering `reply` at its root + `prefix`: the output, the requests."""
    server = serve(reply)
    try:
        out = run_predict(config(tmp_path, server.root + prefix, dataset_dir, **extra))
    finally:
        server.close()
    return out, server.requests


def openai_reply(answer):
    """An OpenAI chat-completions reply; `answer(body, rng)` gives each choice's content."""
    rng = random.Random(0)

    def reply(path, body):
        assert path == "/v1/chat/completions"
        return 200, chat_completion(body["model"], [answer(body, rng) for _ in range(body.get("n", 1))])
    return reply


def schema_model(body, rng):
    """A schema-constrained model: checks the request is OpenAI strict json_schema, answers an instance."""
    fmt = body["response_format"]
    assert fmt["type"] == "json_schema", fmt.get("type")
    spec = fmt["json_schema"]
    assert spec["name"] == STRUCTURED_NAME and spec["strict"] is True
    check_strict(spec["schema"])
    value = sample(spec["schema"], rng)
    jsonschema.validate(value, spec["schema"])
    return json.dumps(value)


@pytest.fixture
def dataset_dir(tmp_path):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path / "data")


def config(tmp_path, url, dataset_dir, name="zeroshot.yaml", **extra):
    cfg = {"method": "mogma", "dataset": str(dataset_dir), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "render_size": 64, "concurrency": 2, "backoff": 0,
           "max_retries": 1, "backend": {"name": "openai", "base_url": url, "timeout": 10, "structured_output": True},
           "model": {"name": "fake"}, "decoding": {"n": 3, "temperature": 1.0}}
    if "n" in extra:
        cfg["decoding"]["n"] = extra.pop("n")
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(cfg.get(k), dict):
            cfg[k].update(v)
        else:
            cfg[k] = v
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg))
    return path


def ledger(tmp_path):
    return json.loads((tmp_path / "run" / "ledger.json").read_text())


# ----------------------------------------------------------------------------- the schema

@pytest.mark.parametrize("kind", ["grid", "unmarked"])
def test_schema_is_the_parsers_grammar(kind):
    schema = answer_schema(kind, CAT, G)
    check_strict(schema)
    jsonschema.Draft202012Validator.check_schema(schema)
    branches = schema["properties"][STRUCTURED_KEY]["items"]["anyOf"]
    assert [b["properties"]["type"]["enum"] for b in branches] == [[t] for t in CAT.types]
    for b in branches:  # each type's branch lists exactly that type's ids
        (t,) = b["properties"]["type"]["enum"]
        assert b["properties"]["id"]["enum"] == sorted(o.id for o in CAT if o.type == t)
    if kind == "grid":
        cells = branches[0]["properties"]["position"]["items"]["enum"]
        assert sorted(cells) == sorted(G.cell_id(c, r) for c in range(8) for r in range(8))
        assert branches[0]["properties"]["cardinal_direction"]["enum"] == list(DIRECTIONS)
    # a perfect answer in JSON validates and reads back into the same items
    ds = make_small_dataset(2, 2)
    placements = ds.arrangements[0].placements
    items = answer_items(list(placements), CAT, kind, G)
    text = format_answer_json(items, kind)
    jsonschema.validate(json.loads(text), schema)
    assert read_answer(text, kind, CAT, G).items == items
    # every random instance of the schema reads with no failure: only a repeated id can be dropped
    rng = random.Random(1)
    for _ in range(300):
        value = sample(schema, rng)
        answer = read_answer(json.dumps(value), kind, CAT, G)
        assert answer.n_read == len(value[STRUCTURED_KEY])
        assert all("already placed" in e for e in answer.item_errors), answer.item_errors


def test_large_grids_and_catalogs_keep_the_schema_small():
    schema = answer_schema("grid", CAT, Grid(20, 26))
    check_strict(schema)
    cell = schema["properties"][STRUCTURED_KEY]["items"]["anyOf"][0]["properties"]["position"]["items"]
    pattern = re.compile(cell["pattern"])
    assert pattern.match("Z20") and pattern.match("A1") and not pattern.match("A21") and not pattern.match("A0")
    assert len(json.dumps(schema)) < 10_000


def test_the_parser_takes_the_json_object_anywhere():
    plate = {"type": "plate", "id": 75, "position": ["D4"], "cardinal_direction": "N"}
    assert read_answer(json.dumps({"objects": []}), "grid", CAT, G).items == []
    fenced = "Sure!\n```json\n" + json.dumps({"objects": [plate, {**plate, "type": "cup"}]}) + "\n```"
    answer = read_answer(fenced, "grid", CAT, G)  # same item policy: the mistyped item is dropped
    assert [it.id for it in answer.items] == [75] and answer.item_errors == ["item 1: id 75 is a plate, not a cup"]
    assert [it.id for it in read_answer(FREE, "grid", CAT, G).items] == [75]  # free text as before


# ----------------------------------------------------------------------------- OpenAI protocol

@pytest.mark.parametrize("method", ["mogma", "louma"])
def test_openai_requests_carry_the_strict_schema(tmp_path, dataset_dir, method):
    out, requests = run_served(openai_reply(schema_model), tmp_path, dataset_dir, "/v1", method=method)
    assert len(requests) == 9
    body = requests[0]["body"]
    assert body["n"] == 3
    assert 'Give your answer as a JSON object formatted as follows: {"objects": [{"type": object_type' in \
        body["messages"][0]["content"][-1]["text"]
    preds = read_predictions(out, make_small_dataset(3, 3).catalog)
    assert all(p.diagnostics["failures"] == [] and p.diagnostics["n_parsed"] == 3 for p in preds)
    assert ledger(tmp_path)["structured_output"] is True


def test_a_server_that_ignores_the_schema(tmp_path, dataset_dir):
    # free text anyway: parsed as usual; prose or garbage: a counted failure, never a traceback
    answers = ["[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]",
               "I would put the plate in the middle.", '{"objects": [{"type": "plate", "id": ']
    server = serve(openai_reply(lambda body, rng: answers[len(server.requests) % 3]))
    try:
        out = run_predict(config(tmp_path, server.root + "/v1", dataset_dir, concurrency=1))
    finally:
        server.close()
    preds = read_predictions(out, make_small_dataset(3, 3).catalog)
    by_text = {}
    for p in preds:
        for f in p.diagnostics["failures"]:
            by_text.setdefault(p.diagnostics["responses"][f["sample"]], f["reason"])
    assert not by_text.get(answers[0])
    assert "no list of objects" in by_text[answers[1]] and "not closed" in by_text[answers[2]]
    assert sum(not p.failed for p in preds) == 3 and sum(p.failed for p in preds) == 6
    assert ledger(tmp_path)["episodes_failed"] == 6


def test_a_server_that_refuses_the_schema_stops_with_one_line(tmp_path, dataset_dir, capsys):
    def refuse(path, body):
        return 400, {"error": {"message": "response_format json_schema is not supported", "type": "invalid"}}
    server = serve(refuse)
    try:
        path = config(tmp_path, server.root + "/v1", dataset_dir)
        assert cli_main(["predict", "--config", str(path)]) == 2
    finally:
        server.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "backend.structured_output" in err[0] and "Traceback" not in err[0]
    assert len(server.requests) <= 2  # fatal: the run stops at once
    assert not (tmp_path / "run" / "predictions.jsonl").exists()


def test_free_text_and_structured_answers_never_mix_in_the_cache(tmp_path, dataset_dir):
    def answer(body, rng):
        return schema_model(body, rng) if "response_format" in body else FREE
    server = serve(openai_reply(answer))
    cache = str(tmp_path / "cache.sqlite")
    try:
        free = config(tmp_path, server.root + "/v1", dataset_dir, "free.yaml", cache=cache,
                      backend={"structured_output": False})
        run_predict(free)
        assert len(server.requests) == 9 and all("response_format" not in r["body"] for r in server.requests)
        structured = config(tmp_path, server.root + "/v1", dataset_dir, cache=cache)
        out = run_predict(structured)
        assert len(server.requests) == 18, "a structured run must not reuse free-text answers"
        assert all("response_format" in r["body"] for r in server.requests[9:])
        assert all(r.startswith('{"objects"') for p in map(json.loads, out.read_text().splitlines())
                   for r in p["diagnostics"]["responses"])
        run_predict(structured)
        out = run_predict(free)
        assert len(server.requests) == 18, "each mode is served from its own cached answers"
        assert all(r == FREE for p in map(json.loads, out.read_text().splitlines()) for r in p["diagnostics"]["responses"])
    finally:
        server.close()


def test_hf_and_unknown_paths_are_one_line_errors():
    with pytest.raises(DegustaError, match=r"^backend.structured_output: the hf backend takes no JSON schema.*"
                                           r"decoding.constrained: true"):
        BackendConfig(name="hf", structured_output=True)
    backend_config("replay", path="x", structured_output=True)  # replay: ignored (both kinds parse)


# ----------------------------------------------------------------------------- Anthropic

def test_anthropic_forces_the_answer_tool(monkeypatch):
    from degusta_learn.prompting.backends.anthropic import AnthropicBackend
    from degusta_learn.task.prompt import Prompt

    calls = []
    value = {"objects": [{"type": "plate", "id": 75, "position": ["D4"], "cardinal_direction": "N"}]}

    class Messages:
        def create(self, **kwargs):
            calls.append(kwargs)
            block = SimpleNamespace(type="tool_use", name=STRUCTURED_NAME, id="t", input=value)
            stringified = SimpleNamespace(type="tool_use", name=STRUCTURED_NAME, id="t",
                                          input={"objects": json.dumps(value["objects"])})
            return SimpleNamespace(content=[block] if len(calls) == 1 else [stringified],
                                   usage=SimpleNamespace(input_tokens=10, output_tokens=5))

    monkeypatch.setattr("degusta_learn.prompting.backends.anthropic._import",
                        lambda: SimpleNamespace(APIStatusError=KeyError, APITimeoutError=KeyError,
                                                APIConnectionError=KeyError))
    from degusta_learn.prompting.backends.base import AnswerSchemas

    backend = AnthropicBackend("claude", SimpleNamespace(messages=Messages()), AnswerSchemas(G, CAT))
    got = backend.complete(Prompt("mogma", ["task"]), n=2, temperature=1.0, max_tokens=100)
    assert [json.loads(c.text) for c in got] == [value, value]  # a stringified list is read too
    (tool,) = calls[0]["tools"]
    assert tool["name"] == STRUCTURED_NAME and tool["input_schema"] == answer_schema("grid", CAT, G)
    assert calls[0]["tool_choice"] == {"type": "tool", "name": STRUCTURED_NAME}


def test_anthropic_wire_shape(tmp_path, dataset_dir, monkeypatch):
    pytest.importorskip("anthropic")
    rng = random.Random(0)

    def reply(path, body):
        assert path == "/v1/messages"
        (tool,) = body["tools"]
        assert tool["name"] == STRUCTURED_NAME and tool["input_schema"]["type"] == "object"
        assert body["tool_choice"] == {"type": "tool", "name": STRUCTURED_NAME}
        assert body["temperature"] == 1.0  # a keyword up to anthropic 1.x, extra_body in 2.x: the same body
        value = sample(tool["input_schema"], rng)
        jsonschema.validate(value, tool["input_schema"])
        return 200, {"id": "msg", "type": "message", "role": "assistant", "model": body["model"],
                     "content": [{"type": "tool_use", "id": "toolu_1", "name": STRUCTURED_NAME, "input": value}],
                     "stop_reason": "tool_use", "stop_sequence": None,
                     "usage": {"input_tokens": 100, "output_tokens": 10}}

    monkeypatch.setenv("ANTHROPIC_API_KEY", "test-key-not-real")
    out, requests = run_served(reply, tmp_path, dataset_dir, n=2, backend={"name": "anthropic"},
                               model={"name": "claude-x"})
    assert len(requests) == 18  # one request a sample
    preds = read_predictions(out, make_small_dataset(3, 3).catalog)
    assert all(p.diagnostics["failures"] == [] for p in preds)


# ----------------------------------------------------------------------------- Gemini

def test_gemini_schema_is_the_openapi_subset():
    schema = gemini_schema(answer_schema("grid", CAT, G))
    text = json.dumps(schema)
    assert "additionalProperties" not in text
    branch = schema["properties"][STRUCTURED_KEY]["items"]["anyOf"][0]
    assert branch["propertyOrdering"] == ["type", "id", "position", "cardinal_direction"]
    assert branch["properties"]["id"]["format"] == "enum" and branch["properties"]["id"]["enum"][:2] == ["0", "1"]
    assert branch["properties"]["type"] == {"type": "string", "enum": ["cup"]}


def test_gemini_wire_shape(tmp_path, dataset_dir, monkeypatch):
    pytest.importorskip("google.genai")
    seen = []

    def reply(path, body):
        assert path.endswith("/models/gemini-x:generateContent"), path
        gen = body["generationConfig"]
        assert gen["responseMimeType"] == "application/json"
        schema = gen["responseSchema"]
        assert "additionalProperties" not in json.dumps(schema)
        seen.append(schema)
        value = format_answer_json(answer_items(list(make_small_dataset(3, 3).arrangements[0].placements), CAT,
                                                "grid", G), "grid")
        return 200, {"candidates": [{"content": {"role": "model", "parts": [{"text": value}]},
                                     "finishReason": "STOP"}],
                     "usageMetadata": {"promptTokenCount": 100, "candidatesTokenCount": 10}}

    monkeypatch.setenv("GEMINI_API_KEY", "test-key-not-real")
    out, requests = run_served(reply, tmp_path, dataset_dir, n=1, backend={"name": "gemini"},
                               model={"name": "gemini-x"})
    assert len(requests) == 9
    items = seen[0]["properties"][STRUCTURED_KEY]["items"]
    ids = (items.get("anyOf") or items["any_of"])[0]["properties"]["id"]  # google-genai writes proto names
    assert ids["enum"][:2] == ["0", "1"] and str(ids["type"]).lower() == "integer"
    preds = read_predictions(out, make_small_dataset(3, 3).catalog)
    assert all(p.diagnostics["failures"] == [] for p in preds)


# ----------------------------------------------------------------------------- the failure rate

@pytest.mark.parametrize("method", ["mogma", "mouma"])
def test_failure_rate_is_zero_by_construction(tmp_path, method):
    """50 episodes x 5 samples against a server answering random schema instances (benchmarks/RESULTS.md)."""
    data = save_dataset(make_small_dataset(n_participants=10, n_trials=5, seed=3), tmp_path / "data")
    out, _ = run_served(openai_reply(schema_model), tmp_path, data, "/v1", method=method, n=5, concurrency=1)
    preds = read_predictions(out, make_small_dataset(10, 5, seed=3).catalog)
    samples = sum(len(p.diagnostics["responses"]) for p in preds)
    failed = sum(len(p.diagnostics["failures"]) for p in preds)
    led = ledger(tmp_path)
    print(f"\n{method} structured: {len(preds)} episodes, {sum(p.failed for p in preds)} failed; samples: "
          f"{failed} of {samples} failed; items: {led['item_errors']} of {led['items_read']} dropped "
          f"(repeated ids only)")
    assert len(preds) == 50 and samples == 250 and failed == 0 and not any(p.failed for p in preds)
