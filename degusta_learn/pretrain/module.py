"""The LightningModule of perception pretraining: `FinetuneModule`'s training, a perception validation.

Training is `FinetuneModule`'s (answer-only next-token loss on every weight, its optimizer and schedule) plus,
with `data.dense_weight > 0`, the dense auxiliary loss on the image tokens (`dense.py`), whose head is trained
with the model and left out of the export, and, with `data.teacher_steps > 0`, the oracle teacher
(`dense.OracleTeacher`): for the first steps the decoder mostly sees perfect image tokens (sums of the
embeddings of what covers each cell) instead of the vision tower's, with a probability falling from 1 to 0
over `teacher_steps`, with `data.readout_weight > 0` the tied readout (`dense.TiedReadout`: the image tokens
read through the decoder's output layer should name their cell's content; logged as train/readout and, at
validation, val/token_type / val/token_id / val/token_direction), and, with `data.retrieval_weight > 0`, the
attention supervision (`retrieval.py`): one decoder head is told where the object an answer names is among the
image tokens. With `data.tower_steps > 0` a vision stage comes first: only the tower, its projector and the
dense head train, on the dense loss alone, and the decoder's warmup and cosine schedule (and the teacher's
hold) start after it; with `data.freeze_tower` the tower then stays as the stage left it. Validation always
sees the tower's tokens and logs the dense head's readouts of them (val/tower_type, val/tower_id: the id among
its type's objects, val/tower_direction); the vision stage's validations answer no questions (val/perception
is NaN there, which best.ckpt ranks last).
Validation generates an answer to each held-out perception question — constrained to the answer grammar
for `list` / `describe` questions, a few free tokens for `gomo` ones — scores it with `score.py` and
logs val/loss, val/object_f1, val/cells_exact, val/cell_iou, val/direction, val/mark_id,
val/parse_rate and their headline mean val/perception.
"""

from __future__ import annotations

import math

from degusta_learn.finetune.loss import lm_loss, unwrap
from degusta_learn.finetune.module import FinetuneModule, freeze_batch_norms
from degusta_learn.pretrain.retrieval import KEYS as RETRIEVAL_KEYS

GOMO_TOKENS = 8  # an id is at most three digits (one token with the domain tokenizer) and the stop token


def monitor_keys(cfg) -> set[str]:
    """Every metric PerceptionModule logs under a PretrainConfig `cfg` (what `trainer.monitor` may name)."""
    keys = {"train/loss"} | ({"train/dense"} if cfg.data.dense_weight > 0 else set())
    keys |= {"train/teacher_p"} if cfg.data.teacher_steps > 0 else set()
    keys |= {"train/retrieval"} if cfg.data.retrieval_weight > 0 else set()
    keys |= {"train/readout"} if cfg.data.readout_weight > 0 else set()
    if cfg.data.val_examples > 0 and cfg.data.dense_weight > 0:
        keys |= {"val/tower_type", "val/tower_id", "val/tower_direction"}
    if cfg.data.val_examples > 0 and cfg.data.readout_weight > 0:
        keys |= {"val/token_type", "val/token_id", "val/token_direction"}
    if cfg.data.val_examples > 0:
        keys |= {f"val/{k}" for k in ("loss", "object_f1", "cells_exact", "cells_exact_all", "cell_iou", "direction",
                                      "mark_id", "parse_rate", "perception")}
    return keys


class PerceptionModule(FinetuneModule):
    """A full-weight VLM trained on perception questions (see the module docstring)."""

    def __init__(self, model, processor, cfg, catalog, grid, n_labels: int = 0, side: int = 8):
        super().__init__(model, processor, cfg, None, grid, "grid")
        self.catalog = catalog
        self._grammar = None
        self.dense_weight = cfg.data.dense_weight
        self.dense = None
        self._tokens = self._features = None
        self._recomputing = False
        self.teacher = None
        from degusta_learn.pretrain.dense import DenseHead, OracleTeacher, projector_of

        if self.dense_weight > 0:
            hidden = model.config.get_text_config().hidden_size
            self.dense = DenseHead(hidden, n_labels, side)
        self.tower_steps = cfg.data.tower_steps
        if cfg.data.teacher_steps > 0:
            self.teacher = OracleTeacher(model.get_input_embeddings(), cfg.data.teacher_steps,
                                         cfg.data.teacher_hold + self.tower_steps)
        self.readout = None
        if cfg.data.readout_weight > 0:
            from degusta_learn.pretrain.dense import OracleTokens, TiedReadout

            oracle = OracleTokens(catalog, processor.tokenizer, grid, "readout_weight")
            self.readout = TiedReadout(model.get_output_embeddings(), oracle, catalog)
        if self.dense is not None or self.teacher is not None or self.readout is not None:
            projector_of(model).register_forward_hook(self._capture)
        self.retrieval = None
        if cfg.data.retrieval_weight > 0:
            from degusta_learn.pretrain.retrieval import RetrievalLoss

            self.retrieval = RetrievalLoss(model, cfg.data.retrieval_layer, cfg.data.retrieval_head)

    def _capture(self, module, inputs, output):
        if self._recomputing:  # `_readout_tokens`'s own projector call: its tokens, never the teacher's
            return None
        self._tokens = output  # (n_images, tokens, hidden): the vision tower's image tokens
        self._features = inputs[0] if inputs else None  # the tower's output, the projector's input
        if self.teacher is not None and self.training and not self.vision_stage:
            return self.teacher.replace(output, self.global_step)  # what the decoder sees instead
        return None

    @property
    def vision_stage(self) -> bool:
        """True during the first `data.tower_steps` steps (only the tower trains, on the dense loss)."""
        return self.global_step < self.tower_steps

    def configure_optimizers(self):
        """`FinetuneModule`'s AdamW and schedule; with a vision stage, the decoder's parameters (everything but
        the tower, its projector and the dense head) get their own warmup and cosine, starting after it."""
        if self.tower_steps <= 0:
            return super().configure_optimizers()
        import torch

        from degusta_learn.optim import warmup_factor
        from degusta_learn.pretrain.dense import projector_of

        o, hf = self.cfg.optim, unwrap(self.model)
        seen = {id(p) for m in (hf.model.vision_tower, projector_of(hf), self.dense) for p in m.parameters()}
        trained = [p for p in self.parameters() if p.requires_grad]
        vision = [p for p in trained if id(p) in seen]
        decoder = [p for p in trained if id(p) not in seen]
        opt = torch.optim.AdamW([{"params": vision, "name": "vision"}, {"params": decoder, "name": "decoder"}],
                                lr=o.lr, weight_decay=o.weight_decay, betas=(0.9, o.beta2))
        total, start = int(self.trainer.estimated_stepping_batches), self.tower_steps
        lambdas = [lambda step: warmup_factor(o, step, total),
                   lambda step: 0.0 if step < start else warmup_factor(o, step - start, total - start)]
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambdas)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_train_batch_start(self, batch, batch_idx) -> None:
        """With `data.freeze_tower`, freeze the tower once the vision stage is over (again after a resume)."""
        if not (self.cfg.data.freeze_tower and self.tower_steps > 0) or self.vision_stage:
            return
        tower = unwrap(self.model).model.vision_tower
        if any(p.requires_grad for p in tower.parameters()):
            tower.requires_grad_(False)
        freeze_batch_norms(tower)  # BatchNorms keep the stage's statistics (Lightning re-enters train mode)

    def _readout_tokens(self):
        """The image tokens the tied readout acts on. After a vision stage it trains the projector only, on the
        tower's detached output: the tower has learned to see, and a loss on its tokens would write over that."""
        if self.tower_steps <= 0 or self._features is None:
            return self._tokens
        from degusta_learn.pretrain.dense import projector_of

        self._recomputing = True  # else the forward hook would swap in the teacher's oracle sums
        try:
            return projector_of(unwrap(self.model))(self._features.detach())
        finally:
            self._recomputing = False

    def _vision_step(self, batch, targets, keep):
        """One step of the vision stage: the tower's tokens of the batch's images and the dense loss alone."""
        self._tokens = self._features = None
        unwrap(self.model).model.get_image_features(pixel_values=batch["pixel_values"])
        dense = self.dense.loss(self._tokens, targets, keep)
        bs = batch["input_ids"].shape[0]
        self.log("train/dense", dense, batch_size=bs)  # as training_step logs it: Lightning refuses a key logged
        return dense                                    # with other arguments within one epoch (the stage's end)

    def training_step(self, batch, batch_idx):
        batch = dict(batch)
        targets, keep = batch.pop("dense_targets", None), batch.pop("dense_keep", None)
        if self.vision_stage:
            return self._vision_step(batch, targets, keep)
        oracle_ids = batch.pop("oracle_ids", None)
        retrieval = [batch.pop(k, None) for k in RETRIEVAL_KEYS]
        if self.teacher is not None:
            self.teacher.ids, self.teacher.keep = oracle_ids, keep
        self._tokens = self._features = None
        loss, n = lm_loss(self.model, batch)
        bs = batch["input_ids"].shape[0]
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        if self.teacher is not None:
            self.log("train/teacher_p", self.teacher.probability(self.global_step), batch_size=bs)
        if self.readout is not None:
            read = self.readout.loss(self._readout_tokens(), oracle_ids, keep)  # the projector's tokens it trains
            if read is not None:
                self.log("train/readout", read, batch_size=bs)
                loss = loss + self.cfg.data.readout_weight * read
        if self.retrieval is not None and retrieval[0] is not None:
            sup = self.retrieval.loss(*retrieval)
            if sup is not None:
                self.log("train/retrieval", sup, batch_size=bs)
                loss = loss + self.cfg.data.retrieval_weight * sup
        if self.dense is None or keep is None:
            return loss
        dense = self.dense.loss(self._tokens, targets, keep)
        self.log("train/dense", dense, batch_size=bs)
        return loss + self.dense_weight * dense

    def grammar(self):
        from degusta_learn.task.grammar import AnswerGrammar

        if self._grammar is None:
            self._grammar = AnswerGrammar("grid", self.catalog, self.grid)
        return self._grammar

    def answer(self, ex) -> str:
        """The greedy answer to one perception example (constrained unless it asks for a mark id)."""
        from degusta_learn.vlm.generate import generate_answers

        located = ex.meta["task"] != "gomo"
        return generate_answers(self.model, self.processor, ex.prompt, n=1, temperature=0.0,
                                max_new_tokens=self.cfg.decoding.max_new_tokens if located else GOMO_TOKENS,
                                constrained=located and self.cfg.decoding.constrained,
                                grammar=self.grammar() if located else None,
                                on_repeat=self.cfg.decoding.on_repeat)[0].text

    def validation_step(self, batch, batch_idx):
        from degusta_learn.pretrain.score import score_answer

        inputs, examples = batch
        self._tokens = None
        loss, _ = lm_loss(self.model, inputs)
        self.log("val/loss", loss, batch_size=len(examples), sync_dist=True)
        if self.dense is not None and self._tokens is not None:
            read = self.dense.readouts(self._tokens, examples, self.catalog)
            for key in ("type", "id", "direction"):
                if read["cells"]:
                    self.log(f"val/tower_{key}", read[key], batch_size=read["cells"], sync_dist=True)
        if self.readout is not None and self._tokens is not None:
            read = self.readout.readouts(self._tokens, examples, self.catalog)
            for key in ("type", "id", "direction"):
                if read["cells"]:
                    self.log(f"val/token_{key}", read[key], batch_size=read["cells"], sync_dist=True)
        if self.vision_stage:  # the decoder has not trained: no answers to score
            self.log("val/perception", float("nan"), batch_size=len(examples), sync_dist=True)
            return
        for ex in examples:
            self._val.append(score_answer(ex, self.answer(ex), self.catalog, self.grid))

    def on_validation_epoch_end(self):
        from degusta_learn.pretrain.score import summarize

        if not self._val:
            return
        rows, self._val = self._val, []
        stats = {f"val/{k}": float(v) for k, v in summarize(rows).items()
                 if not k.startswith("n_") and not math.isnan(v)}
        self.log_dict(stats, prog_bar=False, sync_dist=True)
        self.last_val = stats
