"""The typed config of `degusta train` with `kind: finetune` (see configs/finetune_*.yaml)."""

from __future__ import annotations

from dataclasses import dataclass, field

from degusta_learn.config import bounded, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.lora import LoraConfig
from degusta_learn.trainer import TrainerConfig
from degusta_learn.vlm.prompt_options import COMPOSE, GROUPS


@dataclass
class ModelConfig:
    """The `model:` section: which VLM, its dtype and image budget."""

    name: str = "HuggingFaceTB/SmolVLM-256M-Instruct"
    """Hub id (must already be in the local HF cache: nothing is downloaded) or a saved model folder."""
    build_tiny: str | None = None
    """idefics3 or qwen2vl: build a random-weight tiny model at `name` if that folder is missing (CPU smoke runs)."""
    dtype: str = "auto"
    """auto (bf16 on a bf16 GPU, else fp32), float32, bfloat16, float16."""
    image_size: int | None = bounded(None, 16, 4096)
    """Pixels per image side the model sees (Idefics3: one tile; Qwen2-VL: image_size^2 px). null: model default."""
    gradient_checkpointing: bool = False
    """Recompute activations in backward (less memory, ~30% slower); input grads are enabled for LoRA."""


@dataclass
class GridConfig:
    """The labelled grid of grid methods (must match the predict config's grid)."""

    rows: int = bounded(8, 1, 99)
    """Rows, numbered from the top."""
    cols: int = bounded(8, 1, 26)
    """Columns, lettered from the left."""


@dataclass
class DataConfig:
    """The `data:` section: which episodes, how they are drawn and batched."""

    contexts: list[int] = field(default_factory=lambda: [0, 2, 4])
    """Context lengths of the training episodes (all trials of every train participant, per length)."""
    val_context: int = 4
    """Context length of the validation episodes (val participants)."""
    val_episodes: int = bounded(16, 0, 100_000)
    """Validation episodes generated per validation (0: no validation)."""
    max_train_episodes: int | None = bounded(None, 1, 10_000_000)
    """Cap on training episodes (a seeded subset; null: all)."""
    render_size: int = bounded(448, 32, 4096)
    """Side in pixels the lifted images are drawn at (the processor then resizes to model.image_size)."""
    grid: GridConfig = field(default_factory=GridConfig)
    """Grid of grid methods."""
    include: list[str] = field(default_factory=lambda: list(GROUPS))
    """Image groups sent: objects (GoMO sheets), context (final_state_k), target (initial_state_1)."""
    compose: list[str] = field(default_factory=list)
    """Groups drawn as ONE labelled canvas to save image tokens: objects, context, all."""
    max_length: int = bounded(2048, 16, 262_144)
    """Token budget of one example (prompt + images + answer); longer examples are an error, never truncated."""
    batch_size: int = bounded(4, 1, 4096)
    """Examples per step (effective batch = this x trainer.accumulate_grad_batches x devices)."""
    num_workers: int = bounded(0, 0, 256)
    """DataLoader worker processes rendering images (0: in the main process)."""

    def __post_init__(self):
        for k in self.contexts:
            if k not in (0, 2, 4):
                raise DegustaError(f"data.contexts: expected values in [0, 2, 4], got {k}")
        if self.val_context not in (0, 2, 4):
            raise DegustaError(f"data.val_context: expected 0, 2 or 4, got {self.val_context}")
        bad = [g for g in self.include if g not in GROUPS] + [g for g in self.compose if g not in COMPOSE]
        if bad:
            raise DegustaError(f"data.include / data.compose: unknown group {bad[0]!r}")
        if self.batch_size < 1 or self.max_length < 16:
            raise DegustaError("data.batch_size / data.max_length: expected >= 1 / >= 16")


@dataclass
class OptimConfig:
    """The `optim:` section."""

    lr: float = bounded(2e-4, 0.0, 100.0)
    """Peak learning rate (LoRA ~1e-4..5e-4; full fine-tuning ~1e-5..5e-5; tiny from scratch ~1e-3)."""
    weight_decay: float = 0.0
    """AdamW weight decay."""
    warmup_steps: int = bounded(10, 0, 1_000_000_000)
    """Linear warmup steps."""
    schedule: str = "cosine"
    """cosine (to 5% of lr at the last step) or constant."""

    def __post_init__(self):
        if self.schedule not in ("cosine", "constant"):
            raise DegustaError(f"optim.schedule: expected cosine or constant, got {self.schedule!r}")


@dataclass
class EvalConfig:
    """The `eval:` section: how validation generates."""

    constrained: bool = True
    """Constrain validation answers to the answer grammar (parse rate 100% by construction)."""
    report_unconstrained: bool = False
    """Also generate unconstrained and log val/parse_rate_unconstrained (twice the validation time)."""
    max_new_tokens: int = bounded(384, 1, 32_768)
    """Most new tokens per generated answer."""


@dataclass
class FinetuneConfig:
    """`degusta train` with `kind: finetune`: fine-tune a VLM on lifted images of one prompting method."""

    kind: str = "finetune"
    """Trainer name (TRAINERS)."""
    dataset: str = "data/naturalistic"
    """Dataset folder; train/val participants come from its seeded split."""
    method: str = "mogma"
    """Prompting method whose prompts and answer format are learned: mogma, logma (grid) or mouma, louma."""
    seed: int = seed_field()
    """Seed of the participant split (use the same `seed` in predict configs) and of training."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Which VLM."""
    lora: LoraConfig = field(default_factory=LoraConfig)
    """Adapters (or full fine-tuning)."""
    data: DataConfig = field(default_factory=DataConfig)
    """Examples and batching."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimizer and schedule."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Validation generation."""
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(run_name="finetune"))
    """Lightning settings and the run folder."""

    def __post_init__(self):
        if self.method not in ("louma", "logma", "mouma", "mogma"):
            raise DegustaError(f"method: expected louma, logma, mouma or mogma, got {self.method!r}")
