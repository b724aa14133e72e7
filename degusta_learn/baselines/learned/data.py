"""Training and validation data for the learned arrangement model (a LightningDataModule).

Training samples are drawn fresh each time from (participant, target trial, context length) triples of the
train participants, so one participant's 5 arrangements give many episodes. Augmentations that keep the
task intact:

- which trial is the target, which of the others form the context, and in which order (shuffled);
- table swap (`table_swap`, per arrangement): an arrangement is moved onto another table; its centre keeps
  its position relative to the surface bounds and the objects keep their physical offsets from it (pulled
  inside round surfaces), so contexts and targets meet table pairs the data never had;
- mirror (`mirror`, per episode): every arrangement of the episode is mirrored left-right about its table's
  centre line (rotations too), i.e. a consistent new participant with a mirrored style;
- object relabelling (`object_shuffle`, per episode): the catalog objects of each type are permuted, the
  same way in every arrangement of the episode — a participant with the same habits but other favourite
  objects. It stops the model from recognising a training participant by their objects and recalling
  their target, and teaches it to take the objects from the context instead.

Validation episodes are the val participants' episodes at each of `data.val_contexts` (exactly as
`make_episodes` builds them for `degusta predict`), unaugmented: `training.protocol.selection_episodes`, so the
validation that picks best.ckpt never sees a test participant.

Samples are made by `encode(context, target_table_id, target)` (the slot encoding, slots.py) and batched
by `slots.collate_slots`.

Usage:
    dm = ArrangementDataModule(DataConfig(), ds, encode, seed=0, where="data/naturalistic")
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import ClassVar

import lightning as L
import numpy as np
from torch.utils.data import DataLoader
from torch.utils.data import Dataset as TorchDataset

from degusta_learn.baselines.learned.features import onto_surface
from degusta_learn.baselines.learned.slots import collate_slots
from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError
from degusta_learn.scene import CONTEXT_LENGTHS, Arrangement, Dataset, Episode, Placement
from degusta_learn.scene.episodes import split_participants
from degusta_learn.training.protocol import selection_episodes


@dataclass
class DataConfig:
    """The `data:` section of a learned train config."""

    RENAMED: ClassVar[dict[str, str]] = {"dataset": "dataset", "split_seed": "seed",
                                         "context_lengths": "data.contexts", "val_context_lengths": "data.val_contexts"}
    """Old spellings (before one spelling per concept) -> the key that replaced them."""

    contexts: list[int] = field(default_factory=lambda: list(CONTEXT_LENGTHS))
    """Context lengths mixed during training (one model for all)."""
    val_contexts: list[int] = field(default_factory=lambda: list(CONTEXT_LENGTHS))
    """Context lengths of the validation episodes."""
    batch_size: int = bounded(32, 1, 65_536)
    """Episodes per batch (per device)."""
    repeats: int = bounded(4, 1, 10_000)
    """Samples per (participant, target, context length) in one epoch (each drawn afresh)."""
    num_workers: int = bounded(0, 0, 256)
    """DataLoader worker processes (0: load in the main process; encoding is cheap)."""
    table_swap: float = 0.2
    """Probability, per arrangement, of moving it onto another table (bounds-relative positions)."""
    mirror: float = 0.0
    """Probability, per episode, of mirroring every arrangement left-right."""
    object_shuffle: float = 0.5
    """Probability, per episode, of relabelling objects within each type (see the module docstring)."""

    def __post_init__(self):
        for key in ("contexts", "val_contexts"):
            bad = [k for k in getattr(self, key) if k not in CONTEXT_LENGTHS]
            if bad or not getattr(self, key):
                raise DegustaError(f"data.{key}: expected a non-empty list drawn from {list(CONTEXT_LENGTHS)}, "
                                   f"got {getattr(self, key)}")
        for key in ("table_swap", "mirror", "object_shuffle"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise DegustaError(f"data.{key}: expected a probability in [0, 1], got {getattr(self, key)}")
        if self.batch_size < 1 or self.repeats < 1:
            raise DegustaError("data.batch_size / data.repeats: expected >= 1")


def split_of(ds: Dataset, seed: int, where: str) -> dict[str, list[str]]:
    """Participant split, with a clear error when the dataset is too small for train/val/test."""
    n = len(ds.participants)
    if n < 3:
        raise DegustaError(f"{where}: {n} participant(s), too few for a train/val/test split (need at least 3)")
    return split_participants(ds.participants, seed)


def mirror(arr: Arrangement, ds: Dataset) -> Arrangement:
    x0, _, x1, _ = ds.tables[arr.table].bounds
    return replace(arr, placements=tuple(Placement(p.object, x0 + x1 - p.x, p.y, (360.0 - p.rotation) % 360.0)
                                          for p in arr.placements))


def swap_table(arr: Arrangement, ds: Dataset, new_table: int) -> Arrangement:
    """`arr` moved onto `new_table`: its centre keeps its place relative to the surface bounds, the objects
    keep their physical offsets from that centre (as people do: a place setting does not grow with the
    table), and any object off the new surface is pulled onto it."""
    a, b = ds.tables[arr.table].bounds, ds.tables[new_table].bounds
    xy = arr.positions
    centre = xy.mean(0)
    u = (centre - [a[0], a[1]]) / np.maximum([a[2] - a[0], a[3] - a[1]], 1e-6)
    xy = onto_surface(ds.tables[new_table], xy - centre + [b[0], b[1]] + u * [b[2] - b[0], b[3] - b[1]])
    return replace(arr, table=new_table, placements=tuple(
        Placement(p.object, float(x), float(y), p.rotation) for p, (x, y) in zip(arr.placements, xy)))


def relabel(arr: Arrangement, mapping: dict[int, int]) -> Arrangement:
    return replace(arr, placements=tuple(replace(p, object=mapping[p.object]) for p in arr.placements))


def shuffle_mapping(ds: Dataset, rng) -> dict[int, int]:
    """A random permutation of the catalog within each object type."""
    mapping = {}
    for t in ds.catalog.types:
        ids = [o.id for o in ds.catalog.of_type(t)]
        mapping.update(zip(ids, (ids[i] for i in rng.permutation(len(ids)))))
    return mapping


Encoder = Callable[[list[Arrangement], int, Arrangement], dict]  # (context, target table id, target) -> sample


class TrainEpisodes(TorchDataset):
    """Randomly drawn, augmented training episodes (numpy's global RNG, seeded by seed_everything)."""

    def __init__(self, ds: Dataset, participants: list[str], cfg: DataConfig, encode: Encoder):
        self.ds, self.cfg, self.encode = ds, cfg, encode
        by_p = ds.by_participant()
        self.trials = {p: by_p[p] for p in participants}
        self.items = [(p, t, k) for p in participants for t in range(len(by_p[p]))
                      for k in cfg.contexts if k < len(by_p[p])] * cfg.repeats
        self.table_ids = sorted(ds.tables)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        p, t, k = self.items[i]
        cfg, rng = self.cfg, np.random
        trials = self.trials[p]
        others = [a for j, a in enumerate(trials) if j != t]
        episode = [others[j] for j in rng.permutation(len(others))[:k]] + [trials[t]]  # context..., target
        if cfg.mirror and rng.random() < cfg.mirror:
            episode = [mirror(a, self.ds) for a in episode]
        if cfg.object_shuffle and rng.random() < cfg.object_shuffle:
            mapping = shuffle_mapping(self.ds, rng)
            episode = [relabel(a, mapping) for a in episode]
        if cfg.table_swap and len(self.table_ids) > 1:
            episode = [swap_table(a, self.ds, int(rng.choice([x for x in self.table_ids if x != a.table])))
                       if rng.random() < cfg.table_swap else a for a in episode]
        target = episode[-1]
        return self.encode(episode[:-1], target.table, target)


class ValEpisodes(TorchDataset):
    """The fixed validation episodes (with their targets, for the loss and the metrics)."""

    def __init__(self, ds: Dataset, episodes: list[Episode], encode: Encoder):
        self.ds, self.episodes, self.encode = ds, episodes, encode

    def __len__(self) -> int:
        return len(self.episodes)

    def __getitem__(self, i: int) -> dict:
        e = self.episodes[i]
        target = self.ds.arrangement(e.participant, e.target)
        ctx = [self.ds.arrangement(e.participant, c) for c in e.context]
        s = self.encode(ctx, target.table, target)
        s["index"] = i
        return s


class ArrangementDataModule(L.LightningDataModule):
    """Train / val loaders over a loaded dataset (the split is by participant, seeded by `seed`; `where`
    names the dataset in errors)."""

    def __init__(self, cfg: DataConfig, ds: Dataset, encode: Encoder, seed: int, where: str):
        super().__init__()
        self.cfg, self.ds = cfg, ds
        split = split_of(ds, seed, where)
        self.train_participants = split["train"]
        self.val_episodes = selection_episodes(ds, cfg.val_contexts, seed)  # what best.ckpt is chosen on
        self.train_set = TrainEpisodes(ds, self.train_participants, cfg, encode)
        self.val_set = ValEpisodes(ds, self.val_episodes, encode)
        if not len(self.train_set):
            raise DegustaError(f"{where}: no training episodes (train participants need more trials "
                               f"than the context lengths {cfg.contexts})")

    def train_dataloader(self) -> DataLoader:
        return DataLoader(self.train_set, batch_size=self.cfg.batch_size, shuffle=True, collate_fn=collate_slots,
                          num_workers=self.cfg.num_workers, persistent_workers=self.cfg.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=max(self.cfg.batch_size, 64), shuffle=False,
                          collate_fn=collate_slots, num_workers=self.cfg.num_workers,
                          persistent_workers=self.cfg.num_workers > 0)
