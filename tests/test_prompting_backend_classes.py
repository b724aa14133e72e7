"""What a backend is, asked of its class: every registered backend declares it; the runner, the budget check
and the dry run use only that, so a backend added as one class plus its registry entry runs end to end; a
`backend:` section takes only its backend's keys; and the per-backend configs kept every cache key."""

from __future__ import annotations

import json
from dataclasses import dataclass, fields

import pytest
import yaml
from conftest import make_small_dataset

from degusta_learn.cli import main as cli_main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import build_config, get_method, run_predict
from degusta_learn.prompting.backends.base import (
    BACKENDS,
    Backend,
    BackendConfig,
    Completion,
    api_key,
    backend_class,
    backend_config,
    redact,
)
from degusta_learn.prompting.cache import sample_keys
from degusta_learn.scene import read_predictions, save_dataset
from degusta_learn.shipped import shipped_config, shipped_names
from degusta_learn.task.prompt import Prompt
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings

GOOD = "[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]"


# ----------------------------------------------------------------------------- two backends added by a test


@dataclass
class EchoConfig(BackendConfig):
    name: str = "echo"
    answer: str = "[]"
    """The text every sample answers."""

    answer_keys = ("answer",)  # its keys that change the answers join every cache key


class EchoBackend(Backend):
    """The example of docs/prompting.md ("Adding a backend"), plus a call counter."""

    name, config_class = "echo", EchoConfig
    per_sample = False    # n answers in one request (True: the runner asks one at a time)
    cacheable = True      # answers go to the response cache
    takes_schema = False  # `structured_output: true` is refused
    key_env = None        # no API key (else the variable read when `api_key_env` is unset)
    calls: list[int] = []

    @classmethod
    def is_local(cls, cfg):  # runs here: USD 0 unless `prices` names the model
        return True

    def __init__(self, cfg, model):
        self.model, self.answer = model.name, cfg.answer

    @classmethod
    def from_config(cls, cfg, model, decoding, grid=None, catalog=None):
        return cls(cfg, model)

    def complete(self, prompt, n, temperature, max_tokens, seed=None):
        EchoBackend.calls.append(n)
        return [Completion(self.answer, input_tokens=0, output_tokens=0) for _ in range(n)]


@dataclass
class MeteredConfig(BackendConfig):
    name: str = "metered"


class MeteredBackend(Backend):
    """A paid API without `n` that bills 7 tokens an image and reads its key from METERED_API_KEY."""

    name, config_class = "metered", MeteredConfig
    per_sample, cacheable, takes_schema, key_env = True, True, True, "METERED_API_KEY"
    calls: list[int] = []

    @classmethod
    def image_tokens(cls, width, height, cfg, model):
        return 7

    @classmethod
    def from_config(cls, cfg, model, decoding, grid=None, catalog=None):
        api_key(cls.key_env)
        backend = cls()
        backend.model = model.name
        return backend

    def complete(self, prompt, n, temperature, max_tokens, seed=None):
        MeteredBackend.calls.append(n)
        return [Completion(GOOD, input_tokens=1000, output_tokens=10) for _ in range(n)]


@pytest.fixture
def added(monkeypatch):
    monkeypatch.setitem(BACKENDS, "echo", f"{__name__}:EchoBackend")
    monkeypatch.setitem(BACKENDS, "metered", f"{__name__}:MeteredBackend")
    EchoBackend.calls, MeteredBackend.calls = [], []


@pytest.fixture
def data(tmp_path):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path / "data")


def config(tmp_path, data, backend: dict, model: dict | str | None = None, extra: dict | None = None,
           **decoding) -> str:
    """A zero-shot config: `backend` (its section), `model` (the section, or its name), `decoding` keys (n 3,
    temperature 1) and `extra` top-level keys."""
    cfg = {"method": "mogma", "dataset": str(data), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "render_size": 64, "concurrency": 1, "backend": backend,
           "decoding": {"n": 3, "temperature": 1.0, **decoding}, **(extra or {})}
    if model is not None:
        cfg["model"] = {"name": model} if isinstance(model, str) else model
    path = tmp_path / "zeroshot.yaml"
    path.write_text("# degusta predict --config zeroshot.yaml\n" + yaml.safe_dump(cfg))
    return str(path)


def ledger(tmp_path) -> dict:
    return json.loads((tmp_path / "run" / "ledger.json").read_text())


# ----------------------------------------------------------------------------- declarations


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_registered_backend_declares_what_it_is(name):
    cls = backend_class(name)
    assert issubclass(cls, Backend) and cls.name == name
    declared = {k for c in cls.__mro__ if c is not Backend for k in vars(c)}
    assert {"config_class", "per_sample", "cacheable", "takes_schema", "key_env"} <= declared, \
        f"{name}: a backend declares its capabilities itself"
    assert issubclass(cls.config_class, BackendConfig) and cls.config_class().name == name
    assert all(isinstance(getattr(cls, k), bool) for k in ("per_sample", "cacheable", "takes_schema"))
    assert set(cls.config_class.answer_keys) <= {f.name for f in fields(cls.config_class)}


def test_the_shipped_backends_capabilities():
    openai, local = backend_config("openai"), backend_config("openai", base_url="http://127.0.0.1:8000/v1")
    cls = {n: backend_class(n) for n in BACKENDS}
    assert [n for n in BACKENDS if cls[n].per_sample] == ["anthropic", "gemini"]
    assert [n for n in BACKENDS if not cls[n].cacheable] == ["replay"]
    assert [n for n in BACKENDS if not cls[n].takes_schema] == ["hf"]
    assert {n: cls[n].key_env for n in BACKENDS} == {"openai": "OPENAI_API_KEY", "anthropic": "ANTHROPIC_API_KEY",
                                                     "gemini": "GEMINI_API_KEY", "hf": None, "replay": None}
    gpt4o = ModelSettings(name="gpt-4o")
    assert cls["openai"].price(openai, gpt4o, {}) == (2.5, 10.0) and cls["openai"].price(local, gpt4o, {}) is None
    assert cls["openai"].price(backend_config("openai", base_url="http://localhost/v1"), ModelSettings(name="q"),
                               {"q": [1.0, 2.0]}) == (1.0, 2.0)  # a local model priced on request
    assert cls["hf"].price(backend_config("hf"), gpt4o, {}) is None  # local, whatever its name
    assert cls["anthropic"].price(backend_config("anthropic"), ModelSettings(name="claude-3-haiku-x"),
                                  {}) == (0.25, 1.25)
    assert cls["gemini"].image_tokens(768, 768, backend_config("gemini"), ModelSettings()) == 258
    assert cls["openai"].image_tokens(768, 768, openai, gpt4o) == 765
    assert cls["openai"].image_tokens(768, 768, backend_config("openai", detail="low"), gpt4o) == 85
    assert [n for n in BACKENDS if cls[n].local_decoding] == ["hf"]
    assert {n: cls[n].default_model for n in BACKENDS} == {"openai": "gpt-4o", "anthropic": "", "gemini": "",
                                                           "hf": "", "replay": "replay"}


# ----------------------------------------------------------------------------- config sections


@pytest.mark.parametrize("backend, key, owner", [
    ({"name": "openai", "device": "cpu"}, "device", "hf"),
    ({"name": "hf", "timeout": 3}, "timeout", "openai, anthropic, gemini"),
    ({"name": "replay", "path": "p", "base_url": "http://x"}, "base_url", "openai, anthropic, gemini"),
    ({"name": "anthropic", "detail": "low"}, "detail", "openai"),
])
def test_a_key_of_another_backend_is_one_line_naming_it(tmp_path, capsys, backend, key, owner):
    """These were accepted (one flat config held every backend's keys) and silently ignored."""
    code = cli_main(["predict", "--config", config(tmp_path, "nowhere", backend)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert f"backend.{key}: not a key of the {backend['name']} backend but of {owner}" in err
    with pytest.raises(DegustaError, match=f"backend.{key}: not a key"):
        backend_config(**backend)


def test_a_section_takes_its_backends_keys_and_nothing_else(added):
    with pytest.raises(DegustaError, match=r"unknown key 'backend.modle' \(known keys: name, path, "
                                           r"structured_output\)"):
        backend_config("replay", modle="x")
    with pytest.raises(DegustaError, match="backend.answer: not a key of the openai backend but of echo"):
        backend_config("openai", answer="[]")
    with pytest.raises(DegustaError, match="backend.name: unknown backend 'gpt'"):
        backend_config("gpt")
    with pytest.raises(DegustaError, match="backend.structured_output: the echo backend takes no JSON schema; "
                                           "it works with openai, anthropic, gemini, replay, metered$"):
        backend_config("echo", structured_output=True)
    with pytest.raises(DegustaError, match="configured by OpenAIConfig"):
        BackendConfig(name="openai")  # the common keys alone are no backend's config
    assert backend_config("echo", answer="x") == EchoConfig(answer="x")


def test_shipped_predict_configs_load_into_their_backends_config():
    from degusta_learn.config import read_yaml

    names = [n for n in shipped_names() if n.startswith(("zeroshot_", "predict_hf_"))]
    assert len(names) >= 9
    for name in names:
        path = shipped_config(name)
        _, cfg = build_config(path, [], "method", get_method)
        raw = read_yaml(path)
        section = raw["backend"]
        assert type(cfg.backend) is backend_class(section["name"]).config_class, name
        assert all(getattr(cfg.backend, k) == v for k, v in section.items()), name
        assert all(getattr(cfg.model, k) == v for k, v in raw["model"].items()), name
        assert all(getattr(cfg.decoding, k) == v for k, v in raw["decoding"].items()), name


def test_cache_keys_are_those_of_the_one_flat_config():
    """Keys computed by the code before the per-backend configs (and before the model and its decoding left the
    backend section for `model:` and `decoding:`): existing caches stay valid."""
    golden = {
        "openai": ("gpt-4o", {}, "406e499bdd7cfe26b26ef03658921ea947bee84b823b8295c93e56e96cd4c98b"),
        "openai_local": ("qwen", {"base_url": "http://127.0.0.1:8000/v1", "detail": "low", "timeout": 5,
                                  "api_key_env": "X"}, "b7fecdb2b67071d1f80de52fa2af80f4e428f2b4b070a2f533ba2cc36f4e87dc"),
        "anthropic": ("claude-3-haiku-20240307", {"base_url": "http://proxy/v1"},
                      "8c90649597900f538ed8460b8135dee4bc58f308060ccfebda7c13e12d77a318"),
        "gemini": ("gemini-1.5-pro", {}, "795a2d2ede2850697f0329716f8981887d4f507ac908cec25f63df9caccbbdb7"),
        "replay": ("gpt-4o", {"path": "answers.jsonl"},  # the default model before "replay"
                   "0b83b2cbab210c58b47f5d68972ace73b1a9e8ebeeccea0f0cbb439b6e2b1f79"),
    }
    prompt = Prompt("mogma", ["objects:", "the task"], episode="p001/t2/k4")
    api = DecodingSettings().resolved(local=False)
    for tag, (model, keys, expected) in golden.items():
        cfg = backend_config(tag.split("_")[0], **keys)
        assert sample_keys(prompt, cfg, ModelSettings(name=model), api, 1.0, 1024, 0, 2)[1] == expected, tag
    structured = sample_keys(prompt, backend_config("openai"), ModelSettings(name="gpt-4o"), api, 0.5, 100, None, 1,
                             schema={"type": "object"})[0]
    assert structured == "3ab364389e2742d7f28794fda9aed6c653e369ade34351ee7454dc3311b71e69"


def test_hf_answers_cached_before_the_decoding_changed_are_not_reused():
    """The tight grammar and per-answer noise streams (hf DECODING_VERSION 2) change what a seeded answer is:
    the key the code before them computed (pinned here) must not be hit again."""
    from degusta_learn.prompting.backends.hf import DECODING_VERSION

    prompt = Prompt("mogma", ["objects:", "the task"], episode="p001/t2/k4")
    cfg = backend_config("hf", device="cpu")
    model = ModelSettings(name="no/such/folder", adapter="no/adapter", dtype="float32", image_size=64)
    decoding = DecodingSettings(constrained=True)
    key = sample_keys(prompt, cfg, model, decoding, 1.0, 1024, 0, 2)[1]
    assert DECODING_VERSION >= 2 and cfg.answer_fields(model, decoding)["decoding"] == DECODING_VERSION
    assert key != "aec74a5493733d442445e81f8c45121f0c2627670c63f2d108d0747018b0cc1c"


def test_hf_cache_keys_follow_every_model_and_decoding_key():
    """The keys that moved from `backend:` to `model:` and `decoding:` still key hf answers: a different value of any
    of them asks again (the same values key what they keyed as backend keys, pinned above for the API backends)."""
    prompt = Prompt("mogma", ["objects:", "the task"], episode="p001/t2/k4")
    cfg = backend_config("hf")
    base = (ModelSettings(name="m", adapter="a"), DecodingSettings(constrained=True))
    seen = {sample_keys(prompt, cfg, *base, 1.0, 100, 0, 1)[0]}
    for model, decoding in [(ModelSettings(name="m"), base[1]), (ModelSettings(name="m", adapter="a", dtype="float32"),
                            base[1]), (ModelSettings(name="m", adapter="a", image_size=64), base[1]),
                            (base[0], DecodingSettings(constrained=False)),
                            (base[0], DecodingSettings(constrained=True, on_repeat="stop")),
                            (base[0], DecodingSettings(constrained=True, report_unconstrained=False))]:
        seen.add(sample_keys(prompt, cfg, model, decoding, 1.0, 100, 0, 1)[0])
    assert len(seen) == 7


# ----------------------------------------------------------------------------- the runner asks the class


def test_a_new_backend_is_one_class_and_its_registry_entry(tmp_path, data, added):
    path = config(tmp_path, data, {"name": "echo", "answer": GOOD}, "echo-1")
    out = run_predict(path)
    preds = read_predictions(out, make_small_dataset(n_participants=3, n_trials=3).catalog)
    assert len(preds) == 9 and not any(p.failed for p in preds) and preds[0].placements[0].object == 75
    assert EchoBackend.calls == [3] * 9  # n answers a request
    first = ledger(tmp_path)
    assert first["backend"] == "echo" and first["cost_usd"] == 0 and first["price_usd_per_1m"] is None
    assert first["base_url"] is None and first["requests"] == 9
    run_predict(path)  # cacheable: the re-run is served from the response cache
    assert EchoBackend.calls == [3] * 9 and ledger(tmp_path)["samples_cached"] == 27
    run_predict(config(tmp_path, data, {"name": "echo", "answer": "[]"}, "echo-1"))
    assert EchoBackend.calls == [3] * 18 and ledger(tmp_path)["samples_cached"] == 0  # `answer` joins the cache key


def test_greedy_votes_ask_the_greedy_answer_apart_and_share_the_cache_with_plain_runs(tmp_path, data, added, capsys):
    """`aggregation: greedy_votes_pooled`: a request for the n samples and one at temperature 0 for the greedy answer,
    counted so by the dry run; its answers are cached under the keys a sampled run and a greedy run use, so
    either re-run asks nothing."""
    path = config(tmp_path, data, {"name": "echo", "answer": GOOD}, "echo-1", aggregation="greedy_votes_pooled")
    assert run_predict(path, dry_run=True) is None
    assert "requests: 18 for 36 samples" in capsys.readouterr().out
    run_predict(path)
    assert EchoBackend.calls == [3, 1] * 9 and ledger(tmp_path)["requests"] == 18
    run_predict(config(tmp_path, data, {"name": "echo", "answer": GOOD}, "echo-1", aggregation="steps"))
    run_predict(config(tmp_path, data, {"name": "echo", "answer": GOOD}, "echo-1", n=1, temperature=0.0))
    assert EchoBackend.calls == [3, 1] * 9 and ledger(tmp_path)["samples_cached"] == 9


def test_a_paid_per_sample_backend_is_asked_one_sample_at_a_time_priced_and_redacted(
        tmp_path, data, added, monkeypatch, capsys):
    monkeypatch.setenv("METERED_API_KEY", "metered-secret-0042")
    path = config(tmp_path, data, {"name": "metered"}, "metered-1", extra={"prices": {"metered-1": [1.0, 2.0]}})
    assert run_predict(path, dry_run=True) is None
    dry = capsys.readouterr().out
    assert "requests: 27 for 27 samples" in dry and "at USD 1 / 2 per 1M" in dry
    assert MeteredBackend.calls == []  # a dry run builds no backend
    run_predict(path)
    assert MeteredBackend.calls == [1] * 27  # one sample a request, each cached at once
    led = ledger(tmp_path)
    assert led["price_usd_per_1m"] == [1.0, 2.0]
    assert led["cost_usd"] == pytest.approx(27 * (1000 * 1.0 + 10 * 2.0) / 1e6)
    assert redact("echoed metered-secret-0042 back") == "echoed *** back"  # its key_env is scrubbed too


def test_image_tokens_and_requests_of_the_estimate_come_from_the_class(tmp_path, data, added, capsys):
    from degusta_learn.prompting.costs import prompt_tokens
    from degusta_learn.prompting.runner import ZeroShotRun
    from degusta_learn.scene import load_dataset, make_episodes

    path = config(tmp_path, data, {"name": "metered"}, "metered-1")
    _, cfg = build_config(path, [], "method", get_method)
    ds = load_dataset(data)
    run = ZeroShotRun(cfg, ds)
    prompt, _ = run.prompt(make_episodes(ds, 2, "all")[0])
    assert len(prompt.images) == 8  # 2 context arrangements, the target table, 5 object sheets
    assert run.input_tokens(prompt) == prompt_tokens(prompt, lambda w, h: 7) == prompt_tokens(prompt) - 8 * (255 - 7)


def test_a_dry_run_builds_no_backend_loads_no_model_and_needs_no_key(tmp_path, data, monkeypatch, capsys):
    def refuse(*a, **k):
        raise AssertionError("a dry run built a backend")

    for name in BACKENDS:
        monkeypatch.setattr(backend_class(name), "from_config", classmethod(refuse))
    monkeypatch.delenv("ANTHROPIC_API_KEY", raising=False)
    for backend, model in (({"name": "hf"}, {"name": str(tmp_path / "no_model"), "adapter": str(tmp_path / "no_adapter")}),
                           ({"name": "anthropic"}, "claude-3-5-sonnet"), ({"name": "replay"}, None)):
        assert run_predict(config(tmp_path, data, backend, model), dry_run=True) is None
        assert f"dry run: mogma with {backend['name']}" in capsys.readouterr().out


def test_hf_counts_its_own_image_tokens_from_the_processor():
    """The dry-run estimate of an hf row counts the model's image tokens at model.image_size (the tiny
    Idefics3: 4 px per token side, so 64 px -> 8 x 8 and 128 px -> 16 x 16), not OpenAI's tile rule."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from finetune_support import tiny_dir

    from degusta_learn.prompting.backends.hf import HFBackend

    model = str(tiny_dir("idefics3"))
    hf = backend_config("hf")
    assert HFBackend.image_tokens(448, 448, hf, ModelSettings(name=model, image_size=64)) == 64
    assert HFBackend.image_tokens(448, 448, hf, ModelSettings(name=model, image_size=128)) == 256
    generic = backend_class("openai").image_tokens(448, 448, backend_config("openai"), ModelSettings(name="gpt-4o"))
    assert HFBackend.image_tokens(448, 448, hf, ModelSettings(name="no/such/model")) == generic
