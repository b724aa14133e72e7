"""`degusta train` for the learned arrangement model (config `kind: learned`).

Loads the dataset, builds the vocabulary, the LightningModule and the DataModule, and hands them to the
shared `degusta_learn.training.fit` (run folder `runs/<run>/` with config.yaml, last.ckpt, best.ckpt
by validation RMSD, CSV + TensorBoard logs; resumes from last.ckpt).

Usage:
    degusta train --config configs/learned_cpu.yaml
    degusta train --config configs/learned_cpu.yaml --set trainer.max_epochs=2 --set trainer.run_name=smoke
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from degusta_learn.baselines.learned.data import ArrangementDataModule, DataConfig, split_of
from degusta_learn.baselines.learned.features import Vocab
from degusta_learn.baselines.learned.module import (
    KIND,
    LEARNED_OPTIM,
    LearnedModule,
    monitor_keys,
    population_pairs,
)
from degusta_learn.baselines.learned.slot_model import ModelConfig
from degusta_learn.baselines.learned.slots import SlotEncoder, population_rows
from degusta_learn.config import bounded, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.optim import OptimConfig
from degusta_learn.scene import Dataset, load_dataset
from degusta_learn.scene.dataset import dataset_identity
from degusta_learn.training import TrainerConfig, fit, training_run
from degusta_learn.vlm.record import TrainingData


@dataclass
class LearnedTrainConfig:
    """A train config of kind `learned`: data, model, optimizer and trainer sections."""

    kind: str = KIND
    """Trainer kind (TRAINERS name); must be "learned"."""
    dataset: str = "data/naturalistic"
    """Dataset folder (`degusta data generate naturalistic --out data/naturalistic`)."""
    seed: int = seed_field()
    """Seed of the participant split; use the same `seed` in predict configs so test stays unseen."""
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=lambda: replace(LEARNED_OPTIM))
    """AdamW and its schedule (degusta_learn/optim.py, shared by every trainer)."""
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(run_name="learned"))
    num_threads: int | None = bounded(2, 1, 4096)
    """CPU threads torch may use (null: torch's default; keep small on shared machines)."""

    def __post_init__(self):
        if self.kind != KIND:
            raise DegustaError(f"kind: expected {KIND!r} for this config class, got {self.kind!r}")


def build(cfg: LearnedTrainConfig, ds: Dataset | None = None) -> tuple[LearnedModule, ArrangementDataModule]:
    """The LightningModule and DataModule of `cfg` (loads `cfg.dataset` unless `ds` is given)."""
    ds = ds if ds is not None else load_dataset(cfg.dataset)
    vocab = Vocab.from_dataset(ds)
    split = split_of(ds, cfg.seed, cfg.dataset)  # a clear error before the population needs a split
    population = population_rows(ds, cfg.seed)
    dm = ArrangementDataModule(cfg.data, ds, SlotEncoder(vocab, ds.tables, population, cfg.model.max_objects),
                              seed=cfg.seed, where=cfg.dataset)
    trained_on = TrainingData(dataset=str(cfg.dataset), fingerprint=dataset_identity(ds), seed=cfg.seed,
                              contexts=list(cfg.data.contexts), train_participants=split["train"],
                              val_participants=split["val"])  # learned predict refuses these participants
    module = LearnedModule(model=asdict(cfg.model), optim=asdict(cfg.optim), vocab=vocab.to_dict(),
                           population=population_pairs(population), min_objects=int(ds.meta.get("min_objects", 3)),
                           trained_on=asdict(trained_on))
    return module, dm


def dry_run(cfg: LearnedTrainConfig, ds: Dataset | None = None, log=print) -> None:
    """`degusta train --dry-run` for kind learned: parameters, slots per example, objects per arrangement
    against model.max_objects, steps per epoch and a memory estimate; trains and writes nothing.

    The slot model is small, so it is built for real on the CPU (random initial weights, nothing is loaded).
    Slots are counted over every (participant, target, context length) training item, once, unaugmented
    (augmentations move and relabel objects but keep their number). Refuses an arrangement with more
    objects than model.max_objects (the run would fail on it mid-epoch).
    """
    from degusta_learn.dryrun import (
        dry_run_trainer_lines,
        estimate_memory,
        print_dry_run,
        transformer_activations,
    )
    from degusta_learn.training import world_size

    ds = ds if ds is not None else load_dataset(cfg.dataset)
    most = max(ds.arrangements, key=lambda a: len(a.placements), default=None)
    if most is not None and len(most.placements) > cfg.model.max_objects:
        raise DegustaError(f"model.max_objects: {cfg.model.max_objects}, but participant {most.participant!r} trial "
                           f"{most.trial} of {cfg.dataset} has {len(most.placements)} objects; raise it to at "
                           f"least {len(most.placements)}")
    module, dm = build(cfg, ds)
    total = sum(p.numel() for p in module.parameters())
    trainable = sum(p.numel() for p in module.parameters() if p.requires_grad)
    items = dict.fromkeys(dm.train_set.items)  # unique (participant, target, k), in order
    slots, objects = [], []
    for p, t, k in items:
        trials = dm.train_set.trials[p]
        context = [a for j, a in enumerate(trials) if j != t][:k]
        slots.append(len(dm.train_set.encode(context, trials[t].table, trials[t])["slot_type"]))
        objects.append(len(trials[t].placements))
    val_slots = [len(dm.val_set[i]["slot_type"]) for i in range(len(dm.val_set))]
    S, B, m = max(slots), cfg.data.batch_size, cfg.model
    acts = transformer_activations(B * S, m.d_model, m.d_ff, m.n_layers, 4)
    acts += B * m.n_heads * S * S * 4 * 2 * m.n_layers  # attention weights (plain attention keeps them)
    mem = estimate_memory(total, trainable, 4, 4, acts, world_size(cfg.trainer),
                          note=f"float32; activations for a batch of {B} x {S} slots")
    lines = [("model", f"slot model (d_model {m.d_model}, {m.n_layers} layers, {m.n_heads} heads): {total:,} parameters, "
                       "random initial weights (nothing loaded)"),
             ("trainable", f"{trainable:,} parameters (all)"),
             ("slots per example", f"max {S} / mean {sum(slots) / len(slots):.1f} over {len(slots)} unique training "
                                   f"items (x data.repeats {cfg.data.repeats}, augmented afresh); validation: max "
                                   f"{max(val_slots, default=0)} over {len(val_slots)} episodes"),
             ("objects per target", f"max {max(objects)} / mean {sum(objects) / len(objects):.1f} of model.max_objects "
                                    f"{m.max_objects} ({max(objects) / m.max_objects:.0%} used)")]
    lines += dry_run_trainer_lines(cfg.trainer, monitor_keys(cfg.data.val_contexts), len(dm.train_set), B)
    lines.append(("predicted memory", mem.describe()))
    print_dry_run("dry run of kind learned: nothing trained or written", lines, log)


def train(cfg: LearnedTrainConfig, ds: Dataset | None = None) -> Path:
    """TrainerSpec.run of kind `learned`: train and return the run folder (seeded before the model is built)."""
    from degusta_learn.training import torch_threads

    monitors = monitor_keys(cfg.data.val_contexts)
    with torch_threads(cfg.num_threads), training_run(cfg.trainer, monitors):
        module, dm = build(cfg, ds)
        return fit(module, dm, cfg.trainer, full_config=cfg, monitors=monitors)
