"""The typed config of `degusta train` with `kind: finetune` (see configs/finetune_*.yaml)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

from degusta_learn.config import bounded, check_choices, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.lora import LoraConfig
from degusta_learn.names import CONTEXT_LENGTHS
from degusta_learn.optim import OptimConfig
from degusta_learn.render.grid import Grid
from degusta_learn.task.aggregate import ANCHORED, Aggregation
from degusta_learn.training import TrainerConfig
from degusta_learn.vlm.prompt_options import COMPOSE, GROUPS, PromptOptions


@dataclass
class FinetuneOptimConfig(OptimConfig):
    """The `optim:` section of fine-tuning: the shared one, plus learning rates of their own for the vision tower
    and the connector (AdamW parameter groups; what trains there is set by `lora.vision_targets`,
    `lora.connector`, or `lora.mode: full`)."""

    vision_lr: float | None = bounded(None, 0.0, 100.0)
    """Peak learning rate of the vision tower's trained parameters (null: optim.lr); e.g. lr / 10 when it trains."""
    connector_lr: float | None = bounded(None, 0.0, 100.0)
    """Peak learning rate of the connector / projector's trained parameters (null: optim.lr)."""

    def __post_init__(self):
        super().__post_init__()
        for key in ("vision_lr", "connector_lr"):
            if getattr(self, key) is not None and getattr(self, key) <= 0:
                raise DegustaError(f"optim.{key}: expected > 0 or null, got {getattr(self, key)}")


DEFAULT_MONITOR = "val/set_rmsd"
"""The monitor of fine-tuning unless `trainer.monitor` names another: the set-aware validation score (lower is
better); every unmatched object costs a fixed penalty, so a one-object answer cannot be selected as best."""
HALF_DTYPES = ("bfloat16", "float16")
HALF_TRUE_PRECISIONS = ("bf16-true", "16-true")


@dataclass
class ModelConfig:
    """The `model:` section: which VLM, its dtype and image budget."""

    name: str = "HuggingFaceTB/SmolVLM-256M-Instruct"
    """Hub id (must already be in the local HF cache: nothing is downloaded) or a saved model folder."""
    build_tiny: str | None = None
    """idefics3 or qwen2vl: build a random-weight tiny model at `name` if that folder is missing (CPU smoke runs)."""
    dtype: Literal["auto", "float32", "bfloat16", "float16"] = "auto"
    """Weights' dtype: auto (LoRA: bf16 on a bf16 GPU, else fp32; full: fp32), float32, bfloat16, float16.
    Full fine-tuning needs fp32 weights (they are the optimizer's master weights): train them with
    trainer.precision bf16-mixed; bfloat16 / float16 with lora.mode full are refused."""
    image_size: int | None = bounded(None, 16, 4096)
    """Pixels per image side the model sees (Idefics3: one tile; Qwen2-VL: image_size^2 px). null: model default."""
    gradient_checkpointing: bool = False
    """Recompute activations in backward (less memory, ~30% slower); input grads are enabled for LoRA."""
    cache_tower: bool = True
    """While the vision tower is frozen (LoRA without vision_targets), compute its features once per distinct
    picture (the object sheet, the empty tables and a person's arrangements recur): same numbers, ~30% less
    time a step on a CPU (`finetune.tower_cache`). Off by itself when the tower trains."""

    def __post_init__(self):
        check_choices(self, "model")


@dataclass
class DataConfig:
    """The `data:` section: which episodes, how they are drawn and batched."""

    contexts: list[int] = field(default_factory=lambda: list(CONTEXT_LENGTHS))
    """Context lengths of the training episodes (all trials of every train participant, per length)."""
    val_context: int = 4
    """Context length of the validation episodes (val participants)."""
    val_episodes: int = bounded(16, 0, 100_000)
    """Validation episodes generated per validation (0: no validation)."""
    max_train_episodes: int | None = bounded(None, 1, 10_000_000)
    """Cap on training episodes (a seeded subset; null: all)."""
    render_size: int = bounded(448, 32, 4096)
    """Side in pixels the lifted images are drawn at (the processor then resizes to model.image_size)."""
    grid: Grid = field(default_factory=Grid)
    """Grid of grid methods."""
    include: list[str] = field(default_factory=lambda: list(GROUPS))
    """Image groups sent: objects (GoMO sheets), context (final_state_k), target (initial_state_1)."""
    compose: list[str] = field(default_factory=list)
    """Groups drawn as ONE labelled canvas to save image tokens: objects, context, all."""
    context_answers: bool = False
    """After each context image, its arrangement written in the answer format (ids, cells, directions): the
    model is told which objects the person used instead of reading them from the pictures. Not the paper's
    prompt (vlm/prompt_options.py); saved with the adapter, so predict prompts the same way."""
    list_end_weight: float = bounded(1.0, 0.0, 1000.0)
    """Loss weight of the answer tokens that decide the list's length: each one that ends the list ("]") or
    goes on to another item (", {"); 1: every answer token alike. The loss is then the weighted mean
    (`finetune/loss.py`)."""
    max_length: int = bounded(2048, 16, 262_144)
    """Token budget of one example (prompt + images + answer); longer examples are an error, never truncated."""
    batch_size: int = bounded(4, 1, 4096)
    """Examples per step (effective batch = this x trainer.accumulate_grad_batches x devices)."""
    num_workers: int = bounded(0, 0, 256)
    """DataLoader worker processes rendering images (0: in the main process)."""
    resample_contexts: bool = True
    """Draw each training episode's context trials afresh every epoch (from the same participant's other trials,
    seeded by trainer.seed, epoch and index); false: the same contexts every epoch. Validation episodes never change."""
    group_by_length: bool = False
    """Batch examples of similar token counts together (less padding; transformers' length-grouped order)."""

    def __post_init__(self):
        bad = [k for k in self.contexts if k not in CONTEXT_LENGTHS]
        if bad or not self.contexts:
            raise DegustaError(f"data.contexts: expected a non-empty list drawn from {list(CONTEXT_LENGTHS)}, got "
                               f"{self.contexts}")
        if self.val_context not in CONTEXT_LENGTHS:
            raise DegustaError(f"data.val_context: expected one of {list(CONTEXT_LENGTHS)}, got {self.val_context}")
        bad = [g for g in self.include if g not in GROUPS] + [g for g in self.compose if g not in COMPOSE]
        if bad:
            raise DegustaError(f"data.include / data.compose: unknown group {bad[0]!r}")
        if self.batch_size < 1 or self.max_length < 16:
            raise DegustaError("data.batch_size / data.max_length: expected >= 1 / >= 16")

    def prompt_options(self) -> PromptOptions:
        """How this config's prompts are cut down (and how predict re-applies them from the adapter's record)."""
        return PromptOptions(include=list(self.include), compose=list(self.compose),
                             context_answers=self.context_answers)


@dataclass
class EvalConfig:
    """The `eval:` section: how validation generates."""

    constrained: bool = True
    """Constrain validation answers to the answer grammar (parse rate 100% by construction)."""
    report_unconstrained: bool = False
    """Also generate unconstrained and log val/parse_rate_unconstrained (twice the validation time)."""
    on_repeat: Literal["skip", "stop", "next", "substitute"] = "skip"
    """Constrained: what an item naming an object the answer already placed does (as the hf backend's
    `backend.on_repeat`, so validation scores what predict writes): skip, stop, next or substitute."""
    RENAMED: ClassVar[dict[str, str]] = {"stop_on_repeat": "on_repeat (skip, stop, next or substitute; true was stop)"}
    max_new_tokens: int = bounded(384, 1, 32_768)
    """Most new tokens per generated answer."""
    batch_size: int | None = bounded(None, 1, 4096)
    """Validation episodes answered by one `generate` call (left-padded; n > 1 makes it batch_size x n rows);
    null: data.batch_size. Greedy answers are those of one-by-one generation (tests/test_finetune_validation.py)."""
    n: int = bounded(1, 1, 64)
    """Answers per validation episode: 1 = one answer, as before; > 1 = n sampled answers aggregated exactly as
    `degusta predict` aggregates them (task/aggregate.py), the aggregate then scored (n x the generation)."""
    aggregation: Aggregation = "steps"
    """n > 1: how the answers become one plan, as predict's `aggregation` (steps: the paper's; votes: the objects
    most answers name, as many as the median answer's length; greedy_votes: one more, greedy answer lengthened
    by the samples' votes, a second `generate` call; greedy_votes_pooled: the same objects, each placed from every
    answer naming it; greedy_votes_context: that at the median count of the example's context tables)."""
    temperature: float | None = bounded(None, 0.0, 10.0)
    """Sampling temperature of the validation answers; null: 0 (greedy) at n = 1, 1.0 (predict's default) at
    n > 1. Samples are seeded by `seed` and the episode's position, so a validation is reproducible."""
    log_images: int = bounded(2, 0, 1000)
    """Validation episodes drawn as ground truth vs prediction (the first ones) at every validation: PNGs in
    <run>/val_images/step_<N>/ and images in TensorBoard (rank 0); 0: none."""

    @property
    def sampling_temperature(self) -> float:
        """The temperature validation generates at (`temperature`, or its default for `n`)."""
        if self.temperature is not None:
            return float(self.temperature)
        return 1.0 if self.n > 1 else 0.0

    def __post_init__(self):
        check_choices(self, "eval")  # on_repeat, aggregation: built in Python too (the loader checks YAML)
        if self.aggregation in ANCHORED and self.sampling_temperature == 0:
            raise DegustaError(f"eval.aggregation: {self.aggregation} lengthens a greedy answer by sampled ones; set "
                               "eval.n > 1 (or eval.temperature > 0)")


@dataclass
class FinetuneTrainerConfig(TrainerConfig):
    """The `trainer:` section of fine-tuning: the shared TrainerConfig, selecting on the set-aware score."""

    run_name: str = "finetune"
    """Run folder name: outputs go to `<run_dir>/<run_name>/`."""
    monitor: str | None = DEFAULT_MONITOR
    """Metric that picks best.ckpt and best_adapter/ (val/set_rmsd: lower is better; null: only the last weights)."""


@dataclass
class FinetuneConfig:
    """`degusta train` with `kind: finetune`: fine-tune a VLM on lifted images of one prompting method."""

    kind: str = "finetune"
    """Trainer name (TRAINERS)."""
    dataset: str = "data/naturalistic"
    """Dataset folder; train/val participants come from its seeded split."""
    method: Literal["louma", "logma", "mouma", "mogma"] = "mogma"
    """Prompting method whose prompts and answer format are learned: mogma, logma (grid) or mouma, louma."""
    seed: int = seed_field()
    """Seed of the participant split (use the same `seed` in predict configs) and of the validation subset;
    `trainer.seed` seeds the training itself (adapter init, example order, resampled contexts)."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Which VLM."""
    lora: LoraConfig = field(default_factory=LoraConfig)
    """Adapters (or full fine-tuning)."""
    data: DataConfig = field(default_factory=DataConfig)
    """Examples and batching."""
    optim: FinetuneOptimConfig = field(default_factory=lambda: FinetuneOptimConfig(lr=2e-4))
    """Optimizer and schedule."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Validation generation."""
    trainer: FinetuneTrainerConfig = field(default_factory=FinetuneTrainerConfig)
    """Lightning settings and the run folder; best.ckpt and best_adapter/ are selected on `trainer.monitor`."""

    def __post_init__(self):
        check_choices(self, '')
        if self.lora.mode == "full" and self.model.dtype in HALF_DTYPES:
            raise DegustaError(f"model.dtype: {self.model.dtype} with lora.mode full would train the weights "
                               f"themselves in {self.model.dtype} (no fp32 master weights: small updates round "
                               f"away); use model.dtype float32 (or auto) with trainer.precision bf16-mixed")
        if self.trainer.precision in HALF_TRUE_PRECISIONS:
            raise DegustaError(f"trainer.precision: {self.trainer.precision} casts the trained weights to half "
                               f"precision (no fp32 master weights: small updates round away); use bf16-mixed "
                               f"(LoRA keeps its adapters in fp32 on a bf16 base; full keeps fp32 weights)")
        if self.eval.aggregation == "greedy_votes_context" and self.data.val_context == 0:
            raise DegustaError("eval.aggregation: greedy_votes_context takes its length from the context tables; "
                               "data.val_context 0 has none (use greedy_votes_pooled)")

    @property
    def weights_dtype(self) -> str:
        """The dtype the model is loaded in: `model.dtype`, except that full fine-tuning resolves auto to float32."""
        return "float32" if self.lora.mode == "full" and self.model.dtype == "auto" else self.model.dtype
