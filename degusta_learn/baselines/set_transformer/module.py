"""LightningModule of the set transformer: the matching loss, AdamW, validation by real decoding.

Training minimises `matching.set_loss`. Validation, on the val participants' episodes: the same loss (`val/loss`,
`val/loss_<term>`), and every episode decoded and scored with `degusta_learn.metrics.score_prediction`, as `degusta
evaluate` scores it: `val/set_rmsd` (the set-aware score that ranks methods and, by default, picks best.ckpt and
drives early stopping), `val/set_rmsd_unregistered`, `val/object_accuracy`, `val/rmsd` (Kabsch, over the episodes
with a match), `val/count_error`, and per context length `val/set_rmsd_k4`, `val/object_accuracy_k4`, ... Under DDP
the per-episode rows are gathered and each episode counted once (`training.gather_unique_rows`).

Hyperparameters are plain data (model and optimizer config, vocabulary, min_objects, the training split) plus
`kind: "set_transformer"` and `format`, so checkpoints load weights-only and another kind is recognised (predict.py).

Usage:
    module = SetTransformerModule(model=asdict(ModelConfig()), optim=asdict(SET_OPTIM), vocab=vocab.to_dict())
"""

from __future__ import annotations

import math

import lightning as L
import torch

from degusta_learn.baselines.learned.features import Vocab, onto_surface
from degusta_learn.baselines.set_transformer.matching import LOSS_TERMS, set_loss
from degusta_learn.baselines.set_transformer.model import ModelConfig, SetTransformer
from degusta_learn.metrics import score_prediction
from degusta_learn.optim import OptimConfig, adamw_optimizers
from degusta_learn.scene import Placement
from degusta_learn.training import gather_unique_rows

KIND = "set_transformer"
FORMAT = 2  # 1: rotation and step heads without the placed object's context tokens (refused)
SET_OPTIM = OptimConfig(lr=5e-4, weight_decay=0.01, warmup_steps=100)  # the set transformer's defaults
VAL_METRICS = ("set_rmsd", "set_rmsd_unregistered", "object_accuracy", "rmsd", "count_error")
PER_CONTEXT = ("set_rmsd", "object_accuracy")


def monitor_keys(val_contexts) -> set[str]:
    """Every metric SetTransformerModule logs (what `trainer.monitor` may name), for these validation lengths."""
    keys = {"loss", "train/loss", "val/loss"} | {f"train/{t}" for t in LOSS_TERMS} | {f"val/loss_{t}" for t in LOSS_TERMS}
    keys |= {f"val/{m}" for m in VAL_METRICS}
    return keys | {f"val/{m}_k{k}" for m in PER_CONTEXT for k in val_contexts}


class SetTransformerModule(L.LightningModule):
    def __init__(self, model: dict, optim: dict, vocab: dict, min_objects: int = 1, kind: str = KIND,
                 format: int = FORMAT, trained_on: dict | None = None):
        super().__init__()
        self.save_hyperparameters()
        self.model = SetTransformer(ModelConfig(**model), Vocab(**vocab))
        self.optim_cfg = OptimConfig(**optim)
        self.min_objects = min_objects
        self._val: list[torch.Tensor] = []

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        losses = set_loss(self.model(batch), batch, self.model.cfg)
        self.log_dict({f"train/{k}": v for k, v in losses.items()}, batch_size=len(batch["k"]))
        self.log("loss", losses["loss"], prog_bar=True, logger=False)
        return losses["loss"]

    # --- validation: loss + decoded predictions scored by degusta_learn.metrics -------------------------------
    def on_validation_epoch_start(self) -> None:
        self._val = []

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        losses = set_loss(self.model(batch), batch, self.model.cfg)
        self.log_dict({f"val/{'loss' if k == 'loss' else 'loss_' + k}": v for k, v in losses.items()},
                      batch_size=len(batch["k"]), sync_dist=True)
        dm = self.trainer.datamodule
        ids = [o["id"] for o in self.model.vocab.catalog]
        for i, rows, xy, rot in zip(batch["index"].tolist(), *self.model.decode(batch, self.min_objects)):
            e = dm.val_episodes[i]
            gt = dm.ds.arrangement(e.participant, e.target)
            xy = onto_surface(dm.ds.tables[gt.table], xy)
            s = score_prediction(dm.ds.catalog, gt, [Placement(ids[r], *p, float(a)) for r, p, a in zip(rows, xy, rot)])
            ok = not math.isnan(s.rmsd)
            self._val.append(torch.tensor([i, len(e.context), 1.0, s.set_rmsd, s.set_rmsd_unregistered,
                                           s.object_accuracy, s.rmsd if ok else 0.0, float(ok), s.count_error],
                                          dtype=torch.float64))

    def on_validation_epoch_end(self) -> None:
        ks = sorted(set(self.trainer.datamodule.cfg.val_contexts))
        rows = torch.stack(self._val) if self._val else torch.zeros(0, 9, dtype=torch.float64)
        rows = gather_unique_rows(self, rows)[:, 1:]  # every rank's episodes, each once
        # per context length and overall: sums of [n, set_rmsd, set_rmsd_unreg, accuracy, rmsd, n_rmsd, count_error]
        sums = torch.stack([rows[rows[:, 0] == k, 1:].sum(0) for k in ks] + [rows[:, 1:].sum(0)])
        for name, s in zip([f"_k{k}" for k in ks] + [""], sums):
            n, nr = max(float(s[0]), 1.0), float(s[5])
            metrics = {"set_rmsd": s[1] / n, "set_rmsd_unregistered": s[2] / n, "object_accuracy": s[3] / n,
                       "rmsd": s[4] / nr if nr else float("nan"), "count_error": s[6] / n}
            for key, value in metrics.items():
                if name and key not in PER_CONTEXT:
                    continue
                # gathered from every device: identical on every rank, so sync_dist's mean changes nothing
                self.log(f"val/{key}{name}", float(value), prog_bar=not name and key in ("set_rmsd", "object_accuracy"),
                         sync_dist=True)
        self._val = []

    # --- optimizer ---------------------------------------------------------------------------------------------
    def configure_optimizers(self):
        return adamw_optimizers(self.model, self.optim_cfg, self.trainer.estimated_stepping_batches)
