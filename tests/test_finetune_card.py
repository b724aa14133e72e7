"""Model folders the Hub and peft understand: every exported adapter / model folder carries a real model card."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from finetune_support import dataset, tiny_dir

from degusta_learn.config import load_config
from degusta_learn.finetune.card import CONFIG_FILE, card_base_model, card_text
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.methods import run_train
from degusta_learn.scene import save_dataset

CONFIGS = Path(__file__).parent.parent / "configs"


def front_matter(card: str) -> dict:
    assert card.startswith("---\n"), card[:80]
    head, _, _ = card[4:].partition("\n---\n")
    return yaml.safe_load(head)


def test_base_model_is_a_hub_id_or_a_relative_name_never_an_absolute_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs" / "base").mkdir(parents=True)
    assert card_base_model("HuggingFaceTB/SmolVLM-256M-Instruct") == "HuggingFaceTB/SmolVLM-256M-Instruct"
    assert card_base_model("tiny_vlm_base") == "tiny_vlm_base"
    assert card_base_model("runs/base") == "runs/base"
    assert card_base_model(str(tmp_path / "runs" / "base")) == "base"


@pytest.mark.parametrize("adapter", [True, False])
def test_card_front_matter_is_the_hubs_metadata(tmp_path, adapter):
    data = save_dataset(dataset(), tmp_path / "data")
    cfg = load_config(FinetuneConfig, CONFIGS / "finetune_tiny_base_cpu.yaml", [f"dataset={data}"])
    selection = {"monitor": "val/set_rmsd", "mode": "min", "score": 0.12, "step": 40, "epoch": 0}
    card = card_text(cfg, adapter, selection, {"val/set_rmsd": 0.1234, "val/object_accuracy": 0.3})
    meta = front_matter(card)
    assert meta["base_model"] == "tiny_vlm_base" and meta["pipeline_tag"] == "image-text-to-text"
    assert meta["library_name"] == ("peft" if adapter else "transformers")
    assert "degusta_learn" in meta["tags"]
    assert "0.1234" in card and "step 40" in card and f"degusta train --config {CONFIG_FILE}" in card
    assert "hf upload" in card and "small-test" in card  # the dataset's name
    assert str(tmp_path) not in card  # no local path in what gets published


@pytest.mark.slow
def test_a_training_run_writes_cards_that_peft_and_yaml_read(tmp_path):
    data = save_dataset(dataset(), tmp_path / "data")
    base = tiny_dir("idefics3")
    run = run_train(CONFIGS / "finetune_tiny_cpu.yaml", [
        f"dataset={data}", f"model.name={base}", f"trainer.run_dir={tmp_path / 'runs'}", "trainer.run_name=t",
        "trainer.max_steps=2", "trainer.val_check_interval=2", "trainer.progress_bar=false", "data.val_episodes=2",
        "data.max_train_episodes=8", "data.batch_size=2", "data.render_size=128", "decoding.max_new_tokens=140",
        "decoding.report_unconstrained=false", "trainer.log_every_n_steps=1"])
    for folder in ("adapter", "best_adapter"):
        card = (run / folder / "README.md").read_text()
        meta = front_matter(card)
        assert meta["library_name"] == "peft" and meta["base_model"] == base.name  # absolute -> the folder's name
        assert "val/set_rmsd" in card or "set RMSD" in card
        resolved = yaml.safe_load((run / folder / CONFIG_FILE).read_text())
        assert resolved["model"]["name"] == str(base) and resolved["kind"] == "finetune"
        adapter_config = json.loads((run / folder / "adapter_config.json").read_text())
        assert adapter_config["base_model_name_or_path"] == str(base)
    assert "best `val/set_rmsd`" in (run / "best_adapter" / "README.md").read_text()
    assert "last weights" in (run / "adapter" / "README.md").read_text()
    assert "| set RMSD" in (run / "best_adapter" / "README.md").read_text()  # the validation's scores, in a table
