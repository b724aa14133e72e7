"""Training and validation data of the set transformer (a LightningDataModule).

The episodes and their augmentations are the learned slot model's (`baselines.learned.data`: the same `data:`
section, `DataConfig`): training samples drawn afresh from (participant, target trial, context length) of the
train participants, with table swap, mirror and object relabelling; validation is the val participants' episodes
at each of `data.val_contexts` (`training.protocol.selection_episodes`), unaugmented. Only the encoding differs:
one token per context placement (encoding.py), batched by `collate_sets`.

Usage:
    dm = SetDataModule(DataConfig(), ds, SetEncoder(vocab, ds.tables, 20), seed=0, where="data/naturalistic")
"""

from __future__ import annotations

import lightning as L
from torch.utils.data import DataLoader

from degusta_learn.baselines.learned.data import DataConfig, Encoder, TrainEpisodes, ValEpisodes, split_of
from degusta_learn.baselines.set_transformer.encoding import collate_sets
from degusta_learn.errors import DegustaError
from degusta_learn.scene import Dataset
from degusta_learn.training.protocol import selection_episodes


class SetDataModule(L.LightningDataModule):
    """Train / val loaders over a loaded dataset (split by participant, seeded by `seed`; `where` names the
    dataset in errors)."""

    def __init__(self, cfg: DataConfig, ds: Dataset, encode: Encoder, seed: int, where: str):
        super().__init__()
        self.cfg, self.ds = cfg, ds
        self.train_participants = split_of(ds, seed, where)["train"]
        self.val_episodes = selection_episodes(ds, cfg.val_contexts, seed)  # what best.ckpt is chosen on
        self.train_set = TrainEpisodes(ds, self.train_participants, cfg, encode)
        self.val_set = ValEpisodes(ds, self.val_episodes, encode)
        if not len(self.train_set):
            raise DegustaError(f"{where}: no training episodes (train participants need more trials "
                               f"than the context lengths {cfg.contexts})")

    def _loader(self, dataset, batch_size: int, shuffle: bool) -> DataLoader:
        return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, collate_fn=collate_sets,
                          num_workers=self.cfg.num_workers, persistent_workers=self.cfg.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, self.cfg.batch_size, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, max(self.cfg.batch_size, 64), shuffle=False)
