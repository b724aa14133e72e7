"""`degusta train` with `kind: pretrain`: teach a tiny base VLM to *see* lifted images, from random weights.

Usage (the shipped recipe: 81 minutes on a 2-core EPYC, resumable by running the same command again):
    degusta train --config configs/pretrain_tiny_vlm_cpu.yaml
    degusta train --config configs/pretrain_tiny_vlm_cpu.yaml --set trainer.max_steps=40 --set data.tower_steps=20 \
        --set data.steps_per_epoch=20 --set trainer.run_name=pretrain_smoke --set export=runs/base_smoke   # smoke

What it does: builds a FastVLM of `model:` sizes with random weights and the domain tokenizer (saved
once in `<run>/init/`, so a resumed run continues the same model), then trains every weight on
perception questions about random style-free scenes (`tasks.py`; never a participant's arrangement,
never the DegustaBot question). An "epoch" is `data.steps_per_epoch` steps of fresh examples (the
sampler starts at the steps already trained, `StepSampler`, so no example repeats or is skipped, resumed
or not); each epoch ends with a
validation that generates answers to `data.val_examples` held-out questions (another seed) and logs
val/object_f1, val/cells_exact, val/direction, val/mark_id and their mean val/perception. At the end the
weights are written to `export` as a plain Hugging Face model folder (config, safetensors, processor,
tokenizer) with `degusta_base.json` and a model card (README.md): those of best.ckpt when `trainer.monitor`
names a metric (e.g. val/perception), else the last ones (the shipped config: its 16 validation questions
picked worse weights than the last twice).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from degusta_learn.methods import TrainerSpec
from degusta_learn.pretrain.config import PretrainConfig, PretrainData
from degusta_learn.render.grid import Grid
from degusta_learn.training import trains_on_gpu


def catalog_and_tables(dataset: str | None):
    """(catalog, tables, image root) from a dataset folder, or the embedded default's."""
    from degusta_learn.scene import default_catalog, default_tables, load_dataset

    if dataset is None:
        return default_catalog(), {t.id: t for t in default_tables()}, None
    ds = load_dataset(dataset)
    return ds.catalog, ds.tables, ds.root


class DenseCollate:
    """The collator's batch plus the dense targets (`dense.DenseLabels`) and, given `oracle`, the oracle
    token ids (`dense.OracleTokens`) of its examples."""

    def __init__(self, collator, labels, oracle=None, retrieval=None):
        self.collator, self.labels, self.oracle, self.retrieval = collator, labels, oracle, retrieval

    def __call__(self, examples) -> dict:
        batch = self.collator(examples)
        batch["dense_targets"], batch["dense_keep"] = self.labels(examples)
        if self.oracle is not None:
            batch["oracle_ids"] = self.oracle(examples)
        if self.retrieval is not None:
            batch.update(self.retrieval(examples, batch["input_ids"], batch["labels"]))
        return batch


class StepSampler:
    """Each epoch's `n` indices start where training stands: at `start()` batches done times the batch size, so
    every batch sees fresh examples and a resumed run sees exactly the examples an uninterrupted one would.
    (Lightning's epoch counter is not used: resumed from a checkpoint written at an epoch's end, the run began
    one epoch ahead and skipped that epoch's examples, e.g. 150 steps of a curriculum.)"""

    def __init__(self, n: int, batch_size: int, start=lambda: 0):
        self.n, self.batch_size, self.start = n, batch_size, start

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        first = int(self.start()) * self.batch_size
        return iter(range(first, first + self.n))


def prepare_model(model, cfg: PretrainConfig, export: bool = False) -> None:
    """The training-only memory layout of the tower (`channels_last`), or with `export` the usual one back.

    A tower with a strided 1 x 1 convolution over fewer than 16 channels stays in the usual layout: on AVX-512 CPUs
    oneDNN's backward pass of such a convolution in channels-last (8 channels in, 64 px) corrupts the heap and aborts
    the process (torch 2.14.1; 4, 16 and more channels ran, as does every layer of the recipe's tower)."""
    import torch

    if not cfg.channels_last:
        return
    tower = model.model.vision_tower
    if export:
        tower.to(memory_format=torch.contiguous_format)
    elif channels_last_is_safe(tower):
        tower.to(memory_format=torch.channels_last)
    else:
        print("degusta: note: channels_last: the tower keeps the usual layout (a strided 1x1 convolution over fewer "
              "than 16 channels aborts its backward pass in channels-last on AVX-512 CPUs)", file=sys.stderr)


def channels_last_is_safe(tower) -> bool:
    """False where the tower has a convolution that oneDNN mishandles in channels-last (`prepare_model`)."""
    import torch

    return not any(isinstance(m, torch.nn.Conv2d) and m.kernel_size == (1, 1) and max(m.stride) > 1
                   and m.in_channels < 16 for m in tower.modules())


def needs_oracle(d: PretrainData) -> bool:
    """True when batches carry each cell's oracle token ids (the teacher and the tied readout use them)."""
    return d.teacher_steps > 0 or d.readout_weight > 0


def oracle_key(d: PretrainData) -> str:
    """The config key an error about the oracle tokens names."""
    return "teacher_steps" if d.teacher_steps > 0 else "readout_weight"


def initial_model(cfg: PretrainConfig, run_dir: Path, catalog=None, grid=None) -> Path:
    """`<run>/init/`: the random-weight base and its processor, built once (a resumed run reuses it).
    With `data.teacher_steps`, `data.readout_weight` or `data.retrieval_weight`, the tokenizer is checked for the
    oracle tokens and the attention supervision (given `catalog` and `grid`) before anything is written."""
    from degusta_learn.files.jsonio import atomic_write_json
    from degusta_learn.pretrain.base import build_base
    from degusta_learn.vlm.load import quiet_transformers

    init = run_dir / "init"
    if (init / "degusta_init.json").is_file():
        return init
    quiet_transformers()
    model, processor = build_base(cfg.model, seed=cfg.seed)
    if needs_oracle(cfg.data) and catalog is not None and grid is not None:
        from degusta_learn.pretrain.dense import OracleTokens

        OracleTokens(catalog, processor.tokenizer, grid, oracle_key(cfg.data))  # refuses a tokenizer that splits cells or ids
    if cfg.data.retrieval_weight > 0 and catalog is not None and grid is not None:
        from degusta_learn.pretrain.retrieval import RetrievalTargets

        RetrievalTargets(catalog, processor.tokenizer, model.config.image_token_id, cfg.model.tokens_per_image, grid)
    from degusta_learn.files.write_errors import writing

    with writing(init, "initial model", after="; free space and re-run (it is rebuilt)"):  # one line, no traceback
        init.mkdir(parents=True, exist_ok=True)
        model.save_pretrained(str(init))
        processor.save_pretrained(str(init))
    atomic_write_json(init / "degusta_init.json", {"note": "random initial weights of a pretrain run"})  # last: marks it whole
    return init


@dataclass
class RecipeParts:
    """What `run` trains: the model and its processor, the module, the example streams and their collators."""

    processor: object
    module: object
    train: object
    val: object
    collate: object
    """The training batches' collator (with the dense, oracle and retrieval targets the losses need)."""
    collator: object
    """The plain collator (validation batches)."""


def build_recipe(cfg: PretrainConfig, run_dir: Path, module_cls=None) -> RecipeParts:
    """The initial model (`initial_model`, in the training layout), the PerceptionModule (or `module_cls`) and the
    example streams and collators of `cfg`, as `run` trains them (benchmarks/bench_pretrain_steps.py times them)."""
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.pretrain.dense import DenseLabels, OracleTokens
    from degusta_learn.pretrain.module import PerceptionModule
    from degusta_learn.pretrain.retrieval import RetrievalTargets
    from degusta_learn.pretrain.tasks import PerceptionExamples
    from degusta_learn.vlm.generate import chat_format
    from degusta_learn.vlm.load import load_vlm

    d = cfg.data
    catalog, tables, root = catalog_and_tables(cfg.dataset)
    grid = Grid(d.grid.rows, d.grid.cols)
    model, processor = load_vlm(str(initial_model(cfg, run_dir, catalog, grid)), device="cpu", dtype="float32",
                                key="model")
    prepare_model(model, cfg)
    model.train()
    collator = Collator(processor, chat_format(model, processor), d.max_length, model.config.image_token_id)
    steps = cfg.trainer.max_steps if cfg.trainer.max_steps > 0 else d.steps_per_epoch * max(1, cfg.trainer.max_epochs)
    side = cfg.model.tokens_per_side
    make = lambda seed, n, block, early=None: PerceptionExamples(  # noqa: E731
        catalog, tables, grid, cfg.model.image_size, seed, n, d.mix, block, root, early)
    # a curriculum's first steps ask other questions; validation always asks the final mix's
    batches = steps * cfg.trainer.accumulate_grad_batches
    train = make(cfg.seed, (batches + d.steps_per_epoch) * d.batch_size, d.batch_size,  # the vision stage's
                 ((d.tower_steps + d.curriculum_steps) * cfg.trainer.accumulate_grad_batches * d.batch_size,
                  d.curriculum_mix))  # images are one-scene
    val = make(cfg.seed + 1_000_003, d.val_examples, 1)
    labels = DenseLabels(catalog, side)
    module = (module_cls or PerceptionModule)(model, processor, cfg, catalog, grid, labels.n_labels, side)
    oracle = OracleTokens(catalog, processor.tokenizer, grid, oracle_key(d)) if needs_oracle(d) else None
    retrieval = RetrievalTargets(catalog, processor.tokenizer, model.config.image_token_id, side * side,
                                 grid) if d.retrieval_weight > 0 else None
    dense = d.dense_weight > 0 or oracle is not None or retrieval is not None
    return RecipeParts(processor, module, train, val,
                       DenseCollate(collator, labels, oracle, retrieval) if dense else collator, collator)


def run(cfg: PretrainConfig) -> Path:
    """Pretrain per `cfg` (resuming `<run>/last.ckpt` if present); returns the exported model folder."""
    import torch

    from degusta_learn.finetune.module import FinetuneData
    from degusta_learn.pretrain.export import export_base
    from degusta_learn.pretrain.module import monitor_keys
    from degusta_learn.training import BEST, fit, training_run

    with training_run(cfg.trainer, monitor_keys(cfg)):  # checks trainer values, seeds before the model exists
        run_dir = cfg.trainer.path
        run_dir.mkdir(parents=True, exist_ok=True)
        parts = build_recipe(cfg, run_dir)
        module, processor, d = parts.module, parts.processor, cfg.data
        sampler = StepSampler(d.steps_per_epoch * d.batch_size, d.batch_size,
                              lambda: module.global_step * cfg.trainer.accumulate_grad_batches)
        data = FinetuneData(parts.train, parts.val, parts.collate, d.batch_size, d.num_workers, sampler=sampler,
                            val_collator=parts.collator)
        run_dir = fit(module, data, cfg.trainer, full_config=cfg, monitors=monitor_keys(cfg))
        out, by_name = cfg.export_target
        if module.trainer is not None and not module.trainer.is_global_zero:
            return out
        best, step = run_dir / BEST, module.global_step
        if best.is_file():  # trainer.monitor set: export the best validation, not merely the last weights
            state = torch.load(best, map_location="cpu", weights_only=True)
            module.load_state_dict(state["state_dict"])
            step = int(state.get("global_step", step))
        prepare_model(module.model, cfg, export=True)
        return export_base(module.model, processor, cfg, out, run_dir, steps=step, run_steps=module.global_step,
                           replace_shipped=by_name)

def dry_run(cfg: PretrainConfig, log=print, sample: int = 256) -> None:
    """`degusta train --dry-run` for kind pretrain: sizes, tokens per example against data.max_length, steps
    and a memory estimate. The FastVLM is built on the meta device (no weights); `<run>/init/`'s config and
    processor are used when a run exists, else the processor is built in memory. Token counts cover the first
    `sample` training examples (the stream is endless: every epoch draws fresh ones) and every validation one."""
    import warnings

    import torch

    from degusta_learn.dryrun import dry_run_trainer_lines, print_dry_run
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import ModelConfig
    from degusta_learn.finetune.dry_run import meta_model, vlm_memory
    from degusta_learn.finetune.lora import LoraConfig
    from degusta_learn.finetune.token_count import count_tokens, refuse_over_budget, token_summary
    from degusta_learn.pretrain.base import build_base
    from degusta_learn.pretrain.module import monitor_keys
    from degusta_learn.pretrain.tasks import PerceptionExamples
    from degusta_learn.vlm.inputs import ChatFormat

    catalog, tables, root = catalog_and_tables(cfg.dataset)
    grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
    init = cfg.trainer.path / "init"
    if (init / "degusta_init.json").is_file():
        from degusta_learn.vlm.load import load_processor

        model, config = meta_model(str(init), key="model")
        processor, where = load_processor(str(init), "model"), f"{init}'s config"
    else:
        with torch.device("meta"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, processor = build_base(cfg.model, seed=cfg.seed)
        config, where = model.config, "model: sizes"
    total = sum(p.numel() for p in model.parameters())
    collator = Collator(processor, ChatFormat(processor, model.generation_config), cfg.data.max_length,
                        config.image_token_id)
    d = cfg.data
    make = lambda seed, n, block: PerceptionExamples(catalog, tables, grid, cfg.model.image_size, seed, n,  # noqa: E731
                                                     d.mix, block, root)
    train, val = make(cfg.seed, sample, d.batch_size), make(cfg.seed + 1_000_003, d.val_examples, 1)
    counts, val_counts = count_tokens(train, collator), count_tokens(val, collator)
    refuse_over_budget(train, counts, collator)
    refuse_over_budget(val, val_counts, collator)
    t = cfg.trainer
    lines = [("model", f"FastVLM from {where}: {total:,} parameters, built on the meta device (random initial "
                       "weights at run time; nothing loaded)"),
             ("trainable", f"{total:,} parameters (all: pretraining from scratch)"),
             ("tokens per example", token_summary(counts, d.max_length, "sampled training examples")
              + (f"; validation: max {max(c['total'] for c in val_counts)} over {len(val_counts)}" if val_counts else ""))]
    if d.tower_steps > 0:
        lines.append(("vision stage", f"steps 0-{d.tower_steps - 1}: only the vision tower, projector and dense head "
                                      f"train (dense loss alone, one-scene images); the decoder's curriculum "
                                      f"({d.curriculum_steps} steps), teacher and warmup start at step {d.tower_steps}"
                                      + ("; the tower is then frozen" if d.freeze_tower else "")))
    lines += dry_run_trainer_lines(t, monitor_keys(cfg), d.steps_per_epoch * d.batch_size, d.batch_size)
    on_gpu = trains_on_gpu(t)
    mem = vlm_memory(ModelConfig(dtype="float32"), LoraConfig(mode="full"), t, config, total, total, d.batch_size,
                     counts, on_gpu)
    lines.append(("predicted memory", mem.describe()))
    print_dry_run("dry run of kind pretrain: nothing loaded, trained or written", lines, log)


TRAINER = TrainerSpec(PretrainConfig, run, "pretrain a tiny base VLM from random weights on perception questions "
                      "about random scenes (never the preference task); exports a Hugging Face model folder",
                      dry_run=dry_run)
