"""`degusta train` for the learned arrangement model (config `kind: learned`).

Loads the dataset, builds the vocabulary, the LightningModule and the DataModule, and hands them to the
shared `degusta_learn.trainer.fit` (run folder `checkpoints/<run>/` with config.yaml, last.ckpt, best.ckpt
by validation RMSD, CSV + TensorBoard logs; resumes from last.ckpt).

Usage:
    degusta train --config configs/learned_cpu.yaml
    degusta train --config configs/learned_cpu.yaml --set trainer.max_epochs=2 --set trainer.run_name=smoke
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from degusta_learn.baselines.learned.data import ArrangementDataModule, DataConfig, split_of
from degusta_learn.baselines.learned.features import Vocab
from degusta_learn.baselines.learned.module import KIND, LearnedModule, OptimConfig, monitor_keys, population_pairs
from degusta_learn.baselines.learned.slot_model import ModelConfig
from degusta_learn.baselines.learned.slots import SlotEncoder, population_rows
from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError
from degusta_learn.scene import Dataset, load_dataset
from degusta_learn.trainer import TrainerConfig, fit, training_run


@dataclass
class LearnedTrainConfig:
    """A train config of kind `learned`: data, model, optimizer and trainer sections."""

    kind: str = KIND
    """Trainer kind (TRAINERS name); must be "learned"."""
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(run_name="learned"))
    num_threads: int | None = bounded(2, 1, 4096)
    """CPU threads torch may use (null: torch's default; keep small on shared machines)."""

    def __post_init__(self):
        if self.kind != KIND:
            raise DegustaError(f"kind: expected {KIND!r} for this config class, got {self.kind!r}")


def build(cfg: LearnedTrainConfig, ds: Dataset | None = None) -> tuple[LearnedModule, ArrangementDataModule]:
    """The LightningModule and DataModule of `cfg` (loads `cfg.data.dataset` unless `ds` is given)."""
    ds = ds if ds is not None else load_dataset(cfg.data.dataset)
    vocab = Vocab.from_dataset(ds)
    split_of(ds, cfg.data.split_seed, cfg.data.dataset)  # a clear error before the population needs a split
    population = population_rows(ds, cfg.data.split_seed)
    dm = ArrangementDataModule(cfg.data, ds, SlotEncoder(vocab, ds.tables, population, cfg.model.max_objects))
    module = LearnedModule(model=asdict(cfg.model), optim=asdict(cfg.optim), vocab=vocab.to_dict(),
                           population=population_pairs(population), min_objects=int(ds.meta.get("min_objects", 3)))
    return module, dm


def train(cfg: LearnedTrainConfig, ds: Dataset | None = None) -> Path:
    """TrainerSpec.run of kind `learned`: train and return the run folder (seeded before the model is built)."""
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    monitors = monitor_keys(cfg.data.val_context_lengths)
    with training_run(cfg.trainer, monitors):
        module, dm = build(cfg, ds)
        return fit(module, dm, cfg.trainer, full_config=cfg, monitors=monitors)
