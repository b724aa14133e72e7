"""`degusta train` with `kind: finetune`: fine-tune a VLM (LoRA, QLoRA or full) on lifted images.

Usage (CPU smoke run: builds a random-weight tiny Idefics3 on first use, a few minutes):
    degusta train --config configs/finetune_tiny_cpu.yaml
    degusta train --config configs/finetune_tiny_cpu.yaml --set trainer.max_steps=20 --set data.batch_size=2
GPU (SmolVLM-256M-Instruct from the local HF cache):
    degusta train --config configs/finetune_smolvlm_256m.yaml

Writes `runs/<run>/`: config.yaml, last.ckpt / best.ckpt (LoRA: adapter tensors + optimizer
only), csv/ and tb/ logs, the last weights as `adapter/` (PeftModel.save_pretrained; LoRA) or `model/`
(full), the best ones (best `trainer.monitor`, default val/set_rmsd: what best.ckpt holds) as `best_adapter/`
or `best_model/` (what the predict configs load; finetune/export.py), optional `merged/` (last weights),
and `degusta_finetune.json` (vlm/record.py: how prompts were built and what the model was trained on; the hf
backend re-applies the one and checks predictions against the other).
"""

from __future__ import annotations

from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.finetune.data import build_examples
from degusta_learn.finetune.dry_run import dry_run
from degusta_learn.finetune.export import write_meta
from degusta_learn.finetune.token_count import heaviest_draw, set_budget, token_budget
from degusta_learn.methods import TrainerSpec


def train_sampler(cfg: FinetuneConfig, train, collator):
    """`(num_replicas, rank) -> TrainSampler` for `FinetuneData`: seeded by `trainer.seed` (two training seeds
    on one participant split differ in order, contexts and initial adapters), length-grouped by each
    example's token count (`token_budget`, epoch 0's contexts: a resampled context changes only its
    placement-order lines, a few tokens) when `data.group_by_length`."""
    from degusta_learn.finetune.data import TrainSampler

    lengths = None
    if cfg.data.group_by_length:
        lengths = [c["total"] for c in token_budget(train, collator, seed=cfg.seed, heaviest=False).counts]
    return lambda replicas, rank: TrainSampler(train, cfg.trainer.seed, replicas, rank, lengths=lengths,
                                               batch_size=cfg.data.batch_size)


def prepare_model(cfg: FinetuneConfig):
    """(trainable model, processor) per cfg.model / cfg.lora, image budget set, context checked."""
    from degusta_learn.finetune import lora
    from degusta_learn.vlm.load import load_vlm

    if cfg.model.build_tiny:
        ensure_tiny_model(cfg)
    quant, device = None, "cpu"  # Lightning moves the model to its device
    if cfg.lora.mode == "qlora":  # a 4-bit base is loaded straight onto the GPU (untested here: no GPU)
        lora.check_qlora()
        quant, device = lora.quantization_config(), "cuda"
    model, processor = load_vlm(cfg.model.name, device=device, dtype=cfg.weights_dtype, key="model.name",
                                quantization_config=quant)
    set_budget(cfg, processor, model.config)
    model.train()
    return lora.apply_lora(model, cfg.lora), processor


def check_budget(examples, collator) -> None:
    """Collate the longest-looking training example now (`heaviest_draw`), so a budget error comes before
    training."""
    if len(examples) == 0:
        raise DegustaError("data.contexts: no training episodes (empty train split?)")
    i, ep = heaviest_draw(examples)
    collator([examples.example(i, ep)])


def run(cfg: FinetuneConfig) -> Path:
    """Train per `cfg` (resuming `<run>/last.ckpt` if present); returns the run folder."""
    from degusta_learn.finetune import lora
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.export import save_last, sync_best, validation_scores
    from degusta_learn.finetune.module import (
        FinetuneData,
        FinetuneModule,
        enable_gradient_checkpointing,
        monitor_keys,
    )
    from degusta_learn.finetune.tower_cache import cache_frozen_tower
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.task.answers import answer_kind
    from degusta_learn.training import fit, training_run
    from degusta_learn.vlm.generate import chat_format

    with training_run(cfg.trainer, monitor_keys(cfg)):  # checks trainer values, seeds before the model exists
        ds = load_dataset(cfg.dataset)
        grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
        model, processor = prepare_model(cfg)
        if cfg.model.gradient_checkpointing:
            enable_gradient_checkpointing(model)
        if cfg.model.cache_tower:
            cache_frozen_tower(model)
        fmt = chat_format(model, processor)
        collator = Collator(processor, fmt, cfg.data.max_length, getattr(model.config, "image_token_id", None),
                            list_end_weight=cfg.data.list_end_weight)
        train, val = build_examples(cfg, ds, grid)
        check_budget(train, collator)
        per_epoch = -(-len(train) // cfg.data.batch_size)
        vci = cfg.trainer.val_check_interval
        if isinstance(vci, int) and not isinstance(vci, bool) and vci > per_epoch:  # Lightning refuses it even without val
            raise DegustaError(f"trainer.val_check_interval: {vci} batches is more than an epoch ({per_epoch} batches "
                               f"of {cfg.data.batch_size}); use at most {per_epoch} or a fraction like 1.0")
        run_dir = cfg.trainer.path
        module = FinetuneModule(model, processor, cfg, ds, grid, answer_kind(cfg.method), run_dir=run_dir)
        data = FinetuneData(train, val, collator, cfg.data.batch_size, cfg.data.num_workers,
                            make_sampler=train_sampler(cfg, train, collator))
        run_dir = fit(module, data, cfg.trainer, full_config=cfg, monitors=monitor_keys(cfg))
        if module.trainer is not None and not module.trainer.is_global_zero:
            return run_dir
        save_last(module, run_dir)  # adapter/ (LoRA) or model/ (full): the last weights
        if module.lora and cfg.lora.merge:
            from degusta_learn.files.folders import write_folder
            from degusta_learn.finetune.card import write_finetune_files
            from degusta_learn.finetune.export import MODEL_FOLDER

            with write_folder(run_dir / "merged", MODEL_FOLDER) as merged:  # whole or not at all, as every export
                lora.merge_and_save(model, processor, merged)
                write_meta(merged, cfg, processor, chosen_on_val=False)
                write_finetune_files(merged, cfg, adapter=False, metrics=validation_scores(module, None))
        write_meta(run_dir, cfg, processor)
        sync_best(module, run_dir)  # best_adapter/ or best_model/ = best.ckpt (loads it: keep this last)
        return run_dir


def ensure_tiny_model(cfg: FinetuneConfig, wait_s: float = 600.0) -> None:
    """Build the tiny model at `model.name` if missing; under a launcher that starts every rank at once
    (torchrun, srun) only rank 0 builds it and the others wait for its marker file."""
    import time

    from degusta_learn.training import global_rank
    from degusta_learn.vlm.random_models.tiny import TINY_VERSION, ensure_tiny

    marker = Path(cfg.model.name) / "degusta_tiny.json"
    if global_rank() == 0:
        ensure_tiny(cfg.model.name, cfg.model.build_tiny)
        return
    deadline = time.monotonic() + wait_s
    while not (marker.is_file() and f'"version": {TINY_VERSION}' in marker.read_text()):
        if time.monotonic() > deadline:
            raise DegustaError(f"model.build_tiny: rank {global_rank()} waited {wait_s:.0f} s for rank 0 to build "
                               f"{cfg.model.name}; build it first (a single-process run) or check rank 0's error")
        time.sleep(0.5)


TRAINER = TrainerSpec(FinetuneConfig, run, "fine-tune a VLM (LoRA / QLoRA / full) on lifted images of a "
                      "prompting method; validation generates and scores answers", dry_run=dry_run)
