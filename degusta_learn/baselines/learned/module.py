"""LightningModule of the learned arrangement model: losses, optimizer, validation by real decoding.

Training minimizes `SlotModel.loss`. Validation does two things on the val participants' episodes: the
same loss (`val/loss`), and a full prediction of every episode
scored with `degusta_learn.metrics.score_prediction` exactly as `degusta evaluate` would — logged as
`val/set_rmsd` (the set-aware score that ranks methods: an unmatched object costs `SET_PENALTY`, so a short
answer cannot look best; what the shipped configs' `trainer.monitor` picks best.ckpt by), `val/rmsd`,
`val/object_accuracy`, `val/rmsd_unregistered`, `val/count_error`, `val/acceptable_0.05`, `val/acceptable_0.10`
and per context length (`val/set_rmsd_k4`, `val/rmsd_k4`, ...). Under DDP each rank scores its share of
the episodes and the per-episode rows are gathered, each episode counted once (`training.gather_unique_rows`),
so the metrics equal a single-process validation's; `val/loss` is the mean of the ranks' batch means.

Hyperparameters are saved as plain data (model config, optimizer config, vocabulary, the population rows
used at context 0 as [table id, rows] pairs) plus `kind: "learned"` and `format`, so checkpoints load
with `torch.load(..., weights_only=True)` and a checkpoint of another model kind or an older format is
recognized (see predict.py).

Usage:
    module = LearnedModule(model=asdict(ModelConfig()), optim=asdict(LEARNED_OPTIM), vocab=vocab.to_dict(),
                           population=population_pairs(population_rows(ds)))
"""

from __future__ import annotations

import math

import lightning as L
import torch

from degusta_learn.baselines.learned.features import Vocab, onto_surface
from degusta_learn.baselines.learned.slot_model import ModelConfig, SlotModel
from degusta_learn.metrics import score_prediction
from degusta_learn.optim import OptimConfig, adamw_optimizers
from degusta_learn.scene import Placement
from degusta_learn.training import gather_unique_rows

KIND = "learned"
LEARNED_OPTIM = OptimConfig(lr=1e-3, weight_decay=0.01, warmup_steps=100)  # the learned model's defaults
FORMAT = 3  # 1: the autoregressive token model; 2: rotation and step heads without the slot's own (refused)


def population_pairs(population: dict) -> list:
    """{table id: rows} -> [[table id, rows], ...] (plain lists, safe for weights-only checkpoints)."""
    return [[int(t), rows] for t, rows in sorted(population.items())]


LOSS_TERMS = ("set", "object", "position", "rotation", "step")  # SlotModel.loss terms besides "loss"
VAL_METRICS = ("set_rmsd", "object_accuracy", "rmsd", "rmsd_unregistered", "count_error", "acceptable_0.05",
               "acceptable_0.10")
PER_CONTEXT = ("set_rmsd", "object_accuracy", "rmsd")  # also logged per validation context length (val/rmsd_k4)


def monitor_keys(val_contexts) -> set[str]:
    """Every metric LearnedModule logs (what `trainer.monitor` may name), for these validation lengths."""
    keys = {"loss", "train/loss", "val/loss"} | {f"train/{t}" for t in LOSS_TERMS} | {f"val/loss_{t}" for t in LOSS_TERMS}
    keys |= {f"val/{m}" for m in VAL_METRICS}
    keys |= {f"val/{m}_k{k}" for m in PER_CONTEXT for k in val_contexts}
    return keys


class LearnedModule(L.LightningModule):
    def __init__(self, model: dict, optim: dict, vocab: dict, population: list, min_objects: int = 1,
                 kind: str = KIND, format: int = FORMAT, trained_on: dict | None = None):
        super().__init__()
        self.save_hyperparameters()
        self.model = SlotModel(ModelConfig(**model), Vocab(**vocab))
        self.optim_cfg = OptimConfig(**optim)
        self.min_objects = min_objects
        self._val: list[torch.Tensor] = []

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        losses = self.model.loss(batch, self.model(batch))
        self.log_dict({f"train/{k}": v for k, v in losses.items()}, prog_bar=False, batch_size=len(batch["tgt_table"]))
        self.log("loss", losses["loss"], prog_bar=True, logger=False)
        return losses["loss"]

    # --- validation: loss + decoded predictions scored by degusta_learn.metrics ---------------------------
    def on_validation_epoch_start(self) -> None:
        self._val = []

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        losses = self.model.loss(batch, self.model(batch))
        self.log_dict({f"val/{'loss' if k == 'loss' else 'loss_' + k}": v for k, v in losses.items()},
                      batch_size=len(batch["tgt_table"]), sync_dist=True)
        dm = self.trainer.datamodule
        objs, xys, rots = self.model.decode(batch, self.min_objects)
        ids = [o["id"] for o in self.model.vocab.catalog]
        for i, rows, xy, rot in zip(batch["index"].tolist(), objs, xys, rots):
            e = dm.val_episodes[i]
            gt = dm.ds.arrangement(e.participant, e.target)
            xy = onto_surface(dm.ds.tables[gt.table], xy)
            s = score_prediction(dm.ds.catalog, gt, [Placement(ids[r], *p, float(a)) for r, p, a in zip(rows, xy, rot)])
            ok, set_ok = not math.isnan(s.rmsd), not math.isnan(s.set_rmsd)  # set_rmsd: nan only for an empty truth
            self._val.append(torch.tensor([i, len(e.context), 1.0, s.object_accuracy, s.rmsd if ok else 0.0, float(ok),
                                           s.rmsd_unregistered if ok else 0.0, s.count_error,
                                           ok and s.rmsd <= 0.05, ok and s.rmsd <= 0.10,
                                           s.set_rmsd if set_ok else 0.0, float(set_ok)], dtype=torch.float64))

    def on_validation_epoch_end(self) -> None:
        ks = sorted(set(self.trainer.datamodule.cfg.val_contexts))
        rows = torch.stack(self._val) if self._val else torch.zeros(0, 12, dtype=torch.float64)
        rows = gather_unique_rows(self, rows)[:, 1:]  # every rank's episodes, each once (DDP pads the shares)
        # per context length: sums of [n, acc, rmsd, n_rmsd, rmsd_unreg, count_error, acc@.05, acc@.10, set_rmsd,
        # n_set_rmsd]
        sums = torch.stack([rows[rows[:, 0] == k, 1:].sum(0) for k in ks] + [rows[:, 1:].sum(0)])
        for name, s in zip([f"_k{k}" for k in ks] + [""], sums):
            n, nr, ns = max(float(s[0]), 1.0), float(s[3]), float(s[9])
            metrics = {"set_rmsd": s[8] / ns if ns else float("nan"), "object_accuracy": s[1] / n,
                       "rmsd": s[2] / nr if nr else float("nan"),
                       "rmsd_unregistered": s[4] / nr if nr else float("nan"), "count_error": s[5] / n,
                       "acceptable_0.05": s[6] / n, "acceptable_0.10": s[7] / n}
            for key, value in metrics.items():
                if name and key not in PER_CONTEXT:
                    continue
                # gathered from every device: identical on every rank, so sync_dist's mean changes nothing
                self.log(f"val/{key}{name}", float(value), prog_bar=not name and key in ("set_rmsd", "object_accuracy"),
                         sync_dist=True)
        self._val = []

    # --- optimizer ---------------------------------------------------------------------------------------
    def configure_optimizers(self):
        return adamw_optimizers(self.model, self.optim_cfg, self.trainer.estimated_stepping_batches)
