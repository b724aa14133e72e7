"""`degusta train` with `kind: finetune`: fine-tune a VLM (LoRA, QLoRA or full) on lifted images.

Usage (CPU smoke run: builds a random-weight tiny Idefics3 on first use, a few minutes):
    degusta train --config configs/finetune_tiny_cpu.yaml
    degusta train --config configs/finetune_tiny_cpu.yaml --set trainer.max_steps=20 --set data.batch_size=2
GPU (SmolVLM-256M-Instruct from the local HF cache):
    degusta train --config configs/finetune_smolvlm_256m.yaml

Writes `checkpoints/<run>/`: config.yaml, last.ckpt / best.ckpt (LoRA: adapter tensors + optimizer
only), csv/ and tb/ logs, `adapter/` (PeftModel.save_pretrained; LoRA) or `model/` (full), optional
`merged/`, and `degusta_finetune.json` (how prompts were built: the hf backend re-applies it).
"""

from __future__ import annotations

import random
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.fileio import atomic_write_json
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.methods import TrainerSpec

META_FILE = "degusta_finetune.json"


def build_examples(cfg: FinetuneConfig, ds, grid):
    """(train LiftedExamples, val LiftedExamples) from the dataset's seeded participant split."""
    from degusta_learn.finetune.data import LiftedExamples, PromptOptions
    from degusta_learn.scene import make_episodes

    opts = PromptOptions(include=list(cfg.data.include), compose=list(cfg.data.compose))
    train = [e for k in cfg.data.contexts for e in make_episodes(ds, k, "train", cfg.seed)]
    if cfg.data.max_train_episodes is not None and len(train) > cfg.data.max_train_episodes:
        train = random.Random(cfg.seed).sample(train, cfg.data.max_train_episodes)
    val = make_episodes(ds, cfg.data.val_context, "val", cfg.seed) if cfg.data.val_episodes else []
    if len(val) > cfg.data.val_episodes:
        val = random.Random(cfg.seed + 1).sample(val, cfg.data.val_episodes)
    make = lambda eps: LiftedExamples(ds, eps, cfg.method, grid, cfg.data.render_size, opts)  # noqa: E731
    return make(train), make(val)


def prepare_model(cfg: FinetuneConfig):
    """(trainable model, processor) per cfg.model / cfg.lora, image budget set, context checked."""
    from degusta_learn.finetune import lora
    from degusta_learn.finetune.inputs import check_grid_resolution, set_image_budget
    from degusta_learn.finetune.model import load_vlm
    from degusta_learn.finetune.tiny import ensure_tiny
    from degusta_learn.prompting import answer_kind

    if cfg.model.build_tiny:
        ensure_tiny(cfg.model.name, cfg.model.build_tiny)
    quant, device = None, "cpu"  # Lightning moves the model to its device
    if cfg.lora.mode == "qlora":  # a 4-bit base is loaded straight onto the GPU (untested here: no GPU)
        lora.check_qlora()
        quant, device = lora.quantization_config(), "cuda"
    model, processor = load_vlm(cfg.model.name, device=device, dtype=cfg.model.dtype, key="model.name",
                                quantization_config=quant)
    set_image_budget(processor, model.config, cfg.model.image_size)
    if answer_kind(cfg.method) == "grid":
        check_grid_resolution(processor, model.config, cfg.data.grid, key="model.image_size")
    context = getattr(model.config.get_text_config(), "max_position_embeddings", None)
    if context and cfg.data.max_length > context:
        raise DegustaError(f"data.max_length: {cfg.data.max_length} exceeds the model's context of {context} "
                           "tokens; lower it (and the image budget: model.image_size, data.compose, data.include)")
    model.train()
    return lora.apply_lora(model, cfg.lora), processor


def check_budget(examples, collator) -> None:
    """Collate the longest-looking training example now, so a budget error comes before training."""
    if len(examples) == 0:
        raise DegustaError("data.contexts: no training episodes (empty train split?)")
    ds = examples.ds
    longest = max(range(len(examples)), key=lambda i: (len(examples.episodes[i].context), len(
        ds.arrangement(examples.episodes[i].participant, examples.episodes[i].target).placements)))
    collator([examples[longest]])


def write_meta(out: Path, cfg: FinetuneConfig, processor) -> None:
    ip = processor.image_processor
    atomic_write_json(out / META_FILE, {
        "base_model": cfg.model.name, "method": cfg.method, "mode": cfg.lora.mode,
        "grid": {"rows": cfg.data.grid.rows, "cols": cfg.data.grid.cols},
        "prompt": {"include": list(cfg.data.include), "compose": list(cfg.data.compose)},
        "image_size": cfg.model.image_size, "render_size": cfg.data.render_size,
        "processor_size": dict(getattr(ip, "size", {}) or {}),
    })


def run(cfg: FinetuneConfig) -> Path:
    """Train per `cfg` (resuming `<run>/last.ckpt` if present); returns the run folder."""
    from degusta_learn.finetune import lora
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.generate import chat_format
    from degusta_learn.finetune.module import FinetuneData, FinetuneModule, enable_gradient_checkpointing, monitor_keys
    from degusta_learn.prompting import answer_kind
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.trainer import fit, training_run

    with training_run(cfg.trainer, monitor_keys(cfg)):  # checks trainer values, seeds before the model exists
        ds = load_dataset(cfg.dataset)
        grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
        model, processor = prepare_model(cfg)
        if cfg.model.gradient_checkpointing:
            enable_gradient_checkpointing(model)
        fmt = chat_format(model, processor)
        collator = Collator(processor, fmt, cfg.data.max_length, getattr(model.config, "image_token_id", None))
        train, val = build_examples(cfg, ds, grid)
        check_budget(train, collator)
        per_epoch = -(-len(train) // cfg.data.batch_size)
        vci = cfg.trainer.val_check_interval
        if isinstance(vci, int) and not isinstance(vci, bool) and vci > per_epoch:  # Lightning refuses it even without val
            raise DegustaError(f"trainer.val_check_interval: {vci} batches is more than an epoch ({per_epoch} batches "
                               f"of {cfg.data.batch_size}); use at most {per_epoch} or a fraction like 1.0")
        run_dir = cfg.trainer.path
        module = FinetuneModule(model, processor, cfg, ds, grid, answer_kind(cfg.method), run_dir=run_dir)
        data = FinetuneData(train, val, collator, cfg.data.batch_size, cfg.data.num_workers)
        run_dir = fit(module, data, cfg.trainer, full_config=cfg, monitors=monitor_keys(cfg))
        if module.trainer is not None and not module.trainer.is_global_zero:
            return run_dir
        if module.lora:
            out = lora.save_adapter(model, run_dir / "adapter")
            if cfg.lora.merge:
                write_meta(lora.merge_and_save(model, processor, run_dir / "merged"), cfg, processor)
        else:
            out = run_dir / "model"
            model.save_pretrained(str(out))
            processor.save_pretrained(str(out))
        write_meta(out, cfg, processor)
        write_meta(run_dir, cfg, processor)
        return run_dir


TRAINER = TrainerSpec(FinetuneConfig, run, "fine-tune a VLM (LoRA / QLoRA / full) on lifted images of a "
                      "prompting method; validation generates and scores answers")
