"""`degusta predict` for a trained set transformer: load a checkpoint weights-only, decode every episode.

`checkpoint` is a run folder (its best.ckpt, else last.ckpt) or a .ckpt file. A file that is not a checkpoint, a
checkpoint of another kind (the learned slot model, a fine-tuning run), weights that do not fit, a dataset with
another catalog, or participants the model trained or was validated on are refused in one line.

Usage:
    degusta predict --config configs/set_transformer_predict.yaml --set checkpoint=runs/set_transformer_cpu --set context=2
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from degusta_learn.baselines.learned.features import Vocab, onto_surface
from degusta_learn.baselines.set_transformer.encoding import SetEncoder, collate_sets
from degusta_learn.baselines.set_transformer.model import ModelConfig, SetTransformer
from degusta_learn.baselines.set_transformer.module import FORMAT, KIND
from degusta_learn.config import bounded
from degusta_learn.devices import resolve_device
from degusta_learn.errors import DegustaError
from degusta_learn.methods import PredictConfig
from degusta_learn.scene import Dataset, Episode, Placement, Prediction
from degusta_learn.training.model_checkpoint import load_weights, read_checkpoint, resolve_checkpoint


@dataclass
class SetTransformerPredictConfig(PredictConfig):
    """Predict config of method `set_transformer`: the PredictConfig keys plus the checkpoint to use."""

    checkpoint: str = ""
    """A run folder (uses best.ckpt, else last.ckpt) or a .ckpt file."""
    batch_size: int = bounded(64, 1, 65_536)
    """Episodes decoded together."""
    device: str = "cpu"
    """Torch device for decoding ("cpu", "cuda", "cuda:1", "auto")."""
    num_threads: int | None = bounded(1, 1, 4096)
    """CPU threads torch may use (null: torch's default; decoding is light, 1 suits shared machines)."""

    def __post_init__(self):
        super().__post_init__()
        if not self.checkpoint:
            raise DegustaError("checkpoint: required (a run folder such as runs/set_transformer_cpu, or a .ckpt)")


def load_model(path: str | Path, device: str = "cpu") -> tuple[SetTransformer, dict]:
    """Load a set-transformer checkpoint weights-only; returns (model in eval mode, hyperparameters)."""
    ckpt_path, ckpt, hp = read_checkpoint(path, device, KIND, FORMAT, "set-transformer")
    model = load_weights(SetTransformer(ModelConfig(**hp["model"]), Vocab(**hp["vocab"])), ckpt, ckpt_path,
                         "set transformer")
    return model.to(device).eval(), hp


def predict_episodes(model: SetTransformer, ds: Dataset, episodes: list[Episode], min_objects: int = 1,
                     batch_size: int = 64, method: str = KIND, diagnostics: dict | None = None) -> list[Prediction]:
    """One Prediction per episode, its placements pulled onto the target table's surface."""
    device = next(model.parameters()).device
    encode = SetEncoder(model.vocab, ds.tables, model.cfg.n_queries)
    ids = [o["id"] for o in model.vocab.catalog]
    out = []
    for start in range(0, len(episodes), batch_size):
        chunk = episodes[start:start + batch_size]
        tables = [ds.arrangement(e.participant, e.target).table for e in chunk]
        samples = [encode([ds.arrangement(e.participant, c) for c in e.context], t) for e, t in zip(chunk, tables)]
        batch = {k: v.to(device) for k, v in collate_sets(samples).items()}
        for e, table, rows, xy, rot in zip(chunk, tables, *model.decode(batch, min_objects)):
            xy = onto_surface(ds.tables[table], xy)
            placements = [Placement(ids[r], float(x), float(y), float(a)) for r, (x, y), a in zip(rows, xy, rot)]
            out.append(Prediction(e.id, e.participant, e.target, method, placements, False, dict(diagnostics or {})))
    return out


def run(cfg: SetTransformerPredictConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    """MethodSpec.run of method `set_transformer` (on `cfg.num_threads` torch threads, restored after)."""
    from degusta_learn.scene.dataset import dataset_identity
    from degusta_learn.training import torch_threads
    from degusta_learn.vlm.record import TrainingData

    with torch_threads(cfg.num_threads):
        ckpt = str(resolve_checkpoint(cfg.checkpoint))
        model, hp = load_model(ckpt, resolve_device(cfg.device, "device"))
        model.vocab.check_catalog(ds.catalog, f"{cfg.dataset}/catalog.json")
        if not isinstance(hp.get("trained_on"), dict):
            raise DegustaError(f"{ckpt}: holds no record of its training split; retrain it with `degusta train`")
        TrainingData(**hp["trained_on"]).check_unseen(dataset_identity(ds), {e.participant for e in episodes}, ckpt)
        with torch.no_grad():
            return predict_episodes(model, ds, episodes, hp.get("min_objects", 1), cfg.batch_size,
                                    diagnostics={"checkpoint": ckpt})
