"""`degusta train --dry-run`: what a run would cost, without loading weights or writing anything.

The report lines every trainer kind shares (steps per epoch, the trainer check on this machine) and the
simple memory model (`estimate_memory`, `transformer_activations`): an ESTIMATE, not checked against a GPU.
Each kind's `dry_run` (methods.TrainerSpec) adds its own lines (model size, tokens or slots per example).

Example:
    lines = [("model", "...")] + dry_run_trainer_lines(cfg.trainer, monitors, n_examples=200, batch_size=4)
    print_dry_run("dry run of kind finetune", lines)
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from degusta_learn.errors import DegustaError
from degusta_learn.trainer import TrainerConfig, check_trainer, world_size

GiB = 1024**3
ADAMW_STATE_BYTES = 8
"""AdamW keeps two fp32 moments (exp_avg, exp_avg_sq) per trainable parameter."""


@dataclass
class MemoryEstimate:
    """A predicted peak memory per device, in bytes, by parts (see `estimate_memory`): an ESTIMATE."""

    weights: int
    gradients: int
    optimizer: int
    activations: int
    note: str = ""

    @property
    def total(self) -> int:
        return self.weights + self.gradients + self.optimizer + self.activations

    def describe(self) -> str:
        parts = (f"weights {_size(self.weights)} + gradients {_size(self.gradients)} + AdamW states "
                 f"{_size(self.optimizer)} + activations {_size(self.activations)}")
        return f"~{_size(self.total)} per device (ESTIMATE, not measured: {parts}{'; ' + self.note if self.note else ''})"


def _size(n: float) -> str:
    for unit, scale in (("GiB", GiB), ("MiB", 1024**2), ("KiB", 1024)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{int(n)} B"


def estimate_memory(total_params: int, trainable_params: int, param_bytes: float, trainable_bytes: float = 4,
                    activation_bytes: float = 0, processes: int = 1, note: str = "") -> MemoryEstimate:
    """The simple memory model of `degusta train --dry-run` (an estimate; it is not checked against a GPU).

    peak ~ frozen params x `param_bytes` + trainable params x `trainable_bytes` (the weights)
         + trainable params x `trainable_bytes` (their gradients; x2 under DDP: the all-reduce buckets)
         + trainable params x 8 (AdamW's two fp32 moments)
         + `activation_bytes` (the caller's rough activation term for one batch).
    Not included: the CUDA context and kernels (~0.3-1 GiB), allocator fragmentation, data-loader workers.
    """
    frozen = max(0, total_params - trainable_params)
    grads = trainable_params * trainable_bytes * (2 if processes > 1 else 1)
    return MemoryEstimate(weights=int(frozen * param_bytes + trainable_params * trainable_bytes), gradients=int(grads),
                          optimizer=int(trainable_params * ADAMW_STATE_BYTES), activations=int(activation_bytes),
                          note=note)


def transformer_activations(tokens: int, hidden: int, intermediate: int, layers: int, value_bytes: float,
                            checkpointing: bool = False) -> float:
    """Rough bytes a decoder stack keeps for backward over `tokens` tokens (batch x sequence).

    Per layer and token a (LLaMA-style, SwiGLU, fused attention: no T^2 scores) layer keeps about
    6 x hidden + 4 x intermediate values (norm, QKV and output-projection inputs, attention output; gate, up,
    activation and down-projection inputs). With gradient checkpointing only each layer's input (hidden
    values) is kept, plus one layer's full set while it is recomputed.
    """
    per_layer = (6 * hidden + 4 * intermediate) * tokens * value_bytes
    if checkpointing:
        return hidden * tokens * value_bytes * layers + per_layer
    return per_layer * layers


def steps_per_epoch(n_examples: int, batch_size: int, cfg: TrainerConfig) -> tuple[int, int]:
    """(batches per process per epoch, optimizer steps per epoch) for `n_examples` under `cfg`'s processes."""
    per_process = math.ceil(n_examples / world_size(cfg))  # DistributedSampler pads to equal shares
    batches = math.ceil(per_process / batch_size)
    return batches, math.ceil(batches / cfg.accumulate_grad_batches)


def dry_run_trainer_lines(cfg: TrainerConfig, monitors: Iterable[str] | None, n_examples: int,
                          batch_size: int) -> list[tuple[str, str]]:
    """The report lines every kind shares: steps per epoch, the run's length, the trainer check on this machine."""
    batches, steps = steps_per_epoch(n_examples, batch_size, cfg)
    world = world_size(cfg)
    per = f"{n_examples} examples / ({batch_size} per batch x {world} process{'es' if world > 1 else ''})"
    acc = f", accumulating {cfg.accumulate_grad_batches}" if cfg.accumulate_grad_batches > 1 else ""
    limit = [f"max_steps {cfg.max_steps}" if cfg.max_steps > 0 else "",
             f"max_epochs {cfg.max_epochs}" if cfg.max_epochs > 0 else ""]
    lines = [("steps per epoch", f"{steps} ({per}{acc}); stops at {' or '.join(x for x in limit if x)}")]
    try:
        check_trainer(cfg, monitors)
        lines.append(("trainer check", f"ok on this machine ({cfg.accelerator}, devices {cfg.devices}, "
                                       f"num_nodes {cfg.num_nodes}, strategy {cfg.strategy}, {cfg.precision})"))
    except DegustaError as e:  # a GPU config checked on a login node: say so, the rest of the report still holds
        lines.append(("trainer check", f"FAILS on this machine: {e}"))
    return lines


def print_dry_run(title: str, lines: list[tuple[str, str]], log=print) -> None:
    """`title` then aligned `label  value` lines."""
    log(title)
    width = max((len(k) for k, _ in lines), default=0)
    for key, value in lines:
        log(f"  {key:<{width}}  {value}")
