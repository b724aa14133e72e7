"""The LightningModule and DataModule of VLM fine-tuning.

`FinetuneModule` trains with `lm_loss` (answer tokens only) and validates by GENERATING answers for
held-out (val) participants: each answer is parsed, aggregated and scored like any method's
prediction, and val/parse_rate, val/rmsd, val/set_rmsd, val/object_accuracy, val/count_error (plus
val/loss) are logged. val/set_rmsd charges every unmatched object, so it is the one to select on. Under DDP
each rank generates for its share of the val episodes; the per-episode scores are gathered and each episode
counted once (`trainer.gather_unique_rows`), so the metrics equal a single-process validation's (val/loss is
the mean of the ranks' batch means); only rank 0 writes the adapter. With LoRA,
Lightning checkpoints hold only the trainable tensors (+ optimizer state), never the frozen base;
the adapter itself is written with `PeftModel.save_pretrained` to `<run>/adapter/` whenever a
checkpoint is saved (and at the end), loadable by plain peft.

Usage: built by `train.run` (see `degusta train --config configs/finetune_tiny_cpu.yaml`).
"""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from degusta_learn.finetune.loss import lm_loss, unwrap
from degusta_learn.trainer import gather_unique_rows


def monitor_keys(cfg) -> set[str]:
    """Every metric FinetuneModule logs under a FinetuneConfig `cfg` (what `trainer.monitor` may name)."""
    keys = {"train/loss", "train/answer_tokens"}
    if cfg.data.val_episodes > 0:  # no validation: only training losses exist
        keys |= {"val/loss", "val/parse_rate", "val/rmsd", "val/object_accuracy", "val/set_rmsd", "val/count_error"}
        if cfg.eval.report_unconstrained and cfg.eval.constrained:
            keys.add("val/parse_rate_unconstrained")
    return keys


class FinetuneModule(L.LightningModule):
    """Wraps a (peft) VLM; see the module docstring."""

    def __init__(self, model, processor, cfg, ds, grid, kind: str, run_dir: Path | None = None):
        super().__init__()
        self.model, self.processor, self.cfg = model, processor, cfg
        self.ds, self.grid, self.kind = ds, grid, kind
        self.run_dir = run_dir
        self.lora = getattr(getattr(cfg, "lora", None), "mode", "full") in ("lora", "qlora")
        self.strict_loading = not self.lora  # LoRA checkpoints hold the adapter tensors only
        self._val: list[dict] = []
        self._saved_step = -1

    # ------------------------------------------------------------------ training
    def on_train_epoch_start(self) -> None:
        freeze_batch_norms(self.model)  # Lightning has just put every module in train mode

    def training_step(self, batch, batch_idx):
        loss, n = lm_loss(self.model, batch)
        bs = batch["input_ids"].shape[0]
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        self.log("train/answer_tokens", float(n), batch_size=bs)
        return loss

    def configure_optimizers(self):
        o = self.cfg.optim
        params = [p for p in self.parameters() if p.requires_grad]  # the model and any auxiliary head
        opt = torch.optim.AdamW(params, lr=o.lr, weight_decay=o.weight_decay, betas=(0.9, 0.999))
        total = max(1, int(self.trainer.estimated_stepping_batches))
        warm = min(o.warmup_steps, total)

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / (warm + 1)
            if o.schedule == "constant":
                return 1.0
            progress = (step - warm) / max(1, total - warm)
            return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # ------------------------------------------------------------------ validation (generates)
    def validation_step(self, batch, batch_idx):
        inputs, examples = batch
        loss, n = lm_loss(self.model, inputs)
        self.log("val/loss", loss, batch_size=len(examples), sync_dist=True)
        e = self.cfg.eval
        for ex in examples:
            self._val.append({**self.score(ex, e.constrained), "index": self._val_index(ex)})
            if e.report_unconstrained and e.constrained:
                self._val[-1]["parsed_free"] = self.score(ex, False)["parsed"]

    def _val_index(self, ex) -> int:
        """The example's position in the validation set (ranks' shares are merged by it)."""
        if getattr(self, "_val_positions", None) is None:
            val = getattr(getattr(self.trainer, "datamodule", None), "val", None)
            self._val_positions = {getattr(x, "id", None): i for i, x in enumerate(getattr(val, "episodes", []))}
        return self._val_positions.get(ex.episode, len(self._val_positions))

    def score(self, ex, constrained: bool) -> dict:
        """Generate one greedy answer for `ex` and score it against the ground truth."""
        from degusta_learn.vlm.generate import generate_answers
        from degusta_learn.vlm.grammar import AnswerGrammar
        from degusta_learn.metrics import score_prediction
        from degusta_learn.prompting import AnswerParseError, parse_answer
        from degusta_learn.prompting.aggregate import aggregate

        grammar = AnswerGrammar(self.kind, self.ds.catalog, self.grid) if constrained else None
        text = generate_answers(self.model, self.processor, ex.prompt, n=1, temperature=0.0,
                                max_new_tokens=self.cfg.eval.max_new_tokens, constrained=constrained,
                                grammar=grammar)[0].text
        try:
            items = parse_answer(text, self.kind, self.ds.catalog, self.grid)
        except AnswerParseError:
            items = None
        placements, diag = aggregate([items], self.kind, self.grid)
        gt = self.ds.arrangement(ex.participant, ex.target)
        s = score_prediction(self.ds.catalog, gt, placements, diag["failed"])
        return {"parsed": items is not None, "rmsd": s.rmsd, "acc": s.object_accuracy, "set_rmsd": s.set_rmsd,
                "count_error": s.count_error, "text": text}

    def on_validation_epoch_end(self):
        if not self._val:
            return
        local, self._val = self._val, []
        free = "parsed_free" in local[0]
        table = torch.tensor([[r["index"], r["parsed"], r["rmsd"], r["acc"], r["set_rmsd"], r["count_error"],
                               r.get("parsed_free", 0.0)] for r in local], dtype=torch.float64)
        # every rank's examples, each once (DDP pads the ranks' shares with repeats): a single-process result
        rows = gather_unique_rows(self, table)
        n = len(rows)
        rmsd = rows[:, 2][~torch.isnan(rows[:, 2])]
        stats = {"val/parse_rate": float(rows[:, 1].sum()) / n,
                 "val/rmsd": float(rmsd.sum()) / len(rmsd) if len(rmsd) else float("nan"),
                 "val/object_accuracy": float(rows[:, 3].sum()) / n,
                 # set-aware: an unmatched object costs SET_PENALTY, so a one-object answer cannot look best
                 "val/set_rmsd": float(rows[:, 4].sum()) / n,
                 "val/count_error": float(rows[:, 5].sum()) / n}
        if free:
            stats["val/parse_rate_unconstrained"] = float(rows[:, 6].sum()) / n
        self.log_dict(stats, prog_bar=True, sync_dist=True)  # identical on every rank: the mean is the value
        self.last_val = {**stats, "example": local[0]["text"]}

    # ------------------------------------------------------------------ checkpoints: adapters apart
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.lora:
            keep = {f"model.{n}" for n, p in self.model.named_parameters() if p.requires_grad}
            checkpoint["state_dict"] = {k: v for k, v in checkpoint["state_dict"].items() if k in keep}
        if self.lora and self.run_dir is not None and self.global_step != self._saved_step \
                and self.trainer.is_global_zero:
            self.save_adapter(self.run_dir / "adapter")
            self._saved_step = self.global_step

    def save_adapter(self, out: Path) -> Path:
        from degusta_learn.finetune.lora import save_adapter

        return save_adapter(self.model, out)


class FinetuneData(L.LightningDataModule):
    """Train batches (collated) and val batches ((collated, examples) for loss + generation)."""

    def __init__(self, train, val, collator, batch_size: int, num_workers: int = 0, sampler=None, val_collator=None):
        super().__init__()
        self.train, self.val, self.collator = train, val, collator
        self.val_collator = val_collator or collator
        self.batch_size, self.num_workers, self.sampler = batch_size, num_workers, sampler

    def train_dataloader(self):
        return DataLoader(self.train, batch_size=self.batch_size, shuffle=self.sampler is None, sampler=self.sampler,
                          collate_fn=self.collator, num_workers=self.num_workers,
                          persistent_workers=self.num_workers > 0)

    def val_dataloader(self):
        if self.val is None or len(self.val) == 0:
            return []
        return DataLoader(self.val, batch_size=self.batch_size, shuffle=False, collate_fn=_ValCollate(self.val_collator),
                          num_workers=self.num_workers, persistent_workers=self.num_workers > 0)


class _ValCollate:
    def __init__(self, collator):
        self.collator = collator

    def __call__(self, examples):
        return self.collator(examples), examples


def freeze_batch_norms(model) -> None:
    """Keep frozen BatchNorm layers (e.g. a LoRA-adapted model's CNN vision tower) in eval mode.

    In train mode a BatchNorm normalises with the batch's statistics and overwrites its running ones even
    when its weights are frozen; the adapter would then be trained against a base that the saved model,
    loaded with the original running statistics, is not.
    """
    from torch import nn

    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm) and not any(p.requires_grad for p in m.parameters()):
            m.eval()


def enable_gradient_checkpointing(model) -> None:
    """Activation checkpointing with input grads enabled (else LoRA gets zero gradients)."""
    hf = unwrap(model)
    kwargs = {"use_reentrant": False}
    if hasattr(hf, "activation_checkpointing_enable"):  # transformers >= 5.x name
        hf.activation_checkpointing_enable(activation_checkpointing_kwargs=kwargs)
    else:
        hf.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)
    hf.enable_input_require_grads()
    hf.config.use_cache = False
