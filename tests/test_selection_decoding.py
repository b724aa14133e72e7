"""Selection that matches deployment: a best folder records the validation decoding that chose it (and on what), the
model card says so, predict warns when it decodes otherwise, and `decoding_from: adapter` decodes exactly so."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from finetune_support import dataset

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_train
from degusta_learn.prompting.runner import ZeroShotConfig
from degusta_learn.scene import save_dataset
from degusta_learn.vlm.record import SELECTION_FILE
from degusta_learn.vlm.settings import DecodingSettings

from test_finetune_select import CONFIGS, _overrides, _scripted

SELECTED = {"constrained": True, "on_repeat": "skip", "max_new_tokens": 320, "n": 1, "aggregation": "steps",
            "temperature": None, "report_unconstrained": False}
"""finetune_tiny_base_cpu.yaml's `decoding:` section, as a best folder records it."""
DEPLOYED = {"constrained": True, "on_repeat": "skip", "max_new_tokens": "auto", "n": 5,
            "aggregation": "greedy_votes_pooled", "temperature": 0.5}
"""predict_hf_base_finetuned.yaml's `decoding:` section."""


def _best_folder(tmp_path: Path, decoding: dict | None = SELECTED) -> Path:
    folder = tmp_path / "best_adapter"
    folder.mkdir(parents=True)
    record = {"monitor": "val/set_rmsd", "mode": "min", "score": 0.2, "step": 40, "epoch": 0, "checkpoint": "best.ckpt",
              "split": "val", "val_episodes": 16, "val_participants": 12}
    (folder / SELECTION_FILE).write_text(json.dumps({**record, **({"decoding": decoding} if decoding else {})}))
    return folder


def _predict_cfg(adapter: Path | None, decoding: dict, *keys: str, backend: str = "hf") -> ZeroShotConfig:
    data = {"method": "mogma", "dataset": "data/naturalistic", "out": "runs/x/predictions.jsonl",
            "backend": {"name": backend}, "model": {"name": "tiny_vlm_base", "adapter": str(adapter) if adapter else None},
            "decoding": decoding}
    if backend != "hf":
        data["model"] = {"name": "gpt-4o"}
    return load_config(ZeroShotConfig, data=data, overrides=list(keys))


def test_a_tiny_fine_tune_records_its_selection_decoding_and_predict_can_use_it(tmp_path, monkeypatch):
    data = save_dataset(dataset(), tmp_path / "data")
    _scripted(monkeypatch, {1: 0.30, 2: 0.10, 3: 0.20})  # best at step 2
    run = run_train(CONFIGS / "finetune_tiny_cpu.yaml",
                    _overrides(tmp_path, data, 3, "decoding.n=3", "decoding.temperature=0.7",
                               "decoding.aggregation=greedy_votes_pooled", "decoding.max_new_tokens=200"))
    selection = json.loads((run / "best_adapter" / SELECTION_FILE).read_text())
    assert {k: selection[k] for k in ("monitor", "step", "split", "val_episodes", "val_participants")} == \
        {"monitor": "val/set_rmsd", "step": 2, "split": "val", "val_episodes": 1, "val_participants": 1}
    assert selection["score"] == pytest.approx(0.10)
    assert selection["decoding"] == {"constrained": True, "on_repeat": "skip", "max_new_tokens": 200, "n": 3,
                                     "aggregation": "greedy_votes_pooled", "temperature": 0.7,
                                     "report_unconstrained": False}
    card = (run / "best_adapter" / "README.md").read_text()
    assert "at step 2 (epoch 0), on 1 validation episode of 1 participant (split val)" in card
    assert ("decoded as `{constrained: true, on_repeat: skip, max_new_tokens: 200, n: 3, aggregation: "
            "greedy_votes_pooled, temperature: 0.7, report_unconstrained: false}`") in card
    assert "decoded as" not in (run / "adapter" / "README.md").read_text()  # the last weights: no selection
    cfg = _predict_cfg(run / "best_adapter", DEPLOYED, "decoding_from=adapter")
    assert cfg.decoding == DecodingSettings(constrained=True, on_repeat="skip", max_new_tokens=200, n=3,
                                            aggregation="greedy_votes_pooled", temperature=0.7,
                                            report_unconstrained=False)


def test_a_decoding_other_than_the_selections_is_one_warning_line_naming_the_keys(tmp_path, capsys):
    folder = _best_folder(tmp_path)
    cfg = _predict_cfg(folder, DEPLOYED)
    assert cfg.decoding.n == 5 and cfg.decoding.temperature == 0.5  # a warning, not a change: computed as before
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("degusta: warning: decoding:")
    assert ("on max_new_tokens: 320 vs auto, n: 1 vs 5, aggregation: steps vs greedy_votes_pooled, "
            "temperature: 0.0 vs 0.5 (selected vs here)") in lines[0]
    assert "constrained" not in lines[0] and "on_repeat" not in lines[0]
    _predict_cfg(folder, DEPLOYED)  # the same config built again in this run (compare does): once
    assert capsys.readouterr().err == ""


def test_the_selections_own_decoding_warns_nothing(tmp_path, capsys):
    # temperature null is 0 at n = 1; report_unconstrained changes no scored answer
    same = {**SELECTED, "temperature": 0.0, "report_unconstrained": True}
    _predict_cfg(_best_folder(tmp_path / "a"), same)
    _predict_cfg(_best_folder(tmp_path / "b", decoding=None), DEPLOYED)  # exported before decoding was recorded
    _predict_cfg(None, DEPLOYED)  # no adapter
    assert capsys.readouterr().err == ""


def test_decoding_from_adapter_takes_the_recorded_decoding_exactly(tmp_path, capsys):
    cfg = _predict_cfg(_best_folder(tmp_path), DEPLOYED, "decoding_from=adapter")
    assert cfg.decoding == DecodingSettings(**SELECTED)
    assert cfg.decoding.sampling_temperature == 0.0 and capsys.readouterr().err == ""


@pytest.mark.parametrize("where", ["no_decoding", "no_adapter", "api"])
def test_decoding_from_adapter_without_a_recorded_decoding_is_one_line(tmp_path, where):
    with pytest.raises(DegustaError, match=r"decoding_from: adapter") as e:
        if where == "no_decoding":  # a best folder exported before the decoding was recorded, or the last weights
            _predict_cfg(_best_folder(tmp_path, decoding=None), DEPLOYED, "decoding_from=adapter")
        elif where == "no_adapter":
            _predict_cfg(None, DEPLOYED, "decoding_from=adapter")
        else:
            _predict_cfg(None, {"n": 1}, "decoding_from=adapter", backend="openai")
    assert "\n" not in str(e.value) and "decoding_from: config" in str(e.value)
