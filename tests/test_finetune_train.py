"""End to end on CPU: `degusta train` (kind finetune) -> adapter -> resume -> `degusta predict` (hf backend)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from finetune_support import dataset, tiny_dir

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.methods import run_predict, run_train
from degusta_learn.scene import make_episodes, read_predictions, save_dataset, write_episodes

CONFIGS = Path(__file__).parent.parent / "configs"


def _overrides(tmp_path: Path, data: Path, steps: int) -> list[str]:
    return [f"dataset={data}", f"model.name={tiny_dir('idefics3')}", f"trainer.run_dir={tmp_path / 'runs'}",
            "trainer.run_name=t", f"trainer.max_steps={steps}", f"trainer.val_check_interval={steps}",
            "trainer.progress_bar=false", "data.val_episodes=2", "data.max_train_episodes=16",
            "data.batch_size=2", "data.render_size=128", "decoding.max_new_tokens=140",
            "decoding.report_unconstrained=false", "trainer.log_every_n_steps=1"]


def test_shipped_finetune_configs_load():
    for name in ["finetune_tiny_cpu", "finetune_smolvlm_256m", "finetune_smolvlm_500m", "finetune_qwen2vl_2b"]:
        cfg = load_config(FinetuneConfig, CONFIGS / f"{name}.yaml")
        assert cfg.kind == "finetune" and cfg.lora.targets
    with pytest.raises(DegustaError, match="lora.r"):
        load_config(FinetuneConfig, CONFIGS / "finetune_tiny_cpu.yaml", ["lora.r=0"])


@pytest.mark.slow
def test_train_resume_and_predict_with_the_hf_backend(tmp_path):
    data = save_dataset(dataset(), tmp_path / "data")
    cfg_path = CONFIGS / "finetune_tiny_cpu.yaml"
    run = run_train(cfg_path, _overrides(tmp_path, data, 3))
    adapter = run / "adapter"
    assert (adapter / "adapter_config.json").is_file() and (adapter / "degusta_finetune.json").is_file()
    ckpt = torch.load(run / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 3
    assert ckpt["state_dict"] and all("lora_" in k for k in ckpt["state_dict"])  # no frozen base inside
    with open(next((run / "csv").glob("version_*/metrics.csv"))) as f:
        rows = list(csv.DictReader(f))
    val = [r for r in rows if r.get("val/parse_rate")]
    assert val and float(val[-1]["val/parse_rate"]) == 1.0  # constrained validation generation
    assert any(r.get("val/object_accuracy") for r in rows) and any(r.get("val/rmsd") for r in rows)

    # Resume: the same run folder continues from step 3 to step 5.
    run2 = run_train(cfg_path, _overrides(tmp_path, data, 5))
    assert run2 == run
    assert torch.load(run / "last.ckpt", weights_only=True, map_location="cpu")["global_step"] == 5

    # A config change other than trainer.* refuses to resume into the same folder.
    with pytest.raises(DegustaError, match="cannot resume"):
        run_train(cfg_path, _overrides(tmp_path, data, 6) + ["lora.r=8"])

    # Predict with base + adapter through the hf backend: predictions.jsonl like any method.
    episodes = tmp_path / "episodes.jsonl"
    write_episodes(episodes, make_episodes(dataset(), 2, "test", 0)[:2])
    out = run_predict(CONFIGS / "predict_hf_tiny_finetuned.yaml", [
        f"dataset={data}", f"episodes={episodes}", "context=2", f"out={tmp_path / 'pred' / 'predictions.jsonl'}",
        f"model.name={tiny_dir('idefics3')}", f"model.adapter={adapter}", "decoding.max_new_tokens=140",
        "render_size=128"])
    preds = read_predictions(out, dataset().catalog)
    assert len(preds) == 2 and not any(p.failed for p in preds) and all(p.placements for p in preds)
    with pytest.raises(DegustaError, match="grid"):  # the adapter knows the grid it was trained on
        run_predict(CONFIGS / "predict_hf_tiny_finetuned.yaml", [
            f"dataset={data}", f"episodes={episodes}", "context=2", f"out={tmp_path / 'pred2' / 'p.jsonl'}",
            f"model.name={tiny_dir('idefics3')}", f"model.adapter={adapter}", "render_size=128", "grid.rows=6"])
    with pytest.raises(DegustaError, match="render_size: this model was trained on images rendered at 128 px"):
        run_predict(CONFIGS / "predict_hf_tiny_finetuned.yaml", [  # refused before the model loads
            f"dataset={data}", f"episodes={episodes}", "context=2", f"out={tmp_path / 'pred3' / 'p.jsonl'}",
            f"model.name={tiny_dir('idefics3')}", f"model.adapter={adapter}"])


def test_bad_finetune_inputs_name_the_key(tmp_path):
    data = save_dataset(dataset(), tmp_path / "data")
    base = _overrides(tmp_path, data, 1)
    with pytest.raises(DegustaError, match="lora.targets"):
        run_train(CONFIGS / "finetune_tiny_cpu.yaml", base + ["lora.targets=[nothing_proj]"])
    with pytest.raises(DegustaError, match="data.max_length: 9999 exceeds the model's context"):
        run_train(CONFIGS / "finetune_tiny_cpu.yaml", base + ["data.max_length=9999"])
    with pytest.raises(DegustaError, match=r"data.max_length: episode .* image tokens"):
        run_train(CONFIGS / "finetune_tiny_cpu.yaml", base + ["data.max_length=200"])
    with pytest.raises(DegustaError, match="model.name: .*not in the local Hugging Face cache|model.name: .*neither"):
        run_train(CONFIGS / "finetune_tiny_cpu.yaml", base + ["model.name=nobody/nothing", "model.build_tiny=null"])
    if not torch.cuda.is_available():
        with pytest.raises(DegustaError, match="lora.mode: qlora needs a CUDA GPU"):
            run_train(CONFIGS / "finetune_tiny_cpu.yaml", base + ["lora.mode=qlora"])
