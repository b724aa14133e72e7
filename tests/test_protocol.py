"""The evaluation protocol (docs/metrics.md, "Protocol: validation for choices, test once"): tools that choose refuse
the test split, training selects on the validation participants only, every prediction records its split and
choices, and evaluate / compare name the split in their reports."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest
import yaml
from benchmark_support import load_benchmark

from degusta_learn.errors import DegustaError
from degusta_learn.evaluate import evaluate_files
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry, compare
from degusta_learn.evaluate.report import TEST_REMINDER, VAL_REMINDER
from degusta_learn.methods import get_method, run_predict
from degusta_learn.methods.predict import run_choices
from degusta_learn.methods.registry import build_config, get_trainer
from degusta_learn.scene import (
    Placement,
    Prediction,
    load_dataset,
    make_episodes,
    read_predictions,
    split_participants,
    write_episodes,
    write_predictions,
)
from degusta_learn.scene.predictions import recorded_split
from degusta_learn.training import TrainerConfig
from degusta_learn.training.protocol import refuse_test_split, selection_episodes

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
WHY = "choices are made on the validation participants"


# --- tools that choose refuse the test split ---------------------------------------------------------------------


@pytest.mark.parametrize("split", ["test", "all"])
def test_refuse_test_split_says_why_in_one_line(split):
    with pytest.raises(DegustaError) as e:
        refuse_test_split(split, "--split", "choosing a decoding")
    text = str(e.value)
    assert "\n" not in text and text.startswith(f"--split: {split!r} refused for choosing a decoding: ")
    assert WHY in text and "the test split is for the final number" in text


def test_refuse_test_split_lets_validation_and_training_through():
    refuse_test_split("val", "--split", "choosing a decoding")
    refuse_test_split("train", "--split", "choosing a decoding")


def test_choose_decoding_refuses_to_choose_on_test_before_reading_anything(tmp_path, monkeypatch):
    bench = load_benchmark("choose_decoding")
    missing = tmp_path / "no_such_dataset"  # refused before the dataset or the files are read
    monkeypatch.setattr(sys, "argv", ["choose_decoding.py", str(tmp_path / "p.jsonl"), "--dataset", str(missing),
                                      "--split", "test"])
    with pytest.raises(SystemExit) as e:
        bench.main()
    assert str(e.value).startswith("error: --split: 'test' refused for choosing a decoding: ")
    assert WHY in str(e.value) and "--only WAY" in str(e.value)


def test_choose_decoding_scores_the_chosen_way_on_test(tmp_path, monkeypatch):
    """With --only the script chooses nothing: it goes on to read the dataset (and fails there, none given)."""
    bench = load_benchmark("choose_decoding")
    monkeypatch.setattr(sys, "argv", ["choose_decoding.py", str(tmp_path / "p.jsonl"), "--dataset",
                                      str(tmp_path / "no_such_dataset"), "--split", "test", "--only", "steps"])
    with pytest.raises(DegustaError, match="no_such_dataset"):
        bench.main()


# --- training selects on the validation participants ---------------------------------------------------------------


@pytest.mark.parametrize("monitor", ["test/set_rmsd", "test/rmsd", "test_loss", " Test/rmsd"])
def test_a_monitor_on_test_is_refused(monitor):
    with pytest.raises(DegustaError, match=r"trainer\.monitor: .* refused: the monitor picks best\.ckpt") as e:
        TrainerConfig(monitor=monitor)
    assert WHY in str(e.value)


def test_validation_and_other_monitors_are_kept():
    assert TrainerConfig(monitor="val/set_rmsd").monitor == "val/set_rmsd"
    assert TrainerConfig(monitor="testimony/x").monitor == "testimony/x"  # not the test split
    assert TrainerConfig(monitor=None).monitor is None


@pytest.mark.parametrize("config, overrides", [
    ("learned_cpu.yaml", ["trainer.monitor=test/rmsd"]),
    ("finetune_tiny_cpu.yaml", ["trainer.monitor=test/set_rmsd", "trainer.early_stopping_patience=2"]),
])
def test_a_train_config_that_selects_or_stops_early_on_test_is_refused(config, overrides):
    with pytest.raises(DegustaError) as e:
        build_config(CONFIGS / config, overrides, "kind", get_trainer)
    assert f"{config}: trainer.monitor: " in str(e.value) and WHY in str(e.value)


def test_selection_episodes_are_the_validation_participants_episodes(small_dataset):
    split = split_participants(small_dataset.participants, 3)
    episodes = selection_episodes(small_dataset, [0, 2], seed=3)
    assert {e.participant for e in episodes} == set(split["val"])
    assert [e.id for e in episodes] == [e.id for k in (0, 2) for e in make_episodes(small_dataset, k, "val", 3)]
    assert len(episodes) == 2 * 5 * len(split["val"])  # every trial a target, at both context lengths


def test_the_learned_models_validation_loader_holds_only_validation_participants(small_dataset):
    from degusta_learn.baselines.learned.data import ArrangementDataModule, DataConfig

    dm = ArrangementDataModule(DataConfig(), small_dataset, lambda ctx, table, target: {}, seed=0, where="small")
    split = split_participants(small_dataset.participants, 0)
    assert {e.participant for e in dm.val_episodes} == set(split["val"])
    assert not {e.participant for e in dm.val_episodes} & set(split["test"])


def test_fine_tunings_validation_examples_hold_only_validation_participants(small_dataset_dir):
    from degusta_learn.config import load_config
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.data import build_examples
    from degusta_learn.render.grid import Grid

    cfg = load_config(FinetuneConfig, CONFIGS / "finetune_tiny_cpu.yaml",
                      [f"dataset={small_dataset_dir}", "data.val_episodes=1000", "seed=1"])
    ds = load_dataset(small_dataset_dir)
    _, val = build_examples(cfg, ds, Grid(8, 8))
    assert {e.participant for e in val.episodes} == set(split_participants(ds.participants, 1)["val"])


# --- every prediction records its split and choices ----------------------------------------------------------------


def _predict(tmp_path: Path, ds_dir, name: str, **keys) -> list[Prediction]:
    cfg = {"method": "copy_nearest", "dataset": str(ds_dir), "out": str(tmp_path / f"{name}.jsonl"), "context": 2,
           "split": "val", "seed": 0, **keys}
    (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
    out = run_predict(tmp_path / f"{name}.yaml", log=lambda m: None)
    return read_predictions(out, load_dataset(ds_dir).catalog)


def test_predict_records_the_split_and_the_choices(small_dataset_dir, tmp_path):
    preds = _predict(tmp_path, small_dataset_dir, "val")
    assert preds and all(p.diagnostics["split"] == "val" for p in preds)
    choices = preds[0].diagnostics["choices"]
    assert set(choices) == {"method", "config_sha256", "seed", "episodes"}  # a heuristic: no weights, no decoding
    assert (choices["method"], choices["seed"], choices["episodes"]) == ("copy_nearest", 0, None)
    assert re.fullmatch(r"[0-9a-f]{64}", choices["config_sha256"])
    assert all(p.diagnostics["choices"] == choices for p in preds)
    same = _predict(tmp_path, small_dataset_dir, "val_again")[0].diagnostics["choices"]  # only `out` differs
    other = _predict(tmp_path, small_dataset_dir, "k4", context=4)[0].diagnostics["choices"]
    assert same["config_sha256"] == choices["config_sha256"] != other["config_sha256"]


def test_predict_records_the_weights_it_used(small_dataset_dir):
    _, cfg = build_config(CONFIGS / "predict_hf_tiny_finetuned.yaml", [f"dataset={small_dataset_dir}"], "method",
                          get_method)
    choices = run_choices(cfg)
    assert choices["model.adapter"] == "runs/finetune_tiny_cpu/best_adapter"
    assert (choices["model.name"], choices["decoding.n"], choices["decoding.constrained"]) == (
        "runs/tiny/idefics3", 1, True)
    assert "checkpoint" not in choices


def test_an_episodes_file_records_the_splits_its_participants_are_in(small_dataset_dir, tmp_path):
    ds = load_dataset(small_dataset_dir)
    split = split_participants(ds.participants, 0)
    test_eps = make_episodes(ds, 2, "test", 0)
    write_episodes(tmp_path / "test_eps.jsonl", test_eps)
    preds = _predict(tmp_path, small_dataset_dir, "file", episodes=str(tmp_path / "test_eps.jsonl"))
    assert {p.diagnostics["split"] for p in preds} == {"test"}
    assert preds[0].diagnostics["choices"]["episodes"] == str(tmp_path / "test_eps.jsonl")
    one_each = [next(e for e in make_episodes(ds, 2, s, 0) if e.participant == split[s][0]) for s in ("test", "val")]
    write_episodes(tmp_path / "mixed_eps.jsonl", one_each)
    preds = _predict(tmp_path, small_dataset_dir, "mixed", episodes=str(tmp_path / "mixed_eps.jsonl"))
    assert {p.diagnostics["split"] for p in preds} == {"val+test"}  # split order, whatever the file's order


def test_recorded_split_of_old_mixed_and_malformed_records():
    def pred(diagnostics):
        return Prediction("p/t0/k0", "p", 0, "m", [], diagnostics=diagnostics)

    assert recorded_split([pred({}), pred({"n_parsed": 1})]) == "not recorded"
    assert recorded_split([pred({"split": "test"})] * 3) == "test"
    assert recorded_split([pred({"split": "test"}), pred({"split": "val"}), pred({})]) == "mixed: val, test, not recorded"
    assert recorded_split([pred({"split": "<b>test</b>"}), pred({"split": 3})]) == "not recorded"


# --- reports name the split ----------------------------------------------------------------------------------------


def _perfect(ds, episodes, method: str, split: str | None) -> list[Prediction]:
    extra = {} if split is None else {"split": split}
    return [Prediction(e.id, e.participant, e.target, method,
                       [Placement(p.object, p.x, p.y, p.rotation) for p in ds.arrangement(e.participant, e.target).placements],
                       diagnostics=dict(extra)) for e in episodes]


def _evaluate(tmp_path, ds_dir, files: dict[str, tuple[str, str | None]]) -> tuple[str, dict]:
    """report.md's header (up to the results) and metrics.json of evaluate on one file per method."""
    ds = load_dataset(ds_dir)
    paths = []
    for method, (split, recorded) in files.items():
        path = tmp_path / f"{method}.jsonl"
        write_predictions(path, _perfect(ds, make_episodes(ds, 2, split, 0), method, recorded))
        paths.append(path)
    out = evaluate_files(ds_dir, paths, tmp_path / "ev", n_bootstrap=20)
    return (out / "report.md").read_text().split("## Results")[0], json.loads((out / "metrics.json").read_text())


def test_evaluate_on_test_names_the_split_and_says_the_numbers_are_final(small_dataset_dir, tmp_path):
    header, metrics = _evaluate(tmp_path, small_dataset_dir, {"a": ("test", "test"), "b": ("test", "test")})
    assert "Split (from the predictions' records): **test** participants.\n" in header
    assert TEST_REMINDER in header and "one look per result" in TEST_REMINDER
    assert metrics["a"]["split"] == metrics["b"]["split"] == "test"
    assert metrics["a"]["choices"] == []  # written by hand, not by `degusta predict`


def test_evaluate_on_validation_says_its_numbers_are_for_choosing(small_dataset_dir, tmp_path):
    header, metrics = _evaluate(tmp_path, small_dataset_dir, {"a": ("val", "val")})
    assert "Split (from the predictions' records): **val** participants.\n" in header
    assert VAL_REMINDER in header and TEST_REMINDER not in header
    assert metrics["a"]["split"] == "val"


def test_evaluate_of_an_older_file_says_not_recorded(small_dataset_dir, tmp_path):
    header, metrics = _evaluate(tmp_path, small_dataset_dir, {"old": ("test", None)})
    assert "Split (from the predictions' records): not recorded (predictions written before degusta recorded it)." \
        in header
    assert TEST_REMINDER not in header and VAL_REMINDER not in header
    assert metrics["old"]["split"] == "not recorded"


def test_evaluate_of_methods_on_different_splits_names_each(small_dataset_dir, tmp_path):
    header, metrics = _evaluate(tmp_path, small_dataset_dir, {"a": ("val", "val"), "b": ("test", "test")})
    assert "Split (from the predictions' records): **val** participants (a); **test** participants (b).\n" in header
    assert TEST_REMINDER in header  # one prediction on test is enough


def test_evaluate_reads_back_what_predict_recorded(small_dataset_dir, tmp_path):
    preds = _predict(tmp_path, small_dataset_dir, "cn", split="test")
    out = evaluate_files(small_dataset_dir, [tmp_path / "cn.jsonl"], tmp_path / "ev", n_bootstrap=20)
    metrics = json.loads((out / "metrics.json").read_text())["copy_nearest"]
    assert metrics["split"] == "test"
    assert metrics["choices"] == [preds[0].diagnostics["choices"]]
    assert TEST_REMINDER in (out / "report.md").read_text()


def test_compare_metrics_json_names_its_split(small_dataset_dir, tmp_path):
    ds = load_dataset(small_dataset_dir)
    episodes = make_episodes(ds, 2, "test", 0)
    write_predictions(tmp_path / "a.jsonl", _perfect(ds, episodes, "a", None))
    write_predictions(tmp_path / "b.jsonl", _perfect(ds, episodes, "b", "test"))
    write_episodes(tmp_path / "eps.jsonl", episodes)

    def split_of(name: str, predictions: str, **keys) -> str:
        cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp_path / name), contexts=[2],
                            methods=[MethodEntry("m", predictions=str(tmp_path / predictions))], n_bootstrap=20,
                            qualitative=0, render_size=64, **keys)
        return json.loads((compare(cfg, log=lambda m: None).out / "metrics.json").read_text())["split"]

    assert split_of("by_split", "a.jsonl", split="test") == "test"  # the comparison's own split
    assert split_of("recorded", "b.jsonl", episodes=str(tmp_path / "eps.jsonl")) == "test"  # what the records say
    assert split_of("old", "a.jsonl", episodes=str(tmp_path / "eps.jsonl")) == "not recorded"
