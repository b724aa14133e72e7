"""Seeds, sizes, resample counts, duplicate YAML keys, wrong types and contradictory settings: one line
naming the key (exit 2 or `DegustaError`), never a traceback, a memory blow-up or a silently wrong result.

Each CLI case runs `cli.main([...])` in-process and checks exit 2 and one "degusta: error:" line; each
library case checks the `DegustaError` message. Counted in docs/reliability.md ("Numbers, keys and types").
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pytest

from degusta_learn import cli
from degusta_learn.config import MAX_SEED, check_seed, from_dict, load_config, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry
from degusta_learn.metrics.bootstrap import MAX_RESAMPLES, bootstrap_ci, paired_bootstrap
from degusta_learn.render.lifting import Renderer
from degusta_learn.scene import load_dataset, make_episodes, split_participants, write_episodes

RANDOM = {"method": "random", "out": "p.jsonl", "context": 2, "split": "test", "seed": 0}


def run_cli(args, capsys) -> str:
    """Exit 2 with exactly one "degusta: error:" line and no traceback; returns that line."""
    rc = cli.main([str(a) for a in args])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("degusta: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


def write_yaml(path, data: dict):
    import yaml

    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture
def predict_cfg(tmp_path, small_dataset_dir):
    return write_yaml(tmp_path / "p.yaml", {**RANDOM, "dataset": str(small_dataset_dir),
                                            "out": str(tmp_path / "pred.jsonl")})


@pytest.fixture
def compare_cfg(tmp_path, small_dataset_dir, predict_cfg):
    return write_yaml(tmp_path / "c.yaml", {
        "dataset": str(small_dataset_dir), "out": str(tmp_path / "cmp"), "contexts": [2], "n_bootstrap": 50,
        "methods": [{"name": "rnd", "config": str(predict_cfg)},
                    {"name": "rnd2", "config": str(predict_cfg), "set": ["min_objects=2"]}]})


# -- 1. seeds ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", ["-5", "-1", str(MAX_SEED + 1), "99999999999999999999999999", "1.5", "true"])
def test_predict_seed_out_of_range_names_seed(predict_cfg, capsys, seed):
    err = run_cli(["predict", "--config", predict_cfg, "--set", f"seed={seed}"], capsys)
    assert "seed" in err


@pytest.mark.parametrize("seed", ["-1", str(2**32), "1e30"])
def test_compare_seed_out_of_range_names_seed(compare_cfg, capsys, seed):
    err = run_cli(["compare", "--config", compare_cfg, "--set", f"seed={seed}"], capsys)
    assert "seed" in err and not (compare_cfg.parent / "cmp").exists()


@pytest.mark.parametrize("seed", ["-1", "99999999999999999999999999"])
def test_generate_seed_out_of_range_cli(tmp_path, capsys, seed):
    run_cli(["data", "generate", "naturalistic", "--out", tmp_path / "g", "--seed", seed], capsys)
    assert not (tmp_path / "g").exists()


@pytest.mark.parametrize("name", ["naturalistic", "simulated"])
@pytest.mark.parametrize("seed", [-1, MAX_SEED + 1, 10**26, 1.0, True, None])
def test_generate_dataset_refuses_bad_seeds_before_writing(tmp_path, name, seed):
    from degusta_learn.synth import generate_dataset

    with pytest.raises(DegustaError, match="seed"):
        generate_dataset(name, tmp_path / "g", seed=seed)
    assert not (tmp_path / "g").exists()


def test_the_largest_seed_gives_a_dataset_validate_accepts(tmp_path, capsys):
    """The generator writes its seed into meta.json: the largest seed it takes must validate."""
    from degusta_learn.scene import save_dataset
    from degusta_learn.synth.naturalistic import naturalistic_with_styles

    ds, _ = naturalistic_with_styles(MAX_SEED, n_participants=3)
    save_dataset(ds, tmp_path / "d")
    assert cli.main(["data", "validate", str(tmp_path / "d")]) == 0, capsys.readouterr().err


@pytest.mark.parametrize("seed", [-1, MAX_SEED + 1, 2**70, 0.5, "3", True, np.int64(-2)])
def test_episode_library_entry_points_name_the_seed(small_dataset, seed):
    with pytest.raises(DegustaError, match="^seed: "):
        split_participants(small_dataset.participants, seed)
    with pytest.raises(DegustaError, match="^seed: "):
        make_episodes(small_dataset, 2, "test", seed)


@pytest.mark.parametrize("seed", [-1, MAX_SEED + 1, 2**70, 0.5, None])
def test_bootstrap_entry_points_name_the_seed(seed):
    with pytest.raises(DegustaError, match="^seed: "):
        bootstrap_ci([1.0, 2.0, 3.0], seed=seed)
    with pytest.raises(DegustaError, match="^seed: "):
        paired_bootstrap([1.0, 2.0], [0.5, 1.0], seed=seed)


def test_valid_seeds_are_kept():
    assert check_seed(0) == 0 and check_seed(MAX_SEED) == MAX_SEED and check_seed(np.uint32(7)) == 7


# -- 2. duplicate YAML keys -------------------------------------------------------------------------

@pytest.mark.parametrize("text, line, key", [
    ("method: random\ndataset: d\nout: o\nmethod: oracle\n", 4, "'method'"),
    ("method: random\nbackend:\n  name: openai\n  model: a\n  name: hf\n", 5, "'name'"),
    ("methods:\n  - {name: a, config: x, name: b}\n", 2, "'name'"),
    ("a: 1\n'a': 2\n", 2, "'a'"),
    ("x: {1: a, 1: b}\n", 1, "1"),
])
def test_duplicate_keys_are_refused_with_file_line_and_key(tmp_path, text, line, key):
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    with pytest.raises(DegustaError, match=f"dup.yaml:{line}: duplicate key {key}") as err:
        read_yaml(path)
    assert "\n" not in str(err.value)


def test_duplicate_key_through_the_cli(tmp_path, small_dataset_dir, capsys):
    path = tmp_path / "dup.yaml"
    path.write_text(f"method: random\ndataset: {small_dataset_dir}\nout: {tmp_path / 'o.jsonl'}\nmethod: oracle\n")
    err = run_cli(["predict", "--config", path], capsys)
    assert "dup.yaml:4: duplicate key 'method'" in err and not (tmp_path / "o.jsonl").exists()


def test_duplicate_key_in_a_set_value(predict_cfg, capsys):
    err = run_cli(["predict", "--config", predict_cfg, "--set", "backend={name: a, name: b}"], capsys)
    assert "duplicate key 'name'" in err


def test_merge_keys_may_still_be_overridden(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("base: &b {x: 1, y: 2}\nother:\n  <<: *b\n  x: 3\n")
    assert read_yaml(path)["other"] == {"x": 3, "y": 2}


# -- 3. type confusion ------------------------------------------------------------------------------

@pytest.mark.parametrize("value", ["[random]", "{a: 1}", "5", "true", "null"])
def test_method_of_the_wrong_type_names_method(predict_cfg, capsys, value):
    err = run_cli(["predict", "--config", predict_cfg, "--set", f"method={value}"], capsys)
    assert "method" in err


@pytest.mark.parametrize("key, value", [
    ("out", "[a, b]"), ("out", "{a: 1}"), ("out", "2024"), ("out", "010"), ("out", "1.5"), ("split", "true"),
    ("dataset", "[x]"), ("context", "two"), ("context", "true"), ("context", "2.0"), ("seed", "[1]"),
    ("min_objects", "3.5"), ("episodes", "[a]"),
])
def test_predict_keys_of_the_wrong_type_name_the_key(predict_cfg, capsys, key, value):
    err = run_cli(["predict", "--config", predict_cfg, "--set", f"{key}={value}"], capsys)
    assert f"{key}:" in err


@dataclass
class _Inner:
    name: str = "x"


@dataclass
class _Typed:
    s: str = "a"
    i: int = 1
    f: float = 1.0
    b: bool = False
    xs: list[int] = field(default_factory=list)
    d: dict[str, float] = field(default_factory=dict)
    o: str | None = None
    lit: Literal["a", 1] = "a"
    inner: _Inner = field(default_factory=_Inner)


@pytest.mark.parametrize("key, value", [
    ("s", ["a"]), ("s", {"a": 1}), ("s", 3), ("s", 1.5), ("s", True), ("s", None),
    ("i", "1"), ("i", 1.0), ("i", True), ("i", [1]), ("i", None),
    ("f", "1.0"), ("f", True), ("f", float("nan")), ("f", 10**400), ("f", [1.0]),
    ("b", 1), ("b", "yes"), ("b", None),
    ("xs", 1), ("xs", "12"), ("xs", [1, "2"]), ("xs", [True]), ("xs", {"a": 1}),
    ("d", [1]), ("d", "a"), ("d", {"k": "v"}), ("d", {1: 2.0}),
    ("o", ["a"]), ("o", 3),
    ("lit", "b"), ("lit", True), ("lit", 1.0), ("lit", ["a"]),
    ("inner", "x"), ("inner", {"name": 3}), ("inner", {"nope": 1}),
])
def test_every_basic_type_is_enforced(key, value):
    with pytest.raises(DegustaError, match=f"^cfg: (unknown key .)?{key}") as err:
        from_dict(_Typed, {key: value}, where="cfg")
    assert "\n" not in str(err.value)


def test_well_typed_values_still_convert():
    cfg = from_dict(_Typed, {"s": "t", "i": 2, "f": 3, "b": True, "xs": [1], "d": {"k": 1}, "o": None, "lit": 1,
                             "inner": {"name": "n"}})
    assert cfg == _Typed("t", 2, 3.0, True, [1], {"k": 1.0}, None, 1, _Inner("n"))
    assert isinstance(cfg.f, float) and isinstance(cfg.d["k"], float)


# -- 4. memory bombs --------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [100_000, 4097, 63, 0, -1, 10**30, 1.5, True])
def test_renderer_bounds_the_image_size(small_dataset, size):
    with pytest.raises(DegustaError, match=r"^size \(image_size\): expected an image size from 64 to 4,096"):
        Renderer.for_dataset(small_dataset, size=size)


def test_catalog_sheet_refuses_a_sheet_past_the_pixel_cap(small_dataset, monkeypatch):
    from degusta_learn.render import lifting

    monkeypatch.setattr(lifting, "MAX_SHEET_PIXELS", 500 * 500)
    with pytest.raises(DegustaError, match="^size: a contact sheet of .* use a size of at most"):
        Renderer.for_dataset(small_dataset, size=400).catalog_sheet()


@pytest.mark.parametrize("args", [
    ["render", "episode", "{d}", "--participant", "p000", "--target", "0", "--context", "2", "--method", "mogma",
     "--out", "{t}/rx", "--size", "100000"],
    ["render", "catalog", "{d}", "--out", "{t}/c.png", "--size", "60000"],
    ["evaluate", "--dataset", "{d}", "--predictions", "{t}/x.jsonl", "--out", "{t}/ev", "--bootstrap", "100000000000"],
    ["evaluate", "--dataset", "{d}", "--predictions", "{t}/x.jsonl", "--out", "{t}/ev", "--bootstrap", "0"],
    ["evaluate", "--dataset", "{d}", "--predictions", "{t}/x.jsonl", "--out", "{t}/ev", "--seed", "-1"],
])
def test_cli_sizes_and_counts_are_bounded(tmp_path, small_dataset_dir, capsys, args):
    run_cli([a.format(d=small_dataset_dir, t=tmp_path) for a in args], capsys)


@pytest.mark.parametrize("n", [0, -3, MAX_RESAMPLES + 1, 10**11, 2.0, True, None])
def test_bootstrap_bounds_its_resamples_and_names_the_option(n):
    for call in (lambda: bootstrap_ci([1.0, 2.0, 3.0], n_resamples=n),
                 lambda: paired_bootstrap([1.0, 2.0], [0.0, 1.0], n_resamples=n)):
        with pytest.raises(DegustaError, match=r"^bootstrap \(n_bootstrap\): expected a number of resamples") as err:
            call()
        assert "n_resamples" not in str(err.value)


def test_bootstrap_at_the_cap_stays_small():
    mean, lo, hi = bootstrap_ci(np.arange(50.0), n_resamples=MAX_RESAMPLES, seed=3)
    assert lo <= mean <= hi


@pytest.mark.parametrize("key, value", [
    ("n_bootstrap", "100000000000"), ("n_bootstrap", "0"), ("n_bootstrap", "1e11"), ("qualitative", "-1"),
    ("qualitative", "100000"), ("render_size", "100000"), ("render_size", "8"), ("seed", "-1"),
])
def test_compare_numbers_are_bounded(compare_cfg, capsys, key, value):
    err = run_cli(["compare", "--config", compare_cfg, "--set", f"{key}={value}"], capsys)
    assert f"{key}:" in err and not (compare_cfg.parent / "cmp").exists()


def test_qualitative_is_checked_again_where_it_is_used(tmp_path):
    from types import SimpleNamespace

    from degusta_learn.evaluate.compare_report import _qualitative

    cfg = SimpleNamespace(qualitative=-1, seed=0, render_size=64)
    row = SimpleNamespace(method="m", episode="e", failed=True, set_rmsd=float("nan"))
    with pytest.raises(DegustaError, match="^qualitative: "):
        _qualitative(cfg, None, [row], {"m": []}, {"m": {}}, tmp_path)


# -- 5. contradictory settings ----------------------------------------------------------------------

@pytest.mark.parametrize("contexts", ["[]", "[2, 2]", "[0, 4, 0]", "[3]"])
def test_compare_contexts_must_be_distinct_lengths(compare_cfg, capsys, contexts):
    err = run_cli(["compare", "--config", compare_cfg, "--set", f"contexts={contexts}"], capsys)
    assert "contexts:" in err and not (compare_cfg.parent / "cmp").exists()


def test_compare_contexts_may_be_empty_with_an_episodes_file():
    cfg = CompareConfig(dataset="d", out="o", methods=[MethodEntry("a", predictions="p")], contexts=[],
                        episodes="e.jsonl")
    assert cfg.contexts == []


@pytest.fixture
def k4_episodes(tmp_path, small_dataset_dir):
    path = tmp_path / "ep4.jsonl"
    write_episodes(path, make_episodes(load_dataset(small_dataset_dir), 4, "test", 0))
    return path


@pytest.mark.parametrize("context", ["0", "2"])
def test_predict_context_must_match_the_episodes_file(predict_cfg, k4_episodes, capsys, context):
    out = predict_cfg.parent / "pred.jsonl"
    err = run_cli(["predict", "--config", predict_cfg, "--set", f"episodes={k4_episodes}",
                   "--set", f"context={context}"], capsys)
    assert f"context: {context} contradicts episodes:" in err and "length 4" in err and not out.exists()


@pytest.mark.parametrize("context", ["4", "null"])
def test_predict_context_that_matches_or_is_null_runs(predict_cfg, k4_episodes, capsys, context):
    rc = cli.main(["predict", "--config", str(predict_cfg), "--set", f"episodes={k4_episodes}",
                   "--set", f"context={context}"])
    assert rc == 0, capsys.readouterr().err


def test_predict_context_null_needs_an_episodes_file(predict_cfg, capsys):
    assert "context: null" in run_cli(["predict", "--config", predict_cfg, "--set", "context=null"], capsys)


def _prediction_lines(small_dataset_dir, tmp_path) -> tuple[dict, list]:
    ep = make_episodes(load_dataset(small_dataset_dir), 2, "test", 0)[0]
    record = {"episode": ep.id, "participant": ep.participant, "target": ep.target, "method": "m",
              "placements": [], "failed": True}
    return record, list(ep.context)


@pytest.mark.parametrize("k, n_claimed", [(3, 2), (4, 2), (0, 2), (2, 1)])
def test_evaluate_refuses_an_id_whose_k_contradicts_the_records_context(tmp_path, small_dataset_dir, capsys,
                                                                          k, n_claimed):
    record, context = _prediction_lines(small_dataset_dir, tmp_path)
    record["episode"] = record["episode"].rsplit("/k", 1)[0] + f"/k{k}"
    record["diagnostics"] = {"context": context[:n_claimed]}
    path = tmp_path / "pred.jsonl"
    path.write_text(json.dumps(record) + "\n")
    err = run_cli(["evaluate", "--dataset", small_dataset_dir, "--predictions", path, "--out", tmp_path / "ev"],
                  capsys)
    assert "pred.jsonl:1: field 'episode'" in err and f"context length {k}" in err
    assert not (tmp_path / "ev").exists()


def test_evaluate_accepts_an_id_whose_k_matches(tmp_path, small_dataset_dir, capsys):
    record, context = _prediction_lines(small_dataset_dir, tmp_path)
    record["diagnostics"] = {"context": context}
    path = tmp_path / "pred.jsonl"
    path.write_text(json.dumps(record) + "\n")
    rc = cli.main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(path),
                   "--out", str(tmp_path / "ev"), "--bootstrap", "20"])
    assert rc == 0, capsys.readouterr().err


def test_a_valid_compare_still_runs(compare_cfg, capsys):
    assert cli.main(["compare", "--config", str(compare_cfg), "--set", "qualitative=0"]) == 0, capsys.readouterr().err


def test_load_config_reports_wrong_types_in_compare_methods(tmp_path):
    path = write_yaml(tmp_path / "c.yaml", {"dataset": "d", "out": "o", "methods": [{"name": ["a"], "config": "x"}]})
    with pytest.raises(DegustaError, match=r"c.yaml: methods\[0\].name: expected a string"):
        load_config(CompareConfig, path)


@pytest.mark.parametrize("key", ["seed", "dataset", "split", "episodes", "context", "out"])
def test_compare_refuses_a_method_override_of_its_own_keys(tmp_path, small_dataset_dir, predict_cfg, capsys, key):
    """compare gives every run these keys itself: a method's `set: [seed=5]` was silently lost."""
    cfg = write_yaml(tmp_path / "c2.yaml", {
        "dataset": str(small_dataset_dir), "out": str(tmp_path / "cmp2"), "contexts": [2], "n_bootstrap": 50,
        "methods": [{"name": "rnd", "config": str(predict_cfg), "set": [f"{key}=5"]}]})
    err = run_cli(["compare", "--config", cfg], capsys)
    assert f"methods entry 'rnd': set: '{key}' is the comparison's own" in err
    assert not (tmp_path / "cmp2").exists()
