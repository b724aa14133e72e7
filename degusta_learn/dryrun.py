"""`degusta train --dry-run`: what a run would cost, without loading weights or writing anything.

The report lines every trainer kind shares (steps per epoch, the trainer check on this machine) and the
simple memory model (`estimate_memory`, `transformer_activations`): an ESTIMATE, not checked against a GPU.
Each kind's `dry_run` (methods.TrainerSpec) adds its own lines (model size, tokens or slots per example).

A check that FAILS on this machine (`fails`: a GPU config on a CPU login node) is a report line, and is also
recorded in the `DryRunReport` of the `recording()` block around the dry run: `methods.run_train` returns that
report, so `degusta train --dry-run` exits 3 when a check FAILS without any kind returning anything or any line
being parsed.

Example:
    lines = [("model", "...")] + dry_run_trainer_lines(cfg.trainer, monitors, n_examples=200, batch_size=4)
    print_dry_run("dry run of kind finetune", lines)

    with recording() as report:   # what methods.run_train does around a kind's dry_run
        spec.dry_run(cfg)
    report.failures               # [("trainer check", "trainer.accelerator: 'gpu' but no CUDA GPU ...")]
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

from degusta_learn.errors import MachineMismatch
from degusta_learn.training import TrainerConfig, check_trainer, effective_precision, world_size

GiB = 1024**3
ADAMW_STATE_BYTES = 8
"""AdamW keeps two fp32 moments (exp_avg, exp_avg_sq) per trainable parameter."""
RUNTIME_CPU_BYTES = int(1.0 * GiB)
"""A CPU training process's own memory before the model: Python, torch, transformers, peft, Lightning, the
processor and the dataset (measured RSS at the first training batch minus the fp32 weights, SmolVLM
replicas: see benchmarks/RESULTS.md)."""
CPU_ACTIVATION_FACTOR = 1.75
"""On the CPU the peak RSS exceeds the live saved activations (which `transformer_activations` counts within
2%, checked with saved-tensor hooks on the SmolVLM-256M replica) by the backward pass's transient gradients
and glibc heap fragmentation (freed tensors below the mmap threshold keep their pages): x1.75, fitted on the
SmolVLM-256M replica's measured peak and checked on SmolVLM-500M's (benchmarks/RESULTS.md). Not applied on a
GPU, whose caching allocator reuses freed blocks (its overhead is not measured here). With gradient
checkpointing, glibc's retention is larger (the default-allocator RSS was 24-45% above the prediction on the
SmolVLM-256M and Qwen2-VL-2B replicas); with `MALLOC_MMAP_THRESHOLD_=1048576` (large blocks returned to the
OS at once) the measured peaks were within 3% of it."""
RUNTIME_GPU_BYTES = int(0.75 * GiB)
"""CUDA context, cuBLAS/cuDNN workspaces and kernels on the device (typical 0.5-1 GiB; not measured here)."""


@dataclass
class MemoryEstimate:
    """A predicted peak memory per device, in bytes, by parts (see `estimate_memory`): an ESTIMATE."""

    weights: int
    gradients: int
    optimizer: int
    activations: int
    note: str = ""
    runtime: int = 0
    """The process's own memory: CUDA context and kernels on a GPU, the Python/torch/transformers/Lightning
    process (imports, processor, dataset) on the CPU."""

    @property
    def total(self) -> int:
        return self.weights + self.gradients + self.optimizer + self.activations + self.runtime

    def describe(self) -> str:
        parts = (f"weights {_size(self.weights)} + gradients {_size(self.gradients)} + AdamW states "
                 f"{_size(self.optimizer)} + activations {_size(self.activations)}"
                 + (f" + runtime {_size(self.runtime)}" if self.runtime else ""))
        return f"~{_size(self.total)} per device (ESTIMATE of the memory model: {parts}{'; ' + self.note if self.note else ''})"


def _size(n: float) -> str:
    for unit, scale in (("GiB", GiB), ("MiB", 1024**2), ("KiB", 1024)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{int(n)} B"


def estimate_memory(total_params: int, trainable_params: int, param_bytes: float, trainable_bytes: float = 4,
                    activation_bytes: float = 0, processes: int = 1, note: str = "",
                    runtime_bytes: float = 0) -> MemoryEstimate:
    """The memory model of `degusta train --dry-run`: checked against the measured peak RSS of full-size CPU
    replicas of the GPU fine-tuning configs (fp32; benchmarks/RESULTS.md "Full-size replicas"), not on a GPU.

    peak ~ frozen params x `param_bytes` + trainable params x `trainable_bytes` (the weights)
         + trainable params x `trainable_bytes` (their gradients; x2 under DDP: the all-reduce buckets)
         + trainable params x 8 (AdamW's two fp32 moments)
         + `activation_bytes` (the caller's activation term for one batch, see `transformer_activations`)
         + `runtime_bytes` (CUDA context and kernels, or the CPU process's own memory: see RUNTIME_*).
    Not included: allocator fragmentation, data-loader worker processes (each its own process).
    """
    frozen = max(0, total_params - trainable_params)
    grads = trainable_params * trainable_bytes * (2 if processes > 1 else 1)
    return MemoryEstimate(weights=int(frozen * param_bytes + trainable_params * trainable_bytes), gradients=int(grads),
                          optimizer=int(trainable_params * ADAMW_STATE_BYTES), activations=int(activation_bytes),
                          note=note, runtime=int(runtime_bytes))


LORA_VALUES_PER_TOKEN_LAYER = (18.0, 4.33)
"""Values a LLaMA/Qwen2 decoder layer keeps for backward per token when its 7 projections carry LoRA adapters
with dropout and its base weights are frozen: about 18 x hidden + 4.33 x intermediate (+ 2 x kv width).
Counted with torch's saved-tensor hooks (parameters excluded) on SmolLM2-135M / -360M / Qwen2-1.5B-sized
layers at r=16, dropout 0.05: 17,403 / 28,929 / 66,686 values, which this fits within 1.5%. The two RMSNorms
(input, normalised output), every adapter's dropped-out input and its bool mask, SDPA's q, k, v, output and
log-sum-exp, and the SwiGLU's gate, up and product are what is kept; the frozen base Linears keep nothing."""


def transformer_activations(tokens: int, hidden: int, intermediate: int, layers: int, value_bytes: float,
                            checkpointing: bool = False, lora: bool = False, kv_width: int = 0) -> float:
    """Bytes a decoder stack keeps for backward over `tokens` tokens (batch x sequence).

    Plain (full training, the learned model): about 6 x hidden + 4 x intermediate values per layer and token
    (norm, QKV and output-projection inputs, attention output; gate, up, activation and down-projection inputs;
    fused attention: no T^2 scores). `lora` (frozen base, LoRA with dropout on all 7 projections): the
    measured LORA_VALUES_PER_TOKEN_LAYER instead. With gradient checkpointing only each layer's input
    (hidden values) is kept, plus one layer's full set while it is recomputed; without it, one extra
    layer's set is counted for the backward pass's transient gradients.
    """
    if lora:
        a, b = LORA_VALUES_PER_TOKEN_LAYER
        per_layer = (a * hidden + b * intermediate + 2 * kv_width) * tokens * value_bytes
    else:
        per_layer = (6 * hidden + 4 * intermediate) * tokens * value_bytes
    if checkpointing:
        return hidden * tokens * value_bytes * layers + per_layer
    return per_layer * (layers + (1 if lora else 0))


def steps_per_epoch(n_examples: int, batch_size: int, cfg: TrainerConfig) -> tuple[int, int]:
    """(batches per process per epoch, optimizer steps per epoch) for `n_examples` under `cfg`'s processes."""
    per_process = math.ceil(n_examples / world_size(cfg))  # DistributedSampler pads to equal shares
    batches = math.ceil(per_process / batch_size)
    return batches, math.ceil(batches / cfg.accumulate_grad_batches)


@dataclass
class DryRunReport:
    """What a dry run found that this machine cannot run: (report label, reason) of each check that FAILS."""

    failures: list[tuple[str, str]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures

    def failure_summary(self) -> str:
        """One line naming each failing check ("" when none fails)."""
        return "; ".join(f"{label} FAILS on this machine: {' '.join(reason.split())}" for label, reason in self.failures)


_REPORT: ContextVar[DryRunReport | None] = ContextVar("degusta_dry_run_report", default=None)


@contextmanager
def recording() -> Iterator[DryRunReport]:
    """Collect the checks that `fails` reports inside this block (nested blocks each get their own)."""
    report = DryRunReport()
    token = _REPORT.set(report)
    try:
        yield report
    finally:
        _REPORT.reset(token)


def fails(label: str, reason: str) -> tuple[str, str]:
    """The report line of a check that FAILS on this machine; recorded in the current `recording()` block."""
    report = _REPORT.get()
    if report is not None:
        report.failures.append((label, reason))
    return label, f"FAILS on this machine: {reason}"


def dry_run_trainer_lines(cfg: TrainerConfig, monitors: Iterable[str] | None, n_examples: int,
                          batch_size: int) -> list[tuple[str, str]]:
    """The report lines every kind shares: steps per epoch, the run's length, the trainer check on this machine
    (what this machine lacks is reported as FAILS, see `fails`; a config mistake, such as an unknown monitor,
    raises)."""
    batches, steps = steps_per_epoch(n_examples, batch_size, cfg)
    world = world_size(cfg)
    per = f"{n_examples} examples / ({batch_size} per batch x {world} process{'es' if world > 1 else ''})"
    acc = f", accumulating {cfg.accumulate_grad_batches}" if cfg.accumulate_grad_batches > 1 else ""
    limit = [f"max_steps {cfg.max_steps}" if cfg.max_steps > 0 else "",
             f"max_epochs {cfg.max_epochs}" if cfg.max_epochs > 0 else ""]
    lines = [("steps per epoch", f"{steps} ({per}{acc}); stops at {' or '.join(x for x in limit if x)}")]
    try:
        check_trainer(cfg, monitors)
        precision = effective_precision(cfg)
        if precision != cfg.precision:
            precision = f"{cfg.precision}, run as {precision} here: this CPU has no native bfloat16"
        lines.append(("trainer check", f"ok on this machine ({cfg.accelerator}, devices {cfg.devices}, "
                                       f"num_nodes {cfg.num_nodes}, strategy {cfg.strategy}, {precision})"))
    except MachineMismatch as e:  # a GPU config checked on a login node: say so, the rest of the report holds
        lines.append(fails("trainer check", str(e)))
    return lines


def print_dry_run(title: str, lines: list[tuple[str, str]], log=print) -> None:
    """`title` then aligned `label  value` lines."""
    log(title)
    width = max((len(k) for k, _ in lines), default=0)
    for key, value in lines:
        log(f"  {key:<{width}}  {value}")
