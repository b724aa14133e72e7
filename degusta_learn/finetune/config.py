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
from degusta_learn.training import TrainerConfig
from degusta_learn.vlm.prompt_options import COMPOSE, GROUPS, PromptOptions
from degusta_learn.vlm.settings import ON_REPEAT_RENAMED, DecodingSettings, ModelSettings

CONTEXT_ANSWERS_RENAMED = "data.modality (true was both: images + text; false was images; or text: text only)"


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
class ModelConfig(ModelSettings):
    """The `model:` section of fine-tuning: the shared one (`vlm.settings.ModelSettings`: name, dtype, image_size)
    plus how it trains. Full fine-tuning needs fp32 weights (the optimizer's master weights): bfloat16 / float16
    with lora.mode full are refused (train them with trainer.precision bf16-mixed); dtype auto is then float32."""

    build_tiny: str | None = None
    """idefics3 or qwen2vl: build a random-weight tiny model at `name` if that folder is missing (CPU smoke runs)."""
    gradient_checkpointing: bool = False
    """Recompute activations in backward (less memory, ~30% slower); input grads are enabled for LoRA."""
    cache_tower: bool = True
    """While the vision tower is frozen (LoRA without vision_targets), compute its features once per distinct
    picture (the object sheet, the empty tables and a person's arrangements recur): same numbers, ~30% less
    time a step on a CPU (`finetune.tower_cache`). Off by itself when the tower trains."""


@dataclass
class DataConfig:
    """The `data:` section: which episodes, how they are drawn and batched."""

    contexts: list[int] = field(default_factory=lambda: list(CONTEXT_LENGTHS))
    """Context lengths of the training episodes (all trials of every train participant, per length)."""
    val_contexts: list[int] = field(default_factory=lambda: [4])
    """Context lengths of the validation episodes (val participants; `data.val_episodes` drawn from all of them)."""
    RENAMED: ClassVar[dict[str, str]] = {"val_context": "data.val_contexts (a list, e.g. [4])",
                                         "context_answers": CONTEXT_ANSWERS_RENAMED}
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
    modality: Literal["images", "text", "both"] = "images"
    """How the context tables are shown (task.prompt.MODALITIES): images (the paper's prompt), text (each written in
    the answer format after its placement-order line: ids, cells, directions; the context images left out) or both.
    Saved in the adapter's record, so predict prompts the same way (the predict config's `modality` unless set)."""
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
        bad = [k for k in self.val_contexts if k not in CONTEXT_LENGTHS]
        if bad or not self.val_contexts or len(set(self.val_contexts)) < len(self.val_contexts):
            raise DegustaError(f"data.val_contexts: expected a non-empty list of distinct lengths drawn from "
                               f"{list(CONTEXT_LENGTHS)}, got {self.val_contexts}")
        bad = [g for g in self.include if g not in GROUPS] + [g for g in self.compose if g not in COMPOSE]
        if bad:
            raise DegustaError(f"data.include / data.compose: unknown group {bad[0]!r}")
        if self.batch_size < 1 or self.max_length < 16:
            raise DegustaError("data.batch_size / data.max_length: expected >= 1 / >= 16")
        self.prompt_options()  # data.modality against data.include

    def prompt_options(self) -> PromptOptions:
        """How this config's prompts are cut down (and how predict re-applies them from the adapter's record)."""
        return PromptOptions(include=list(self.include), compose=list(self.compose), modality=self.modality)


@dataclass
class EvalConfig:
    """The `eval:` section: what only validation has (how it generates is the `decoding:` section)."""

    batch_size: int | None = bounded(None, 1, 4096)
    """Validation episodes answered by one `generate` call (left-padded; n > 1 makes it batch_size x n rows);
    null: data.batch_size. Greedy answers are those of one-by-one generation (tests/test_finetune_validation.py)."""
    log_images: int = bounded(2, 0, 1000)
    """Validation episodes drawn as ground truth vs prediction (the first ones) at every validation: PNGs in
    <run>/val_images/step_<N>/ and images in TensorBoard (rank 0); 0: none."""

    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"decoding.{k}" for k in ("constrained", "report_unconstrained", "on_repeat", "max_new_tokens", "n",
                                        "aggregation", "temperature")},
        "stop_on_repeat": ON_REPEAT_RENAMED}


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
    model: ModelConfig = field(default_factory=lambda: ModelConfig(name="HuggingFaceTB/SmolVLM-256M-Instruct"))
    """Which VLM (no adapter: fine-tuning trains its own on `model.name`)."""
    lora: LoraConfig = field(default_factory=LoraConfig)
    """Adapters (or full fine-tuning)."""
    data: DataConfig = field(default_factory=DataConfig)
    """Examples and batching."""
    optim: FinetuneOptimConfig = field(default_factory=lambda: FinetuneOptimConfig(lr=2e-4))
    """Optimizer and schedule."""
    decoding: DecodingSettings = field(default_factory=DecodingSettings)
    """How validation generates, as `degusta predict` does with the hf backend (constrained null: true;
    max_new_tokens auto: sized from the dataset with the model's tokenizer, `vlm.generate.answer_token_budget`)."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """What only validation has: episodes per generate call, episodes drawn as pictures (`log_images`)."""
    trainer: FinetuneTrainerConfig = field(default_factory=FinetuneTrainerConfig)
    """Lightning settings and the run folder; best.ckpt and best_adapter/ are selected on `trainer.monitor`."""

    def __post_init__(self):
        check_choices(self, '')
        if not self.model.name.strip():
            raise DegustaError("model.name: required: a hub id (e.g. HuggingFaceTB/SmolVLM-256M-Instruct), a model "
                               "folder or a shipped model (tiny_vlm_base)")
        if self.model.adapter is not None:
            raise DegustaError("model.adapter: fine-tuning trains a new adapter on model.name and starts from none; "
                               "to go on from a fine-tuned model, give its merged folder (lora.merge) as model.name")
        self.decoding = self.decoding.resolved(local=True)  # validation decodes with the local model
        if self.lora.mode == "full" and self.model.dtype in HALF_DTYPES:
            raise DegustaError(f"model.dtype: {self.model.dtype} with lora.mode full would train the weights "
                               f"themselves in {self.model.dtype} (no fp32 master weights: small updates round "
                               f"away); use model.dtype float32 (or auto) with trainer.precision bf16-mixed")
        if self.trainer.precision in HALF_TRUE_PRECISIONS:
            raise DegustaError(f"trainer.precision: {self.trainer.precision} casts the trained weights to half "
                               f"precision (no fp32 master weights: small updates round away); use bf16-mixed "
                               f"(LoRA keeps its adapters in fp32 on a bf16 base; full keeps fp32 weights)")

    @property
    def weights_dtype(self) -> str:
        """The dtype the model is loaded in: `model.dtype`, except that full fine-tuning resolves auto to float32."""
        return "float32" if self.lora.mode == "full" and self.model.dtype == "auto" else self.model.dtype
