"""`degusta train --dry-run` for kind finetune: model size, trainable parameters, tokens per example, where the grid's
cells fall among the image tokens, steps and predicted memory, with no weights loaded and nothing written.

Usage:
    degusta train --config configs/finetune_smolvlm_256m.yaml --dry-run
"""

from __future__ import annotations

from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.finetune.token_count import (
    describe_budget,
    refuse_budget,
    set_budget,
    token_budget,
    token_summary,
)


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
    from degusta_learn.dryrun import (
        CPU_ACTIVATION_FACTOR,
        RUNTIME_CPU_BYTES,
        RUNTIME_GPU_BYTES,
        estimate_memory,
        transformer_activations,
    )
    from degusta_learn.training import effective_precision, world_size

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


def grid_alignment_line(cfg: FinetuneConfig, ds, grid, processor, model_config) -> str | None:
    """Where the grid cells of the GMA images fall among the image tokens (`vlm.inputs.check_grid_resolution`):
    one `GridAlignment.describe` per distinct GMA image size among the dataset's tables; None for a method
    without grid-marked images."""
    from degusta_learn.render.lifting import Renderer, method_liftings
    from degusta_learn.vlm.inputs import check_grid_resolution

    if method_liftings(cfg.method)[1] != "gma":
        return None
    if "all" in cfg.data.compose:
        return "not computed: data.compose [all] tiles the grid-marked images into one canvas"
    renderer = Renderer.for_dataset(ds, size=cfg.data.render_size)
    sizes = sorted({renderer.table(tid, grid).size for tid in ds.tables})
    found = [(size, check_grid_resolution(processor, model_config, grid, key="model.image_size",
                                          render_size=cfg.data.render_size, image_size=size)) for size in sizes]
    if any(a is None for _, a in found):
        return "not computed: this model's image-token geometry is not known (vlm/token_grid.py)"
    text = "; ".join(a.describe() for _, a in found)
    if "context" in cfg.data.compose:
        text += " (the target image; data.compose [context] tiles the context images, not computed for them)"
    return text


def dry_run(cfg: FinetuneConfig, log=print, sample: int | None = 32, heaviest: bool = True) -> None:
    """`degusta train --dry-run` for kind finetune: sizes, token budget, steps and memory; loads no weights,
    trains nothing, writes nothing (an unbuilt tiny model is built in a temporary folder, then removed).

    Tokens: `token_budget` of the training and validation examples (every example's exact count, the image
    processor run on one example per image layout and on `sample` more to check; `heaviest`: each training
    example also with the heaviest contexts an epoch could draw). `sample=None, heaviest=False` is the count
    before `token_budget`: the processor on every example, epoch 0's contexts only (minutes; comparisons,
    benchmarks/bench_dry_run.py)."""
    import contextlib
    import dataclasses
    import tempfile
    import warnings

    import torch

    from degusta_learn.dryrun import dry_run_trainer_lines, print_dry_run
    from degusta_learn.finetune import lora
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.module import monitor_keys
    from degusta_learn.finetune.data import build_examples
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.training import trains_on_gpu
    from degusta_learn.vlm.hub import resolve_model
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor

    ds = load_dataset(cfg.dataset)
    grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
    notes = []
    with contextlib.ExitStack() as stack:
        source = cfg.model.name
        marker = Path(source) / "degusta_tiny.json"
        if cfg.model.build_tiny and not marker.is_file():
            from degusta_learn.vlm.random_models.tiny import ensure_tiny

            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="degusta-dry-run-"))
            source = str(ensure_tiny(Path(tmp) / "tiny", cfg.model.build_tiny))
            notes.append(f"{cfg.model.name} is not built yet: its tiny {cfg.model.build_tiny} was built in a temporary "
                         "folder to read its config and processor (the run builds it in place)")
        else:  # a hub id: its config and processor files only, downloaded now if missing (weights when it trains)
            source = str(resolve_model(source, "model.name", weights=False))
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
    calibration: dict = {}  # image layouts measured on the training examples serve the validation ones
    budget = token_budget(train, collator, sample, cfg.seed, heaviest, calibration)
    val_budget = token_budget(val, collator, None if sample is None else min(sample, 8), cfg.seed, False,
                              calibration)
    refuse_budget(budget, collator)
    refuse_budget(val_budget, collator)
    counts, val_counts = budget.everything, val_budget.counts
    t = cfg.trainer
    on_gpu = trains_on_gpu(t)
    what = {"lora": f"LoRA r={cfg.lora.r} adapters", "qlora": f"QLoRA r={cfg.lora.r} adapters on a 4-bit base",
            "full": "full fine-tuning" + (" (vision tower frozen)" if cfg.lora.freeze_vision else "")}[cfg.lora.mode]
    lines = [("model", f"{cfg.model.name} ({config.model_type}): {total:,} parameters, built on the meta device "
                       "(no weights loaded)"),
             ("trainable", f"{trainable:,} parameters ({trainable / max(total_after, 1):.2%} of {total_after:,}), "
                           f"{what}"),
             ("tokens per example", token_summary(budget.counts, cfg.data.max_length, "training examples",
                                                  budget.heavier)
              + (f"; validation: max {max(c['total'] for c in val_counts)} over {len(val_counts)}" if val_counts else "")),
             ("tokens counted", describe_budget(budget, val_budget, cfg.seed))]
    alignment = grid_alignment_line(cfg, ds, grid, processor, config)
    if alignment:
        lines.append(("grid alignment", alignment))
    lines += dry_run_trainer_lines(t, monitor_keys(cfg), len(train), cfg.data.batch_size)
    mem = vlm_memory(cfg.model, cfg.lora, t, config, total_after, trainable, cfg.data.batch_size, counts, on_gpu)
    lines.append(("predicted memory", mem.describe()))
    lines += [("note", n) for n in notes]
    print_dry_run(f"dry run of kind finetune ({cfg.method}): nothing loaded, trained or written", lines, log)
