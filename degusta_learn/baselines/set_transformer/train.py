"""`degusta train` for the set transformer (config `kind: set_transformer`).

Loads the dataset, builds the vocabulary, the LightningModule and the DataModule, and hands them to the shared
`degusta_learn.training.fit` (run folder `runs/<run>/` with config.yaml, last.ckpt, best.ckpt by validation set
RMSD, CSV + TensorBoard logs; resumes from last.ckpt), exactly as the learned slot model does.

Usage:
    degusta train --config configs/set_transformer_cpu.yaml
    degusta train --config configs/set_transformer_cpu.yaml --set trainer.max_epochs=1 --set trainer.run_name=smoke
    degusta train --config configs/set_transformer_cpu.yaml --dry-run
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from degusta_learn.baselines.learned.data import DataConfig, split_of
from degusta_learn.baselines.learned.features import Vocab
from degusta_learn.baselines.set_transformer.data import SetDataModule
from degusta_learn.baselines.set_transformer.encoding import SetEncoder
from degusta_learn.baselines.set_transformer.model import ModelConfig
from degusta_learn.baselines.set_transformer.module import KIND, SET_OPTIM, SetTransformerModule, monitor_keys
from degusta_learn.config import bounded, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.optim import OptimConfig
from degusta_learn.scene import Dataset, load_dataset
from degusta_learn.scene.dataset import dataset_identity
from degusta_learn.training import TrainerConfig, fit, training_run
from degusta_learn.vlm.record import TrainingData


@dataclass
class SetTransformerTrainConfig:
    """A train config of kind `set_transformer`: data, model, optimizer and trainer sections."""

    kind: str = KIND
    """Trainer kind (TRAINERS name); must be "set_transformer"."""
    dataset: str = "data/naturalistic"
    """Dataset folder (`degusta data generate naturalistic --out data/naturalistic`)."""
    seed: int = seed_field()
    """Seed of the participant split; use the same `seed` in predict configs so test stays unseen."""
    data: DataConfig = field(default_factory=DataConfig)
    """Episodes and augmentations (the learned slot model's `data:` section, docs/learned.md)."""
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=lambda: replace(SET_OPTIM))
    """AdamW and its schedule (degusta_learn/optim.py, shared by every trainer)."""
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(run_name="set_transformer",
                                                                         monitor="val/set_rmsd"))
    num_threads: int | None = bounded(2, 1, 4096)
    """CPU threads torch may use (null: torch's default; keep small on shared machines)."""

    def __post_init__(self):
        if self.kind != KIND:
            raise DegustaError(f"kind: expected {KIND!r} for this config class, got {self.kind!r}")


def check_queries(cfg: SetTransformerTrainConfig, ds: Dataset) -> None:
    """Refuse `model.n_queries` below the largest arrangement's object count (that target could not be matched)."""
    most = max(ds.arrangements, key=lambda a: len(a.placements), default=None)
    if most is not None and len(most.placements) > cfg.model.n_queries:
        raise DegustaError(f"model.n_queries: {cfg.model.n_queries}, but participant {most.participant!r} trial "
                           f"{most.trial} of {cfg.dataset} has {len(most.placements)} objects; raise it to at "
                           f"least {len(most.placements)}")


def build(cfg: SetTransformerTrainConfig, ds: Dataset | None = None) -> tuple[SetTransformerModule, SetDataModule]:
    """The LightningModule and DataModule of `cfg` (loads `cfg.dataset` unless `ds` is given)."""
    ds = ds if ds is not None else load_dataset(cfg.dataset)
    check_queries(cfg, ds)
    vocab = Vocab.from_dataset(ds)
    split = split_of(ds, cfg.seed, cfg.dataset)
    dm = SetDataModule(cfg.data, ds, SetEncoder(vocab, ds.tables, cfg.model.n_queries), seed=cfg.seed,
                       where=cfg.dataset)
    trained_on = TrainingData(dataset=str(cfg.dataset), fingerprint=dataset_identity(ds), seed=cfg.seed,
                              contexts=list(cfg.data.contexts), train_participants=split["train"],
                              val_participants=split["val"])  # predict refuses these participants
    module = SetTransformerModule(model=asdict(cfg.model), optim=asdict(cfg.optim), vocab=vocab.to_dict(),
                                  min_objects=int(ds.meta.get("min_objects", 3)), trained_on=asdict(trained_on))
    return module, dm


def _most_tokens(trials, target: int, k: int) -> int:
    """The most context tokens an episode of `trials` with this target and k context arrangements can have."""
    sizes = sorted((len(a.placements) for j, a in enumerate(trials) if j != target), reverse=True)
    return sum(sizes[:k])


def dry_run(cfg: SetTransformerTrainConfig, ds: Dataset | None = None, log=print) -> None:
    """`degusta train --dry-run` for kind set_transformer: parameters, tokens per example, objects per target
    against model.n_queries, steps per epoch and a memory estimate; trains and writes nothing (the model is small:
    built for real on the CPU with random weights)."""
    from degusta_learn.dryrun import dry_run_trainer_lines, estimate_memory, print_dry_run, transformer_activations
    from degusta_learn.training import world_size

    ds = ds if ds is not None else load_dataset(cfg.dataset)
    module, dm = build(cfg, ds)  # refuses n_queries below the largest arrangement
    total = sum(p.numel() for p in module.parameters())
    items = dict.fromkeys(dm.train_set.items)  # unique (participant, target, k), in order
    tokens = [_most_tokens(dm.train_set.trials[p], t, k) for p, t, k in items]
    objects = [len(dm.train_set.trials[p][t].placements) for p, t, _ in items]
    T, B, m = 1 + max(tokens), cfg.data.batch_size, cfg.model
    acts = transformer_activations(B * T, m.d_model, m.d_ff, m.n_encoder_layers, 4)
    acts += transformer_activations(B * m.n_queries, m.d_model, m.d_ff, 2 * m.n_decoder_layers, 4)
    mem = estimate_memory(total, total, 4, 4, acts, world_size(cfg.trainer),
                          note=f"float32; activations for a batch of {B} x {T} tokens and {m.n_queries} queries")
    lines = [("model", f"set transformer (d_model {m.d_model}, {m.n_encoder_layers} + {m.n_decoder_layers} layers, "
                       f"{m.n_heads} heads, {m.n_queries} queries): {total:,} parameters, random initial weights"),
             ("tokens per example", f"at most {T} (target + the largest k context arrangements; mean of that bound "
                                    f"{1 + sum(tokens) / len(tokens):.1f} over {len(tokens)} unique training items)"),
             ("objects per target", f"max {max(objects)} / mean {sum(objects) / len(objects):.1f} of model.n_queries "
                                    f"{m.n_queries}")]
    lines += dry_run_trainer_lines(cfg.trainer, monitor_keys(cfg.data.val_contexts), len(dm.train_set), B)
    lines.append(("predicted memory", mem.describe()))
    print_dry_run("dry run of kind set_transformer: nothing trained or written", lines, log)


def train(cfg: SetTransformerTrainConfig, ds: Dataset | None = None) -> Path:
    """TrainerSpec.run of kind `set_transformer`: train and return the run folder (seeded before the model is built)."""
    from degusta_learn.training import torch_threads

    monitors = monitor_keys(cfg.data.val_contexts)
    with torch_threads(cfg.num_threads), training_run(cfg.trainer, monitors):
        module, dm = build(cfg, ds)
        return fit(module, dm, cfg.trainer, full_config=cfg, monitors=monitors)
