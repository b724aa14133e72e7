"""The machine a run trains on: ranks, seeding, CPU threads and kernels (AVX2 pinning, native bf16), the
precision a run really uses.
"""

from __future__ import annotations

import contextlib
import os
import sys

from degusta_learn.training.config import TrainerConfig


def global_rank() -> int:
    """This process's rank as the launchers announce it, before any process group exists: torchrun's RANK,
    SLURM_PROCID, or (Lightning's own children) NODE_RANK / LOCAL_RANK, where only 0 / 0 means 0."""
    env = os.environ
    for key in ("RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK"):
        if env.get(key, "").isdigit():
            return int(env[key])
    ranks = [int(env[k]) for k in ("NODE_RANK", "GROUP_RANK", "LOCAL_RANK") if env.get(k, "").isdigit()]
    return 0 if not any(ranks) else max(1, sum(ranks))


def is_global_zero(trainer=None) -> bool:
    """True in the one process that writes files (rank 0), before and after the Trainer exists."""
    if trainer is not None:
        return bool(trainer.is_global_zero)
    return global_rank() == 0


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch (and data-loader workers) quietly."""
    import lightning as L

    L.seed_everything(seed, workers=True, verbose=False)


@contextlib.contextmanager
def torch_threads(n: int | None):
    """torch's CPU threads set to `n` (None: unchanged) inside the block, and restored after it: a step that
    wants one thread must not leave every later step of the same process (quickstart's VLM fine-tuning) on one."""
    import torch

    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


AVX2_KERNELS = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}
"""The environment that caps torch's own kernels, oneDNN's and MKL's at AVX2 (each reads it at its first use)."""


def x86_with_avx2() -> bool:
    """Whether this CPU is an x86 one with AVX2: where `cpu_kernels: avx2` can cap the kernels at all."""
    import platform

    import torch

    return (platform.machine().lower() in ("x86_64", "amd64")
            and bool(getattr(torch.cpu, "_is_avx2_supported", lambda: False)()))


def pin_cpu_kernels(kernels: str) -> str:
    """Ask torch, oneDNN and MKL for `kernels` (`TrainerConfig.cpu_kernels`: "avx2" caps them at AVX2, "native"
    leaves them be) before this process's first CPU operation fixes them; variables already in the environment
    are kept. Returns the kernels torch runs ("AVX2", "AVX512", "DEFAULT", ...), with a note on stderr where "avx2"
    was asked for and is not what runs."""
    import platform

    import torch

    x86_avx2 = x86_with_avx2()
    if kernels == "avx2" and x86_avx2:
        for name, value in AVX2_KERNELS.items():
            os.environ.setdefault(name, value)
    running = torch.backends.cpu.get_cpu_capability()
    if kernels == "avx2" and running != "AVX2":
        asked = os.environ.get("ATEN_CPU_CAPABILITY", "")
        why = (f"this CPU ({platform.machine() or 'unknown'}) has no AVX2" if not x86_avx2 else
               f"ATEN_CPU_CAPABILITY={asked} in the environment asks for others" if asked.lower() != "avx2" else
               "this process ran torch before the run began, and the kernels are chosen at its first operation; "
               "start a fresh process, or set " + " ".join(f"{k}={v}" for k, v in AVX2_KERNELS.items())
               + " before Python starts")
        print(f"degusta: note: trainer.cpu_kernels avx2: torch runs its {running} kernels: {why}", file=sys.stderr)
    return running


def trains_on_gpu(cfg: TrainerConfig) -> bool:
    """Whether a run of `cfg` trains on a GPU on this machine (`accelerator: gpu`, or `auto` where CUDA is present)."""
    import torch

    return cfg.accelerator in ("gpu", "cuda") or (cfg.accelerator == "auto" and torch.cuda.is_available())


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX); elsewhere torch emulates it, ~60x slower
    than float32 (`run_precision`): autocast to bfloat16 on the CPU only where this is true."""
    import torch

    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


def effective_precision(cfg: TrainerConfig) -> str:
    """The precision a run of `cfg` uses on this machine: `cfg.precision`, except bfloat16 on a CPU that has no
    native bfloat16 (AVX512-BF16 or AMX), which runs it emulated: measured on an AVX2 EPYC, a 3x3 convolution 127x
    and a matmul 60x slower than float32. There it is 32-true (the same config stays fast where bf16 is native)."""
    if cfg.precision not in ("bf16-mixed", "bf16") or cfg.accelerator not in ("cpu", "auto") or trains_on_gpu(cfg):
        return cfg.precision
    return cfg.precision if cpu_has_native_bf16() else "32-true"


def run_precision(cfg: TrainerConfig) -> str:
    """The precision Lightning gets (`effective_precision`), with a note where it is not `cfg.precision`."""
    precision = effective_precision(cfg)
    if precision != cfg.precision:
        print(f"degusta: note: trainer.precision {cfg.precision}: this CPU has no native bfloat16 (AVX512-BF16/AMX) "
              f"and emulates it ~60x slower than float32; training in {precision}", file=sys.stderr)
    return precision
