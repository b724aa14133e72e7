"""`degusta train` with `kind: finetune`: fine-tune a VLM (LoRA, QLoRA or full) on lifted images.

Usage (CPU smoke run: builds a random-weight tiny Idefics3 on first use, a few minutes):
    degusta train --config configs/finetune_tiny_cpu.yaml
    degusta train --config configs/finetune_tiny_cpu.yaml --set trainer.max_steps=20 --set data.batch_size=2
GPU (SmolVLM-256M-Instruct from the local HF cache):
    degusta train --config configs/finetune_smolvlm_256m.yaml

Writes `checkpoints/<run>/`: config.yaml, last.ckpt / best.ckpt (LoRA: adapter tensors + optimizer
only), csv/ and tb/ logs, the last weights as `adapter/` (PeftModel.save_pretrained; LoRA) or `model/`
(full), the best ones (best `trainer.monitor`, default val/set_rmsd: what best.ckpt holds) as `best_adapter/`
or `best_model/` (what the predict configs load; finetune/export.py), optional `merged/` (last weights),
and `degusta_finetune.json` (vlm/record.py: how prompts were built and what the model was trained on; the hf
backend re-applies the one and checks predictions against the other).
"""

from __future__ import annotations

import random
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.methods import TrainerSpec


def build_examples(cfg: FinetuneConfig, ds, grid):
    """(train LiftedExamples, val LiftedExamples) from the dataset's seeded participant split."""
    from degusta_learn.finetune.data import LiftedExamples
    from degusta_learn.scene import make_episodes

    opts = cfg.data.prompt_options()
    train = [e for k in cfg.data.contexts for e in make_episodes(ds, k, "train", cfg.seed)]
    if cfg.data.max_train_episodes is not None and len(train) > cfg.data.max_train_episodes:
        train = random.Random(cfg.seed).sample(train, cfg.data.max_train_episodes)
    val = make_episodes(ds, cfg.data.val_context, "val", cfg.seed) if cfg.data.val_episodes else []
    if len(val) > cfg.data.val_episodes:
        val = random.Random(cfg.seed + 1).sample(val, cfg.data.val_episodes)
    # training contexts drawn afresh each epoch, seeded by the training seed (the split stays the split seed's)
    resample = cfg.trainer.seed if cfg.data.resample_contexts else None
    return (LiftedExamples(ds, train, cfg.method, grid, cfg.data.render_size, opts, resample_seed=resample),
            LiftedExamples(ds, val, cfg.method, grid, cfg.data.render_size, opts))  # validation: fixed


def train_sampler(cfg: FinetuneConfig, train, collator):
    """`(num_replicas, rank) -> TrainSampler` for `FinetuneData`: seeded by `trainer.seed` (two training seeds
    on one participant split differ in order, contexts and initial adapters), length-grouped by each
    example's token count (`count_tokens`, epoch 0's contexts: a resampled context changes only its
    placement-order lines, a few tokens) when `data.group_by_length`."""
    from degusta_learn.finetune.data import TrainSampler

    lengths = [c["total"] for c in count_tokens(train, collator)] if cfg.data.group_by_length else None
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


def set_budget(cfg: FinetuneConfig, processor, model_config) -> None:
    """Set the processor's image budget, then check it against the grid and `data.max_length` against the
    model's context (one-line errors naming the key)."""
    from degusta_learn.vlm.inputs import check_grid_resolution, set_image_budget
    from degusta_learn.prompting import answer_kind

    set_image_budget(processor, model_config, cfg.model.image_size)
    if answer_kind(cfg.method) == "grid":
        check_grid_resolution(processor, model_config, cfg.data.grid, key="model.image_size")
    context = getattr(model_config.get_text_config(), "max_position_embeddings", None)
    if context and cfg.data.max_length > context:
        raise DegustaError(f"data.max_length: {cfg.data.max_length} exceeds the model's context of {context} "
                           "tokens; lower it (and the image budget: model.image_size, data.compose, data.include)")


def check_budget(examples, collator) -> None:
    """Collate the longest-looking training example now, so a budget error comes before training: the most
    context arrangements and objects, with (when contexts are redrawn each epoch) the heaviest context any
    epoch could draw for it."""
    if len(examples) == 0:
        raise DegustaError("data.contexts: no training episodes (empty train split?)")
    ds = examples.ds
    heaviest = [examples.heaviest(i) for i in range(len(examples))]
    size = [(len(ep.context), sum(len(ds.arrangement(ep.participant, t).placements) for t in (*ep.context, ep.target)))
            for ep in heaviest]
    i = max(range(len(heaviest)), key=size.__getitem__)
    collator([examples.example(i, heaviest[i])])


def write_meta(out: Path, cfg: FinetuneConfig, processor, chosen_on_val: bool = True) -> None:
    """Write the run's `FinetuneRecord` (`degusta_finetune.json`, vlm/record.py) into `out`: how the prompts
    were built, and what the model was trained on (dataset fingerprint, split seed, train and validation
    participants), which the hf backend checks before predicting. `chosen_on_val`: whether validation chose the
    weights in `out` (a best folder, the run folder) or not (the last weights); early stopping makes it true."""
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset, participants_in
    from degusta_learn.scene.dataset import dataset_identity
    from degusta_learn.vlm.record import FinetuneRecord, TrainingData, write_record

    ds = load_dataset(cfg.dataset)
    trained_on = TrainingData(
        dataset=cfg.dataset, fingerprint=dataset_identity(ds), seed=cfg.seed, contexts=list(cfg.data.contexts),
        train_participants=participants_in(ds, "train", cfg.seed),
        val_participants=participants_in(ds, "val", cfg.seed) if cfg.data.val_episodes else [],  # as build_examples
        chosen_on_val=chosen_on_val or cfg.trainer.early_stopping_patience is not None)
    write_record(out, FinetuneRecord(
        base_model=cfg.model.name, method=cfg.method, mode=cfg.lora.mode,
        grid=Grid(cfg.data.grid.rows, cfg.data.grid.cols),
        prompt=cfg.data.prompt_options(),
        image_size=cfg.model.image_size, render_size=cfg.data.render_size,
        processor_size=dict(getattr(processor.image_processor, "size", {}) or {}), trained_on=trained_on))


def run(cfg: FinetuneConfig) -> Path:
    """Train per `cfg` (resuming `<run>/last.ckpt` if present); returns the run folder."""
    from degusta_learn.finetune import lora
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.export import save_last, sync_best
    from degusta_learn.finetune.tower_cache import cache_frozen_tower
    from degusta_learn.vlm.generate import chat_format
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
            write_meta(lora.merge_and_save(model, processor, run_dir / "merged"), cfg, processor, chosen_on_val=False)
        write_meta(run_dir, cfg, processor)
        sync_best(module, run_dir)  # best_adapter/ or best_model/ = best.ckpt (loads it: keep this last)
        return run_dir


def ensure_tiny_model(cfg: FinetuneConfig, wait_s: float = 600.0) -> None:
    """Build the tiny model at `model.name` if missing; under a launcher that starts every rank at once
    (torchrun, srun) only rank 0 builds it and the others wait for its marker file."""
    import time

    from degusta_learn.vlm.tiny import TINY_VERSION, ensure_tiny
    from degusta_learn.trainer import global_rank

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


class _SizeOnlyRenderer:
    """Stands in for the lifted-image renderer when only token counts are needed: blank images of the
    renderer's exact size (every lifted image is `size` x `size`; the processor's token count depends only on
    that), so counting every training example takes seconds instead of drawing every scene."""

    def __init__(self, size: int):
        self.size = size

    def _blank(self, *args, **kwargs):
        from PIL import Image

        return Image.new("RGB", (self.size, self.size), "white")

    gomo = gomo_sheet = uma = gma = table = _blank


def count_tokens(examples, collator, limit: int | None = None, batch: int = 16) -> list[dict]:
    """`Collator.token_counts` of every example (or the first `limit`): prompts built as in training, the
    lifted images blank at their size."""
    import copy

    n = len(examples) if limit is None else min(limit, len(examples))
    if n == 0:
        return []
    counting = copy.copy(examples)
    counting._renderer = _SizeOnlyRenderer(examples.render_size)
    out: list[dict] = []
    for start in range(0, n, batch):
        out += collator.token_counts([counting[i] for i in range(start, min(start + batch, n))])
    return out


def token_summary(counts: list[dict], max_length: int, what: str) -> str:
    """"max M / mean m of data.max_length L (p% used) over N <what>; image, text, answer max / mean"."""
    def mm(key: str) -> str:
        values = [c[key] for c in counts]
        return f"{max(values)} / {sum(values) / len(values):.1f}"

    top = max(c["total"] for c in counts)
    return (f"max {top} / mean {sum(c['total'] for c in counts) / len(counts):.1f} tokens of data.max_length "
            f"{max_length} ({top / max_length:.0%} used) over {len(counts)} {what} (max / mean: image {mm('image')}, "
            f"other prompt {mm('text')}, answer {mm('answer')})")


def refuse_over_budget(examples, counts: list[dict], collator) -> None:
    """The collator's own one-line `data.max_length` error for the longest example over the budget."""
    if not counts:
        return
    worst = max(range(len(counts)), key=lambda i: counts[i]["total"])
    if counts[worst]["total"] > collator.max_length:
        raise collator.budget_error(examples[worst], counts[worst])


def meta_model(source: str, key: str = "model.name"):
    """(model built from its config on the meta device: shapes only, no memory, no weights read; its config)."""
    import torch
    from transformers import AutoConfig, AutoModelForImageTextToText

    try:
        config = AutoConfig.from_pretrained(source, local_files_only=True)
        with torch.device("meta"):
            model = AutoModelForImageTextToText.from_config(config)
    except Exception as e:  # noqa: BLE001 - a foreign or broken config.json: one line
        first = (str(e).strip().splitlines() or [""])[0]
        raise DegustaError(f"{key}: cannot build {source!r} from its config: {type(e).__name__}: {first}"[:400]) from None
    return model, config


def vlm_memory(cfg_model, lora_cfg, trainer_cfg, config, total: int, trainable: int, batch_size: int,
               counts: list[dict], on_gpu: bool):
    """The dry run's memory estimate of a VLM fine-tune (see `dryrun.estimate_memory` for the model)."""
    from degusta_learn.dryrun import (CPU_ACTIVATION_FACTOR, RUNTIME_CPU_BYTES, RUNTIME_GPU_BYTES, estimate_memory,
                                      transformer_activations)
    from degusta_learn.trainer import effective_precision, world_size

    dtype = cfg_model.dtype if cfg_model.dtype != "auto" else ("bfloat16" if on_gpu and lora_cfg.mode != "full"
                                                               else "float32")  # full: fp32 master weights
    param_bytes = {"float32": 4, "bfloat16": 2, "float16": 2}[dtype]
    note = f"{dtype} weights"
    if lora_cfg.mode == "qlora":
        param_bytes, note = 0.55, "4-bit NF4 base (~0.55 bytes per weight with its scales)"
    trainable_bytes = 4 if lora_cfg.mode != "full" else param_bytes  # peft keeps adapter weights in fp32
    precision = effective_precision(trainer_cfg)  # bf16-mixed on a CPU without native bf16 runs as 32-true
    act_bytes = 2 if (param_bytes < 4 or "16" in precision) else 4
    T = max(c["total"] for c in counts)
    text = config.get_text_config()
    hidden = getattr(text, "hidden_size", 0)
    inter = getattr(text, "intermediate_size", 4 * hidden)
    layers = getattr(text, "num_hidden_layers", 0)
    heads = getattr(text, "num_attention_heads", 1) or 1
    kv_width = (getattr(text, "num_key_value_heads", None) or heads) * (getattr(text, "head_dim", None) or hidden // heads)
    acts = transformer_activations(batch_size * T, hidden, inter, layers, act_bytes,
                                   checkpointing=cfg_model.gradient_checkpointing,
                                   lora=lora_cfg.mode in ("lora", "qlora"), kv_width=kv_width)
    answer = max(c["answer"] for c in counts)
    vocab = getattr(text, "vocab_size", 0)
    acts += batch_size * answer * vocab * 4 * 2  # fp32 logits of the supervised positions + their softmax grad
    # the connector comes after the tower: adapting it keeps none of the tower's activations for the backward pass
    vision_trains = lora_cfg.vision_targets or (lora_cfg.mode == "full" and not lora_cfg.freeze_vision)
    vc = getattr(config, "vision_config", None)
    if vision_trains and vc is not None and getattr(vc, "hidden_size", None) and getattr(vc, "num_hidden_layers", None):
        merge = getattr(config, "scale_factor", None) or getattr(vc, "spatial_merge_size", None) or 1
        patches = batch_size * max(c["image"] for c in counts) * merge**2
        acts += transformer_activations(patches, vc.hidden_size, getattr(vc, "intermediate_size", 4 * vc.hidden_size),
                                        vc.num_hidden_layers, act_bytes, cfg_model.gradient_checkpointing)
        note += "; the vision tower trains: its activations are counted"
    elif vision_trains:
        note += "; the vision tower trains, but its activations are not modelled (no transformer config): add them"
    else:
        note += "; frozen vision tower: no activations kept for it"
    note += (f"; activations for a batch of {batch_size} x {T} tokens"
             f"{', gradient checkpointing' if cfg_model.gradient_checkpointing else ''}")
    if not on_gpu:
        acts *= CPU_ACTIVATION_FACTOR
        note += f"; activations x{CPU_ACTIVATION_FACTOR} on the CPU (backward transients, heap fragmentation)"
        if cfg_model.gradient_checkpointing:  # measured: benchmarks/RESULTS.md, "glibc and gradient checkpointing"
            note += ("; with gradient checkpointing glibc keeps the recomputed layers' freed memory: the RSS was "
                     "24-45% above this on the replicas, and within 3% of it with MALLOC_MMAP_THRESHOLD_=1048576")
    runtime = RUNTIME_GPU_BYTES if on_gpu else RUNTIME_CPU_BYTES
    note += "; runtime: CUDA context and kernels" if on_gpu else "; runtime: the CPU process itself"
    return estimate_memory(total, trainable, param_bytes, trainable_bytes, acts, world_size(trainer_cfg), note,
                           runtime_bytes=runtime)


def dry_run(cfg: FinetuneConfig, log=print) -> None:
    """`degusta train --dry-run` for kind finetune: sizes, token budget, steps and memory; loads no weights,
    trains nothing, writes nothing (an unbuilt tiny model is built in a temporary folder, then removed)."""
    import contextlib
    import dataclasses
    import tempfile
    import warnings

    import torch

    from degusta_learn.finetune import lora
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor
    from degusta_learn.finetune.module import monitor_keys
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.dryrun import dry_run_trainer_lines, print_dry_run
    from degusta_learn.trainer import trains_on_gpu

    ds = load_dataset(cfg.dataset)
    grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
    notes = []
    with contextlib.ExitStack() as stack:
        source = cfg.model.name
        marker = Path(source) / "degusta_tiny.json"
        if cfg.model.build_tiny and not marker.is_file():
            from degusta_learn.vlm.tiny import ensure_tiny

            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="degusta-dry-run-"))
            source = str(ensure_tiny(Path(tmp) / "tiny", cfg.model.build_tiny))
            notes.append(f"{cfg.model.name} is not built yet: its tiny {cfg.model.build_tiny} was built in a temporary "
                         "folder to read its config and processor (the run builds it in place)")
        processor = load_processor(source, "model.name")
        model, config = meta_model(source)
    set_budget(cfg, processor, config)
    fmt = ChatFormat(processor, getattr(model, "generation_config", None))
    total = sum(p.numel() for p in model.parameters())
    counting_lora = dataclasses.replace(cfg.lora, mode="lora") if cfg.lora.mode == "qlora" else cfg.lora
    with torch.device("meta"), warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # peft asks a deprecated transformers property
        model = lora.apply_lora(model, counting_lora)
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    total_after = sum(p.numel() for p in model.parameters())
    collator = Collator(processor, fmt, cfg.data.max_length, getattr(config, "image_token_id", None))
    train, val = build_examples(cfg, ds, grid)
    if len(train) == 0:
        raise DegustaError("data.contexts: no training episodes (empty train split?)")
    counts, val_counts = count_tokens(train, collator), count_tokens(val, collator)
    refuse_over_budget(train, counts, collator)
    refuse_over_budget(val, val_counts, collator)
    t = cfg.trainer
    on_gpu = trains_on_gpu(t)
    what = {"lora": f"LoRA r={cfg.lora.r} adapters", "qlora": f"QLoRA r={cfg.lora.r} adapters on a 4-bit base",
            "full": "full fine-tuning" + (" (vision tower frozen)" if cfg.lora.freeze_vision else "")}[cfg.lora.mode]
    lines = [("model", f"{cfg.model.name} ({config.model_type}): {total:,} parameters, built on the meta device "
                       "(no weights loaded)"),
             ("trainable", f"{trainable:,} parameters ({trainable / max(total_after, 1):.2%} of {total_after:,}), "
                           f"{what}"),
             ("tokens per example", token_summary(counts, cfg.data.max_length, "training examples")
              + (f"; validation: max {max(c['total'] for c in val_counts)} over {len(val_counts)}" if val_counts else ""))]
    lines += dry_run_trainer_lines(t, monitor_keys(cfg), len(train), cfg.data.batch_size)
    mem = vlm_memory(cfg.model, cfg.lora, t, config, total_after, trainable, cfg.data.batch_size, counts, on_gpu)
    lines.append(("predicted memory", mem.describe()))
    lines += [("note", n) for n in notes]
    print_dry_run(f"dry run of kind finetune ({cfg.method}): nothing loaded, trained or written", lines, log)


TRAINER = TrainerSpec(FinetuneConfig, run, "fine-tune a VLM (LoRA / QLoRA / full) on lifted images of a "
                      "prompting method; validation generates and scores answers", dry_run=dry_run)
