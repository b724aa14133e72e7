"""The LightningModule and DataModule of VLM fine-tuning.

`FinetuneModule` trains with `lm_loss` (answer tokens only) and validates by GENERATING answers for
held-out (val) participants: each answer is parsed, aggregated and scored like any method's prediction.
The answers of `eval.batch_size` episodes come from one left-padded `generate` call
(`vlm.generate.generate_batch`), decoded as the `decoding:` section says (the keys `degusta predict` reads); with
`decoding.n > 1` each episode gets n answers sampled at `decoding.temperature`, aggregated by predict's own
`task.aggregate.combine` (`decoding.aggregation`), and the aggregate is scored. `decoding.max_new_tokens: auto` is
predict's hf budget: the dataset's longest answer in the model's tokenizer + 10% + the grammar's closing reserve. The
first `eval.log_images` episodes are drawn as ground truth vs prediction (rank 0: <run>/val_images/step_<N>/ and
TensorBoard image summaries). Logged per validation (besides val/loss):

- val/set_rmsd: the set-aware score (metrics/set_score.py; every unmatched object costs SET_PENALTY, a
  failed answer scores it): what `trainer.monitor` selects on (a one-object answer cannot look best);
- val/rmsd (the paper's Kabsch RMSD over matched pairs; 0 for a one-object answer), val/object_accuracy
  (the paper's: per ground-truth object), val/count_error, val/few_matched (share of answers matching
  <= 2 objects of >= 3: the "degenerate" test of `compare`);
- per field, over matched pairs (`field_scores.py`): val/id_accuracy, and for grid methods val/cell_iou and
  val/direction_accuracy;
- val/parse_rate (constrained when decoding.constrained) and, with decoding.report_unconstrained,
  val/parse_rate_unconstrained (every answer decoded a second time without the grammar).

Under DDP each rank generates for its share of the val episodes; the per-episode scores are gathered and
each episode counted once (`training.gather_unique_rows`), so the metrics equal a single-process
validation's (val/loss is the mean of the ranks' batch means). With LoRA, Lightning checkpoints hold only
the trainable tensors (+ optimizer state), never the frozen base. Exports (`export.py`, rank 0 only): the
last weights to `<run>/adapter/` (full: `model/`) whenever a checkpoint is saved, and the best weights to
`<run>/best_adapter/` (full: `best_model/`) whenever a validation improves `trainer.monitor`.

Usage: built by `train.run` (see `degusta train --config configs/finetune_tiny_cpu.yaml`).
"""

from __future__ import annotations

from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from degusta_learn.finetune.loss import lm_loss, unwrap
from degusta_learn.optim import lr_schedule
from degusta_learn.training import gather_unique_rows

VAL_COLUMNS = ("index", "parsed", "parsed_free", "rmsd", "acc", "set_rmsd", "count_error", "n_gt", "n_matched",
               "failed", "pairs", "id_correct", "cell_iou", "direction_correct")
"""One row per validation episode (gathered over ranks as a float tensor)."""
PROGRESS_BAR = ("val/set_rmsd", "val/parse_rate", "val/object_accuracy")


def monitor_keys(cfg) -> set[str]:
    """Every metric FinetuneModule logs under a FinetuneConfig `cfg` (what `trainer.monitor` may name)."""
    from degusta_learn.task.answers import answer_kind
    keys = {"train/loss", "train/answer_tokens"}
    if cfg.data.val_episodes > 0:  # no validation: only training losses exist
        keys |= {"val/loss", "val/parse_rate", "val/rmsd", "val/object_accuracy", "val/set_rmsd", "val/count_error",
                 "val/few_matched", "val/id_accuracy"}
        if answer_kind(cfg.method) == "grid":
            keys |= {"val/cell_iou", "val/direction_accuracy"}
        if cfg.decoding.report_unconstrained and cfg.decoding.constrained:
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
        self._pending: list = []  # validation examples waiting for a full eval.batch_size generate call
        self._saved_step = -1
        self._best_seen = None  # (path, score) of the best checkpoint last exported (or found at the start)

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
        opt = torch.optim.AdamW(param_groups(self, o), lr=o.lr, weight_decay=o.weight_decay, betas=(0.9, o.beta2))
        return {"optimizer": opt, "lr_scheduler": lr_schedule(opt, o, self.trainer.estimated_stepping_batches)}

    # ------------------------------------------------------------------ validation (generates)
    def validation_step(self, batch, batch_idx):
        inputs, examples = batch
        loss, n = lm_loss(self.model, inputs)
        self.log("val/loss", loss, batch_size=len(examples), sync_dist=True)
        self._pending += list(examples)
        size = self.cfg.eval.batch_size or self.cfg.data.batch_size
        while len(self._pending) >= size:
            self._answer(self._pending[:size])
            self._pending = self._pending[size:]

    def _answer(self, examples) -> None:
        """Generate and score the validation answers of `examples` (one `generate` call a decoding mode)."""
        e = self.cfg.decoding
        indices = [self._val_index(ex) for ex in examples]
        rows = self.score_batch(examples, e.constrained, indices)
        free = self.score_batch(examples, False, indices) if e.report_unconstrained and e.constrained else None
        for i, (ex, row) in enumerate(zip(examples, rows)):
            row.update(index=indices[i], parsed_free=free[i]["parsed"] if free else 0.0,
                       episode=(ex.episode, ex.participant, ex.target))
            self._val.append(row)

    def _val_index(self, ex) -> int:
        """The example's position in the validation set (ranks' shares are merged by it)."""
        if getattr(self, "_val_positions", None) is None:
            val = getattr(getattr(self.trainer, "datamodule", None), "val", None)
            self._val_positions = {getattr(x, "id", None): i for i, x in enumerate(getattr(val, "episodes", []))}
        return self._val_positions.get(ex.episode, len(self._val_positions))

    def score(self, ex, constrained: bool) -> dict:
        """Generate the answer(s) to `ex` and score them (`score_batch` of one example)."""
        return self.score_batch([ex], constrained)[0]

    def score_batch(self, examples, constrained: bool, indices: list[int] | None = None) -> list[dict]:
        """Generate `decoding.n` answers per example (one `generate` call, left-padded), aggregate each example's
        answers as predict does and score the aggregate: one VAL_COLUMNS row (+ `text`, the first answer, and
        `placements`) per example. `indices` (positions in the validation set) seed the samples."""
        from degusta_learn.task.aggregate import ANCHORED
        from degusta_learn.task.grammar import AnswerGrammar
        from degusta_learn.vlm.generate import generate_batch

        e = self.cfg.decoding
        indices = list(range(len(examples))) if indices is None else indices
        grammar = AnswerGrammar(self.kind, self.ds.catalog, self.grid) if constrained else None
        prompts, seeds = [ex.prompt for ex in examples], [self.cfg.seed + i for i in indices]
        budget = self.max_new_tokens()
        answers = generate_batch(self.model, self.processor, prompts, n=e.n, temperature=e.sampling_temperature,
                                 max_new_tokens=budget, constrained=constrained, grammar=grammar,
                                 seeds=seeds, on_repeat=e.on_repeat)
        greedy = [None] * len(examples)
        if e.aggregation in ANCHORED:  # + the greedy answer, as predict asks for it
            greedy = [c[0].text for c in generate_batch(self.model, self.processor, prompts, n=1, temperature=0.0,
                                                        max_new_tokens=budget, constrained=constrained,
                                                        grammar=grammar, seeds=seeds, on_repeat=e.on_repeat)]
        return [self.score_answers(ex, [c.text for c in completions], anchor)
                for ex, completions, anchor in zip(examples, answers, greedy)]

    def max_new_tokens(self) -> int:
        """`decoding.max_new_tokens`, or for auto the hf backend's budget (`vlm.generate.answer_token_budget`: the
        dataset's longest answer in this tokenizer + 10%, + the grammar's closing reserve when constrained), once."""
        e = self.cfg.decoding
        if e.max_new_tokens != "auto":
            return e.max_new_tokens
        if getattr(self, "_budget", None) is None:
            from degusta_learn.task.grammar import AnswerGrammar
            from degusta_learn.vlm.generate import answer_token_budget

            grammar = AnswerGrammar(self.kind, self.ds.catalog, self.grid) if e.constrained else None
            self._budget = answer_token_budget(self.processor.tokenizer, self.ds, self.kind, self.grid,
                                               grammar=grammar)["max_new_tokens"]
        return self._budget

    def score_answers(self, ex, texts: list[str], greedy: str | None = None) -> dict:
        """Score the answers `texts` to `ex`: parsed, aggregated (`prompting.aggregate.combine`, predict's own
        function, by `decoding.aggregation`) and the aggregate scored against the ground truth. `parsed` is the share
        of answers that parse. The per-field counts compare the answer's items (n = 1) or, for n > 1, the aggregated
        plan written as an answer (`answer_items`: the cells its placements cover)."""
        from degusta_learn.finetune.field_scores import field_counts
        from degusta_learn.metrics import score_prediction
        from degusta_learn.task.aggregate import combine
        from degusta_learn.task.answer_format import answer_items
        from degusta_learn.task.answers import AnswerParseError, parse_answer

        parsed = []
        for text in texts + ([greedy] if greedy is not None else []):
            try:
                parsed.append(parse_answer(text, self.kind, self.ds.catalog, self.grid))
            except AnswerParseError:
                parsed.append(None)
        anchor = parsed.pop() if greedy is not None else None
        placements, diag = combine(parsed, self.kind, self.grid, self.cfg.decoding.aggregation, anchor=anchor)
        gt = self.ds.arrangement(ex.participant, ex.target)
        s = score_prediction(self.ds.catalog, gt, placements, diag["failed"])
        items = parsed[0] if len(parsed) == 1 else (
            answer_items(placements, self.ds.catalog, self.kind, self.grid) if placements else None)
        f = field_counts(items, placements, gt, self.ds.catalog, self.grid, self.kind)
        return {"parsed": sum(p is not None for p in parsed) / len(parsed), "rmsd": s.rmsd,
                "acc": s.object_accuracy, "set_rmsd": s.set_rmsd, "count_error": s.count_error, "n_gt": s.n_gt,
                "n_matched": s.n_matched, "failed": diag["failed"], "pairs": f.pairs, "id_correct": f.id_correct,
                "cell_iou": f.cell_iou, "direction_correct": f.direction_correct, "text": texts[0],
                "placements": placements}

    def on_validation_epoch_end(self):
        pending, self._pending = self._pending, []
        if pending:
            self._answer(pending)
        if not self._val:
            return
        local, self._val = self._val, []
        table = torch.tensor([[float(r[c]) for c in VAL_COLUMNS] for r in local], dtype=torch.float64)
        # every rank's examples, each once (DDP pads the ranks' shares with repeats): a single-process result
        stats = validation_stats(gather_unique_rows(self, table), self.kind,
                                 self.cfg.decoding.report_unconstrained and self.cfg.decoding.constrained)
        bar = {k: v for k, v in stats.items() if k in PROGRESS_BAR}
        # identical on every rank: the sync_dist mean is the value
        self.log_dict(bar, prog_bar=True, sync_dist=True)
        self.log_dict({k: v for k, v in stats.items() if k not in bar}, sync_dist=True)
        self.last_val = {**stats, "example": local[0]["text"]}
        if self.trainer.is_global_zero and not self.trainer.sanity_checking:
            self._log_images(local)

    def _log_images(self, rows: list[dict]) -> list[Path]:
        """Ground truth vs prediction of the first `eval.log_images` validation episodes (this rank's share; rank
        0 calls it): PNGs in <run>/val_images/step_<N>/ and, with a TensorBoard logger, its image summaries."""
        from lightning.pytorch.loggers import TensorBoardLogger

        from degusta_learn.evaluate.qualitative import render_side_by_side
        from degusta_learn.render.lifting import Renderer

        count = self.cfg.eval.log_images
        if count <= 0 or self.run_dir is None:
            return []
        if getattr(self, "_image_renderer", None) is None:
            self._image_renderer = Renderer.for_dataset(self.ds, size=self.cfg.data.render_size)
        folder = Path(self.run_dir) / "val_images" / f"step_{self.global_step}"
        tensorboard = next((lg for lg in self.loggers if isinstance(lg, TensorBoardLogger)), None)
        paths = []
        for row in sorted(rows, key=lambda r: r["index"])[:count]:
            episode, participant, target = row["episode"]
            score = "failed" if row["failed"] else (f"set {row['set_rmsd']:.3f}, RMSD {row['rmsd']:.3f}, "
                                                    f"acc {row['acc']:.2f}")
            label = f"step {self.global_step}" + (f", n = {self.cfg.decoding.n}" if self.cfg.decoding.n > 1 else "")
            path = render_side_by_side(self.ds, self._image_renderer, participant, target,
                                       {f"prediction ({label})": (row["placements"], score)},
                                       folder / f"{int(row['index']):03d}_{_file_safe(episode)}.png")
            paths.append(path)
            if tensorboard is not None:
                import numpy as np
                from PIL import Image

                with Image.open(path) as im:
                    tensorboard.experiment.add_image(f"val_images/{int(row['index']):03d}",
                                                     np.asarray(im.convert("RGB")), self.global_step,
                                                     dataformats="HWC")
        return paths

    def on_train_start(self) -> None:
        from degusta_learn.finetune.export import best_score

        self._best_seen = best_score(self.trainer)  # a resumed run: the restored best is already exported

    def on_validation_end(self) -> None:
        """Export the weights best.ckpt now holds when this validation improved the monitor.

        Runs after every callback's on_validation_end, so after ModelCheckpoint has saved best.ckpt (it
        saves after validation whenever a monitor is set: `trainer.build_trainer`).
        """
        from degusta_learn.finetune.export import best_score, save_best

        if self.run_dir is None or self.trainer.sanity_checking:
            return
        best = best_score(self.trainer)
        if best is None or best == self._best_seen:
            return
        self._best_seen = best
        if self.trainer.is_global_zero:
            save_best(self, self.run_dir, best[1])

    # ------------------------------------------------------------------ checkpoints: adapters apart
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.lora:
            keep = {f"model.{n}" for n, p in self.model.named_parameters() if p.requires_grad}
            checkpoint["state_dict"] = {k: v for k, v in checkpoint["state_dict"].items() if k in keep}
        if self.lora and self.run_dir is not None and self.global_step != self._saved_step \
                and self.trainer.is_global_zero:
            from degusta_learn.finetune.export import save_last

            save_last(self, self.run_dir)
            self._saved_step = self.global_step

    def save_adapter(self, out: Path) -> Path:
        from degusta_learn.finetune.lora import save_adapter

        return save_adapter(self.model, out)


def param_groups(module, optim) -> list[dict]:
    """AdamW parameter groups of `module`'s trained parameters: the vision tower's at `optim.vision_lr`, the
    connector's at `optim.connector_lr` (either null: `optim.lr`), everything else (the language model, any
    auxiliary head) at `optim.lr`. The parts are found as `lora.py` finds them (the connector first: Qwen2-VL's
    merger sits inside its vision tower). Empty groups are left out; each group carries its `name`."""
    from degusta_learn.finetune.lora import CONNECTOR_PREFIXES, VISION_PREFIXES, find_part

    hf = unwrap(module.model)
    vision, connector = find_part(hf, VISION_PREFIXES), find_part(hf, CONNECTOR_PREFIXES)
    part = {}
    for name, p in hf.named_parameters():
        if connector and name.startswith(connector + "."):
            part[id(p)] = "connector"
        elif vision and name.startswith(vision + "."):
            part[id(p)] = "vision"
    lrs = {"language": optim.lr, "vision": getattr(optim, "vision_lr", None) or optim.lr,
           "connector": getattr(optim, "connector_lr", None) or optim.lr}
    groups = {k: [] for k in lrs}
    for p in module.parameters():
        if p.requires_grad:
            groups[part.get(id(p), "language")].append(p)
    return [{"params": ps, "lr": lrs[k], "name": k} for k, ps in groups.items() if ps]


def validation_stats(rows, kind: str, unconstrained: bool) -> dict[str, float]:
    """The logged validation metrics from the gathered VAL_COLUMNS rows (one per episode; see the docstring)."""
    from degusta_learn.metrics import few_matched_fraction

    col = {c: rows[:, i] for i, c in enumerate(VAL_COLUMNS)}
    nan = float("nan")

    def mean(values) -> float:
        return float(values.sum()) / len(values) if len(values) else nan

    pairs = float(col["pairs"].sum())
    per_pair = lambda key: float(col[key].sum()) / pairs if pairs else nan  # noqa: E731 - pooled over all pairs
    few, _ = few_matched_fraction(col["n_gt"].long().tolist(), col["n_matched"].long().tolist(),
                                  col["failed"].bool().tolist())
    stats = {"val/parse_rate": mean(col["parsed"]),
             "val/rmsd": mean(col["rmsd"][~torch.isnan(col["rmsd"])]),
             "val/object_accuracy": mean(col["acc"]),
             # set-aware: an unmatched object costs SET_PENALTY, so a one-object answer cannot look best
             "val/set_rmsd": mean(col["set_rmsd"]),
             "val/count_error": mean(col["count_error"]),
             "val/few_matched": nan if few is None else few,
             "val/id_accuracy": per_pair("id_correct")}
    if kind == "grid":
        stats["val/cell_iou"] = per_pair("cell_iou")
        stats["val/direction_accuracy"] = per_pair("direction_correct")
    if unconstrained:
        stats["val/parse_rate_unconstrained"] = mean(col["parsed_free"])
    return stats


class FinetuneData(L.LightningDataModule):
    """Train batches (collated) and val batches ((collated, examples) for loss + generation)."""

    def __init__(self, train, val, collator, batch_size: int, num_workers: int = 0, sampler=None, val_collator=None,
                 make_sampler=None):
        super().__init__()
        self.train, self.val, self.collator = train, val, collator
        self.val_collator = val_collator or collator
        self.batch_size, self.num_workers, self.sampler = batch_size, num_workers, sampler
        self.make_sampler = make_sampler
        """`(num_replicas, rank) -> sampler` (e.g. `data.TrainSampler`), called once the ranks are known."""

    def train_dataloader(self):
        if self.make_sampler is not None:
            t = self.trainer
            self.sampler = self.make_sampler(t.world_size if t else 1, t.global_rank if t else 0)
        return DataLoader(self.train, batch_size=self.batch_size, shuffle=self.sampler is None, sampler=self.sampler,
                          collate_fn=self.collator, num_workers=self.num_workers,
                          persistent_workers=self.num_workers > 0)

    def val_dataloader(self):
        if self.val is None or len(self.val) == 0:
            return []
        return DataLoader(self.val, batch_size=self.batch_size, shuffle=False, collate_fn=_ValCollate(self.val_collator),
                          num_workers=self.num_workers, persistent_workers=self.num_workers > 0)


def _file_safe(name) -> str:
    """`name` with every character a file name should not hold replaced by `_`."""
    import re

    return re.sub(r"[^A-Za-z0-9._-]", "_", str(name))[:80]


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
    inputs_require_grads(hf)
    hf.config.use_cache = False


def inputs_require_grads(hf) -> None:
    """Make the output of the text input embeddings require grad, and a sub-model's (the vision tower's patch
    embedding) only when that sub-model has trainable weights.

    transformers' `enable_input_require_grads` (which enabling checkpointing calls too) hooks the input
    embeddings of EVERY sub-model: a frozen vision tower then builds an autograd graph and is back-propagated
    through for nothing. Measured on the Qwen2-VL-2B replica (7 images of 1,024 patches, fp32 on the CPU):
    the first LoRA step ran out of 24 GiB, where the memory model (a frozen tower keeps no activations)
    predicts 11.5 GiB. Those hooks are removed and replaced by these.
    """
    from transformers import PreTrainedModel

    def hook(module, inputs, output):
        output.requires_grad_(True)

    models = [m for m in hf.modules() if isinstance(m, PreTrainedModel)]
    for module in models:
        module.disable_input_require_grads()
    text = hf.get_input_embeddings()
    seen: set[int] = set()
    hooks = []
    for module in models:
        try:
            embeddings = module.get_input_embeddings()
        except (NotImplementedError, AttributeError):
            continue
        if embeddings is None or id(embeddings) in seen or not hasattr(embeddings, "register_forward_hook"):
            continue
        if embeddings is not text and not any(p.requires_grad for p in module.parameters()):
            continue  # a frozen sub-model (the vision tower without vision LoRA): no graph through it
        seen.add(id(embeddings))
        hooks.append(embeddings.register_forward_hook(hook))
    hf._require_grads_hooks = hooks  # so that transformers' disable_input_require_grads removes them
