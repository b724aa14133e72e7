"""Model selection of fine-tuning: best_adapter/ is best.ckpt's weights, early stopping, per-field validation
metrics, atomic exports, and fp32 master weights for full fine-tuning."""

from __future__ import annotations

import json
import math
from pathlib import Path

import lightning as L
import pytest
import torch
from finetune_support import dataset, tiny_dir
from safetensors.torch import load_file

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.files.folders import write_folder
from degusta_learn.finetune import module as fm
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.finetune.export import MODEL_FOLDER, SELECTION_FILE
from degusta_learn.finetune.field_scores import field_counts
from degusta_learn.methods import run_train
from degusta_learn.render.grid import Grid
from degusta_learn.scene import Placement, save_dataset
from degusta_learn.scene.types import Arrangement
from degusta_learn.task.answer_format import answer_items
from degusta_learn.task.answers import AnswerItem

CONFIGS = Path(__file__).parent.parent / "configs"
GRID = Grid(8, 8)


def _overrides(tmp_path: Path, data: Path, steps: int, *extra: str) -> list[str]:
    return [f"dataset={data}", f"model.name={tiny_dir('idefics3')}", f"trainer.run_dir={tmp_path / 'runs'}",
            "trainer.run_name=t", f"trainer.max_steps={steps}", "trainer.val_check_interval=1",
            "trainer.progress_bar=false", "data.val_episodes=1", "data.max_train_episodes=8", "data.contexts=[0]",
            "data.batch_size=1", "data.render_size=64", "decoding.report_unconstrained=false",
            "trainer.log_every_n_steps=1", *extra]


def _scripted(monkeypatch, scores: dict[int, float]) -> None:
    """Validation without generation: the set score of the validation after step s is scores[s]."""

    def score(self, ex, constrained):
        return {"parsed": True, "rmsd": 0.0, "acc": 1.0, "set_rmsd": scores[self.global_step], "count_error": 0,
                "n_gt": 3, "n_matched": 3, "failed": False, "pairs": 3, "id_correct": 3, "cell_iou": 3.0,
                "direction_correct": 3, "text": "[]", "placements": []}

    monkeypatch.setattr(fm.FinetuneModule, "score_batch",
                        lambda self, examples, constrained, indices=None: [score(self, ex, constrained) for ex in examples])


def _lora_tensors(ckpt: Path) -> dict[str, torch.Tensor]:
    """best.ckpt / last.ckpt adapter tensors under peft's saved names (no `model.` prefix, no adapter name)."""
    state = torch.load(ckpt, weights_only=True, map_location="cpu")["state_dict"]
    return {k.removeprefix("model.").replace(".default.", "."): v for k, v in state.items()}


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_best_adapter_holds_best_ckpt_and_adapter_the_last(tmp_path, monkeypatch):
    data = save_dataset(dataset(), tmp_path / "data")
    _scripted(monkeypatch, {1: 0.10, 2: 0.05, 3: 0.08, 4: 0.09})  # improves, then worsens: best at step 2
    run = run_train(CONFIGS / "finetune_tiny_cpu.yaml", _overrides(tmp_path, data, 4))
    best, last = load_file(run / "best_adapter" / "adapter_model.safetensors"), \
        load_file(run / "adapter" / "adapter_model.safetensors")
    assert torch.load(run / "best.ckpt", weights_only=True)["global_step"] == 2
    assert _same(best, _lora_tensors(run / "best.ckpt"))
    assert _same(last, _lora_tensors(run / "last.ckpt")) and not _same(best, last)
    assert (run / "best_adapter" / "degusta_finetune.json").is_file()
    selection = json.loads((run / "best_adapter" / SELECTION_FILE).read_text())
    assert selection["step"] == 2 and selection["monitor"] == "val/set_rmsd" and selection["score"] == pytest.approx(0.05)
    assert not list(run.glob(".tmp-*"))  # no export left half-way
    # validation chose best_adapter/, not adapter/: only the last weights may be predicted on the val participants
    chosen = {d: json.loads((run / d / "degusta_finetune.json").read_text())["trained_on"]["chosen_on_val"]
              for d in ("best_adapter", "adapter", ".")}
    assert chosen == {"best_adapter": True, "adapter": False, ".": True}


def test_a_stale_best_adapter_is_redone_from_best_ckpt_at_the_end(tmp_path, monkeypatch):
    data = save_dataset(dataset(), tmp_path / "data")
    _scripted(monkeypatch, {1: 0.10, 2: 0.05, 3: 0.08})
    monkeypatch.setattr(fm.FinetuneModule, "on_validation_end", lambda self: None)  # as if a kill stopped the export
    run = run_train(CONFIGS / "finetune_tiny_cpu.yaml", _overrides(tmp_path, data, 3))
    assert _same(load_file(run / "best_adapter" / "adapter_model.safetensors"), _lora_tensors(run / "best.ckpt"))
    assert (run / "best_adapter" / "degusta_finetune.json").is_file()


def test_early_stopping_and_full_mode_best_model(tmp_path, monkeypatch, capsys):
    data = save_dataset(dataset(), tmp_path / "data")
    _scripted(monkeypatch, {1: 0.10, 2: 0.05, 3: 0.08, 4: 0.09, 5: 0.01, 6: 0.01})
    run = run_train(CONFIGS / "finetune_tiny_cpu.yaml", _overrides(
        tmp_path, data, 6, "trainer.early_stopping_patience=2", "lora.mode=full", "optim.lr=0.01"))
    assert torch.load(run / "last.ckpt", weights_only=True)["global_step"] == 4  # 2 validations without a gain
    assert "stopped early at step 4" in capsys.readouterr().err
    best = torch.load(run / "best.ckpt", weights_only=True)
    saved = load_file(run / "best_model" / "model.safetensors")
    assert best["global_step"] == 2 and (run / "best_model" / "degusta_finetune.json").is_file()
    name = next(k for k in saved if "layers.0.self_attn.q_proj" in k)
    assert torch.equal(saved[name], best["state_dict"]["model." + name])
    assert not torch.equal(saved[name], load_file(run / "model" / "model.safetensors")[name])
    # early stopping chose when the last weights were taken: they count as chosen on the validation participants
    assert json.loads((run / "model" / "degusta_finetune.json").read_text())["trained_on"]["chosen_on_val"] is True


def test_finetune_configs_select_on_the_set_score_and_refuse_half_master_weights(tmp_path):
    for path in sorted(CONFIGS.glob("finetune_*.yaml")):
        cfg = load_config(FinetuneConfig, path)
        assert cfg.trainer.monitor == "val/set_rmsd" and cfg.trainer.monitor_mode == "min", path.name
        assert cfg.trainer.monitor in fm.monitor_keys(cfg)
    assert load_config(FinetuneConfig, None, data={"trainer": {"max_steps": 3}}).trainer.monitor == "val/set_rmsd"
    assert load_config(FinetuneConfig, None, ["lora.mode=full"]).weights_dtype == "float32"  # auto: fp32 masters
    assert load_config(FinetuneConfig, None, ["model.dtype=bfloat16"]).weights_dtype == "bfloat16"  # LoRA base
    with pytest.raises(DegustaError, match="model.dtype: bfloat16 with lora.mode full .* bf16-mixed"):
        load_config(FinetuneConfig, CONFIGS / "finetune_smolvlm_256m.yaml", ["lora.mode=full"])
    with pytest.raises(DegustaError, match="trainer.precision: bf16-true"):
        load_config(FinetuneConfig, None, ["trainer.precision=bf16-true"])
    with pytest.raises(DegustaError, match="trainer.early_stopping_patience"):
        load_config(FinetuneConfig, None, ["trainer.early_stopping_patience=3", "trainer.monitor=null"])


def test_full_fine_tuning_loads_fp32_weights(monkeypatch):
    from degusta_learn.finetune import train

    seen = {}

    def fake_load(name, **kw):
        seen.update(kw)
        raise DegustaError("stop here")

    monkeypatch.setattr("degusta_learn.vlm.load.load_vlm", fake_load)
    cfg = load_config(FinetuneConfig, None, [f"model.name={tiny_dir('idefics3')}", "lora.mode=full"])
    with pytest.raises(DegustaError, match="stop here"):
        train.prepare_model(cfg)
    assert seen["dtype"] == "float32"


def _arrangement(ds, objects: list[tuple[int, float, float, float]]) -> Arrangement:
    base = ds.arrangements[0]
    return Arrangement(base.participant, base.trial, base.table, tuple(Placement(*o) for o in objects))


def test_field_counts_compare_ids_cells_and_directions_over_matched_pairs():
    ds = dataset()
    ids = ds.arrangements[0].placements
    a, b = ids[0].object, ids[1].object
    gt = _arrangement(ds, [(a, 0.3, 0.3, 0.0), (b, 0.7, 0.7, 90.0)])
    truth = answer_items(gt.placements, ds.catalog, "grid", GRID)
    cells_b = list(truth[1].cells)
    # object a exactly right; object b with one extra cell and the wrong direction
    items = [truth[0], AnswerItem(truth[1].type, b, cells_b + ["A1"], "S" if truth[1].direction != "S" else "N")]
    placements = [Placement(a, 0.3, 0.3, 0.0), Placement(b, 0.7, 0.7, 90.0)]
    f = field_counts(items, placements, gt, ds.catalog, GRID, "grid")
    extra = 0 if "A1" in cells_b else 1
    assert (f.pairs, f.id_correct, f.direction_correct) == (2, 2, 1)
    assert f.cell_iou == pytest.approx(1.0 + len(cells_b) / (len(cells_b) + extra))
    assert field_counts(None, [], gt, ds.catalog, GRID, "grid").pairs == 0  # a failed answer: no pairs


def test_validation_stats_show_a_one_object_answer_for_what_it_is():
    # three episodes of 5 objects answered with one right object each: Kabsch RMSD 0, set score near c
    rows = torch.tensor([[i, 1, 0, 0.0, 0.2, math.sqrt(4 / 5) * 0.2, 4, 5, 1, 0, 1, 1, 1.0, 1] for i in range(3)],
                        dtype=torch.float64)
    stats = fm.validation_stats(rows, "grid", unconstrained=True)
    assert stats["val/rmsd"] == 0.0 and stats["val/set_rmsd"] == pytest.approx(0.1789, abs=1e-4)
    assert stats["val/few_matched"] == 1.0 and stats["val/id_accuracy"] == 1.0 and stats["val/cell_iou"] == 1.0
    assert stats["val/count_error"] == 4 and stats["val/parse_rate_unconstrained"] == 0.0
    assert set(stats) <= fm.monitor_keys(load_config(FinetuneConfig, None, ["decoding.report_unconstrained=true"]))


def test_a_weights_folder_is_written_all_or_nothing_and_keeps_the_users_files(tmp_path):
    out = tmp_path / "best_adapter"
    with write_folder(out, MODEL_FOLDER) as d:
        (d / "adapter_model.safetensors").write_text("old")
    (out / "notes.md").write_text("mine")

    with pytest.raises(DegustaError, match="best_adapter.*No space left"), write_folder(out, MODEL_FOLDER) as d:
        (d / "adapter_model.safetensors").write_text("half")
        raise OSError(28, "No space left on device")
    assert (out / "adapter_model.safetensors").read_text() == "old" and [p.name for p in tmp_path.iterdir()] == [out.name]
    with write_folder(out, MODEL_FOLDER) as d:
        (d / "adapter_config.json").write_text("{}")
    assert sorted(p.name for p in out.iterdir()) == ["adapter_config.json", "notes.md"]
    assert [p.name for p in tmp_path.iterdir()] == [out.name]


class _Toy(L.LightningModule):
    """Linear regression whose validation logs a scripted val/rmsd and which records its checkpoint saves."""

    def __init__(self, scores: dict[int, float]):
        super().__init__()
        self.lin, self.scores, self.saved = torch.nn.Linear(2, 1), scores, []

    def training_step(self, batch, _):
        x, y = batch
        return ((self.lin(x) - y) ** 2).mean()

    def validation_step(self, batch, _):
        self.log("val/rmsd", self.scores[self.global_step])

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def on_save_checkpoint(self, checkpoint):
        self.saved.append(self.global_step)


def test_last_ckpt_follows_every_validation_even_without_improvement(tmp_path):
    from torch.utils.data import TensorDataset

    from degusta_learn.training import TrainerConfig, fit

    x = torch.randn(32, 2, generator=torch.Generator().manual_seed(0))
    data = L.LightningDataModule.from_datasets(
        TensorDataset(x, x.sum(1, keepdim=True)), TensorDataset(x[:4], x[:4].sum(1, keepdim=True)), batch_size=8)
    toy = _Toy({2: 0.5, 4: 0.3, 6: 0.4, 8: 0.45})
    cfg = TrainerConfig(run_dir=str(tmp_path), run_name="toy", max_epochs=-1, max_steps=8, accelerator="cpu", devices=1,
                        progress_bar=False, val_check_interval=2)
    run = fit(toy, data, cfg, full_config={"kind": "toy"})
    assert 6 in toy.saved  # Lightning's save_last alone skips the validations that do not improve the monitor
    assert torch.load(run / "best.ckpt", weights_only=True)["global_step"] == 4
