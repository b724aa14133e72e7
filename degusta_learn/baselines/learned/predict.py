"""`degusta predict` for a trained learned model: load a checkpoint weights-only, decode every episode.

`checkpoint` is a run folder (its best.ckpt, else last.ckpt) or a .ckpt file. Loading uses
`torch.load(..., weights_only=True)`; a file that is not a checkpoint, or a checkpoint of another model kind
(e.g. a fine-tuning run), is refused with a DegustaError naming the file.

Usage:
    degusta predict --config configs/learned_predict.yaml --set checkpoint=runs/learned_cpu --set context=2
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from degusta_learn.baselines.learned.features import Vocab, onto_surface
from degusta_learn.baselines.learned.module import FORMAT, KIND
from degusta_learn.baselines.learned.slot_model import ModelConfig, SlotModel
from degusta_learn.baselines.learned.slots import SlotEncoder, collate_slots
from degusta_learn.devices import resolve_device
from degusta_learn.errors import DegustaError
from degusta_learn.methods import PredictConfig
from degusta_learn.scene import Dataset, Episode, Placement, Prediction
from degusta_learn.training.model_checkpoint import load_weights, read_checkpoint, resolve_checkpoint


@dataclass
class LearnedPredictConfig(PredictConfig):
    """Predict config of method `learned`: the PredictConfig keys plus the checkpoint to use."""

    checkpoint: str = ""
    """A run folder (uses best.ckpt, else last.ckpt) or a .ckpt file."""
    batch_size: int = 64
    """Episodes decoded together."""
    device: str = "cpu"
    """Torch device for decoding ("cpu", "cuda", "cuda:1")."""
    num_threads: int | None = 1
    """CPU threads torch may use (null: torch's default; decoding is light, 1 suits shared machines)."""

    def __post_init__(self):
        super().__post_init__()
        if not self.checkpoint:
            raise DegustaError("checkpoint: required (a run folder such as runs/learned_cpu, or a .ckpt)")


def load_model(path: str | Path, device: str = "cpu") -> tuple[SlotModel, dict]:
    """Load a learned-model checkpoint weights-only; returns (model in eval mode, hyperparameters with
    "population" as {table id: rows})."""
    ckpt_path, ckpt, hp = read_checkpoint(path, device, KIND, FORMAT, "learned-model (slot model)")
    model = load_weights(SlotModel(ModelConfig(**hp["model"]), Vocab(**hp["vocab"])), ckpt, ckpt_path, "slot model")
    hp = {**hp, "population": {int(t): rows for t, rows in hp["population"]}}
    return model.to(device).eval(), hp


def predict_episodes(model: SlotModel, ds: Dataset, episodes: list[Episode], population: dict,
                     min_objects: int = 1, batch_size: int = 64, method: str = KIND,
                     diagnostics: dict | None = None) -> list[Prediction]:
    """Predictions for `episodes` (one Prediction each, placements on the target table's surface);
    `population`: {table id: rows}, the checkpoint's population rows (used at context 0)."""
    device = next(model.parameters()).device
    encode = SlotEncoder(model.vocab, ds.tables, population, model.cfg.max_objects)
    ids = [o["id"] for o in model.vocab.catalog]
    out = []
    for start in range(0, len(episodes), batch_size):
        chunk = episodes[start:start + batch_size]
        samples = []
        for e in chunk:
            table = ds.arrangement(e.participant, e.target).table
            ctx = [ds.arrangement(e.participant, c) for c in e.context]
            samples.append(encode(ctx, table))
        batch = {k: v.to(device) for k, v in collate_slots(samples).items()}
        for e, rows, xy, rot in zip(chunk, *model.decode(batch, min_objects)):
            table = ds.arrangement(e.participant, e.target).table
            xy = onto_surface(ds.tables[table], xy)
            placements = [Placement(ids[r], float(x), float(y), float(a) % 360.0) for r, (x, y), a in zip(rows, xy, rot)]
            out.append(Prediction(e.id, e.participant, e.target, method, placements, False, dict(diagnostics or {})))
    return out


def run(cfg: LearnedPredictConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    """MethodSpec.run of method `learned` (on `cfg.num_threads` torch threads, restored after)."""
    from degusta_learn.training import torch_threads

    with torch_threads(cfg.num_threads):
        return _run(cfg, ds, episodes)


def _run(cfg: LearnedPredictConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    ckpt = str(resolve_checkpoint(cfg.checkpoint))
    model, hp = load_model(ckpt, resolve_device(cfg.device, "device"))
    model.vocab.check_catalog(ds.catalog, f"{cfg.dataset}/catalog.json")
    if isinstance(hp.get("trained_on"), dict):  # checkpoints before it recorded its split: unchecked
        from degusta_learn.scene.dataset import dataset_identity
        from degusta_learn.vlm.record import TrainingData

        TrainingData(**hp["trained_on"]).check_unseen(dataset_identity(ds), {e.participant for e in episodes}, ckpt)
    with torch.no_grad():
        return predict_episodes(model, ds, episodes, hp["population"], hp.get("min_objects", 1), cfg.batch_size,
                                diagnostics={"checkpoint": ckpt})
