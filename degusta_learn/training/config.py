"""The `trainer:` section of every train config (`TrainerConfig`) and its checks: accelerator, devices,
precision, strategy, loggers, cluster variables, each refused in one line naming the key.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from degusta_learn.config import bounded, check_choices, seed_field
from degusta_learn.errors import DegustaError, MachineMismatch
from degusta_learn.training.protocol import check_monitor

ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps", "tpu")


PRECISIONS = ("32-true", "32", "64-true", "64", "16-mixed", "16", "bf16-mixed", "bf16", "16-true", "bf16-true",
              "transformer-engine", "transformer-engine-float16")


MAX_DEVICES = 4096


LOGGERS = {"csv": None, "tensorboard": None, "wandb": "wandb", "mlflow": "mlflow"}
"""`trainer.loggers` choices -> the module an optional one needs (installed by the extra of the same name)."""


@dataclass
class TrainerConfig:
    """The `trainer:` section of every train config (Lightning settings + where the run is written)."""

    run_name: str = "run"
    """Run folder name: outputs go to `<run_dir>/<run_name>/`."""
    run_dir: str = "runs"
    """Parent folder of run folders."""
    resume: bool = True
    """Continue from `<run>/last.ckpt` when it exists (false: refuse to reuse a folder that has one)."""
    seed: int = seed_field()
    """Seed for Python, numpy, torch and data-loader workers."""
    max_epochs: int = bounded(10, 1, 1_000_000, special=(-1,))
    """Stop after this many epochs (-1: no epoch limit, use max_steps)."""
    max_steps: int = bounded(-1, 1, 1_000_000_000, special=(-1,))
    """Stop after this many optimizer steps (-1: no step limit)."""
    accelerator: str = "auto"
    """"cpu", "gpu", "auto" (GPU when present)."""
    devices: Any = "auto"
    """Devices per node: a number (GPUs, or CPU processes: at most os.cpu_count()), a list of GPU indices, or "auto"."""
    num_nodes: int = bounded(1, 1, 100_000)
    """Machines of a multi-node run (launched by torchrun or SLURM `srun`; see docs/finetune.md)."""
    strategy: str = "auto"
    """Lightning strategy: "auto", "ddp", "ddp_fork", "fsdp", ... (multi-GPU needs no code change; the
    "ddp_spawn" family is refused: it pickles the run)."""
    precision: str = "32-true"
    """"32-true", "bf16-mixed" (GPU), "16-mixed" (GPU)."""
    cpu_kernels: Literal["native", "avx2"] = "native"
    """Which x86 kernels torch, oneDNN and MKL compute with on the CPU: "native", the widest this CPU has (AVX-512
    where present), or "avx2", capped at AVX2 (what most CPUs run). Rounding differs between them and takes a run
    elsewhere: the pretraining recipe's builds met the fine-tuned route's bars with AVX2 kernels and failed them with
    AVX-512 ones, so its config asks for avx2. Kernels are chosen once per process, at
    torch's first CPU operation: `degusta train` asks before it; a process that ran torch earlier keeps its kernels,
    with a note. No effect off x86 or on a CPU without AVX2."""
    accumulate_grad_batches: int = bounded(1, 1, 10_000)
    """Gradient accumulation: effective batch = batch_size * this * devices * num_nodes."""
    gradient_clip_val: float | None = bounded(1.0, 0.0)
    """Clip the gradient norm to this (null: no clipping)."""
    log_every_n_steps: int = bounded(10, 1, 1_000_000_000)
    """How often training losses are logged."""
    val_check_interval: int | float = 1.0
    """Validate every this fraction of an epoch (float) or number of batches (int); the step that reaches
    `max_steps` validates too, wherever it falls."""
    check_val_every_n_epoch: int = bounded(1, 1, 1_000_000)
    """Validate every this many epochs."""
    monitor: str | None = "val/rmsd"
    """Validation metric that picks best.ckpt and that early stopping watches (null: only last.ckpt); a test metric
    (`test/...`) is refused: choices are made on the validation participants (training/protocol.py)."""
    monitor_mode: Literal["min", "max"] = "min"
    """"min" or "max" for `monitor`."""
    early_stopping_patience: int | None = bounded(None, 1, 1_000_000)
    """Stop after this many validations in a row without a better `monitor` (null: never stop early)."""
    early_stopping_min_delta: float = bounded(0.0, 0.0)
    """How much `monitor` must improve to count as better for early stopping (0: any improvement)."""
    progress_bar: bool = True
    """Show Lightning's progress bar."""
    num_sanity_val_steps: int = bounded(0, 0, 1_000_000, special=(-1,))
    """Validation batches run before training as a smoke check (0: none)."""
    loggers: list[str] = field(default_factory=lambda: ["csv", "tensorboard"])
    """Where metrics go, any of csv (`<run>/csv/`), tensorboard (`<run>/tb/`), wandb, mlflow (optional packages:
    `pip install 'degusta_learn[tracking]'`); see `tracking_offline`."""
    tracking_offline: bool = True
    """wandb / mlflow write only into the run folder: W&B offline mode (`<run>/wandb/`, `wandb sync` uploads it
    later), an MLflow file store `file:<run>/mlruns` (`mlflow ui --backend-store-uri <run>/mlruns`). false:
    W&B logs to its server (`wandb login`), MLflow to MLFLOW_TRACKING_URI (required)."""

    def __post_init__(self):
        check_choices(self, "trainer")
        if (not self.run_name or any(c in self.run_name for c in "/\\\0") or self.run_name in (".", "..")
                or len(self.run_name) > 200):
            raise DegustaError(f"trainer.run_name: expected a plain folder name, got {self.run_name[:80]!r}")
        if not self.run_dir or "\0" in self.run_dir:
            raise DegustaError(f"trainer.run_dir: expected a folder path, got {self.run_dir[:80]!r}")
        if self.max_epochs == -1 and self.max_steps == -1:
            raise DegustaError("trainer.max_epochs / trainer.max_steps: set at least one of them (not both -1)")
        if isinstance(self.num_nodes, bool) or not isinstance(self.num_nodes, int) or self.num_nodes < 1:
            raise DegustaError(f"trainer.num_nodes: expected a number of machines >= 1, got {self.num_nodes!r}")
        if self.accumulate_grad_batches < 1:
            raise DegustaError(f"trainer.accumulate_grad_batches: expected >= 1, got {self.accumulate_grad_batches}")
        if self.accelerator not in ACCELERATORS:
            raise DegustaError(f"trainer.accelerator: expected one of {', '.join(ACCELERATORS)}, "
                               f"got {self.accelerator[:40]!r}")
        if self.precision not in PRECISIONS:
            raise DegustaError(f"trainer.precision: expected one of {', '.join(PRECISIONS[:10])}, "
                               f"got {self.precision[:40]!r}")
        self.devices = _check_devices(self.devices)
        vci = self.val_check_interval
        if isinstance(vci, float) and not 0.0 < vci <= 1.0:
            raise DegustaError(f"trainer.val_check_interval: a fraction of an epoch must be in (0, 1], got {vci} "
                               f"(or give a whole number of batches)")
        if isinstance(vci, int) and not 1 <= vci <= 1_000_000_000:
            raise DegustaError(f"trainer.val_check_interval: expected a number of batches >= 1, got {vci}")
        if self.monitor is not None and not self.monitor.strip():
            raise DegustaError("trainer.monitor: expected a logged metric name (or null), got ''")
        check_monitor(self.monitor)
        if self.early_stopping_patience is not None and self.monitor is None:
            raise DegustaError("trainer.early_stopping_patience: early stopping watches trainer.monitor, which is "
                               "null; name a validation metric in trainer.monitor or set the patience to null")
        if not self.strategy or not isinstance(self.strategy, str):
            raise DegustaError(f"trainer.strategy: expected a Lightning strategy name, got {self.strategy!r}")
        self.loggers = _check_logger_names(self.loggers)

    @property
    def path(self) -> Path:
        """The run folder `<run_dir>/<run_name>`."""
        return Path(self.run_dir) / self.run_name


def _check_devices(devices: Any) -> Any:
    """`devices` as Lightning takes it: "auto", a count >= 1 (-1: all), or a list of device indices."""
    bad = DegustaError(f"trainer.devices: expected \"auto\", a number of devices (1..{MAX_DEVICES}, -1: all) "
                       f"or a list of device indices, got {str(devices)[:40]!r}")
    if isinstance(devices, str):
        text = devices.strip()
        if text == "auto":
            return "auto"
        try:
            parts = [int(p) for p in text.split(",") if p.strip()]
        except ValueError:
            raise bad from None
        if not parts:
            raise bad
        devices = parts[0] if len(parts) == 1 and "," not in text else parts
    if isinstance(devices, bool):
        raise bad
    if isinstance(devices, int):
        if devices == -1 or 1 <= devices <= MAX_DEVICES:
            return devices
        raise bad
    if isinstance(devices, (list, tuple)) and devices and len(devices) <= MAX_DEVICES and all(
            isinstance(d, int) and not isinstance(d, bool) and 0 <= d < MAX_DEVICES for d in devices) \
            and len(set(devices)) == len(devices):
        return list(devices)
    raise bad


def check_trainer(cfg: TrainerConfig, monitors: Iterable[str] | None = None) -> None:
    """Check what only this machine and the module can tell: the accelerator is present, enough devices,
    a known strategy, a precision this accelerator runs, and (given the keys the module logs) the monitor.

    Raises `MachineMismatch` (a `DegustaError`) for what this machine lacks (a GPU, cores, a logger package, a
    launcher) and `DegustaError` for a config mistake (an unknown strategy or monitor), each naming the
    `trainer.` key; writes nothing.
    """
    import torch

    acc = cfg.accelerator
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if acc in ("gpu", "cuda") and gpus == 0:
        raise MachineMismatch(f"trainer.accelerator: {acc!r} but no CUDA GPU is available on this machine; "
                           f"use trainer.accelerator=cpu (or auto)")
    if acc == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise MachineMismatch("trainer.accelerator: 'mps' but Apple MPS is not available here; use cpu (or auto)")
    if acc == "tpu":
        try:
            import torch_xla  # noqa: F401
        except ImportError:
            raise MachineMismatch("trainer.accelerator: 'tpu' but no TPU runtime (torch_xla) is installed; "
                               "use cpu (or auto)") from None
    on_gpu = acc in ("gpu", "cuda") or (acc == "auto" and gpus > 0)
    if on_gpu:
        wanted = cfg.devices if isinstance(cfg.devices, int) else len(cfg.devices) if isinstance(cfg.devices, list) else 0
        top = max(cfg.devices) + 1 if isinstance(cfg.devices, list) else wanted
        if wanted > gpus or top > gpus:
            raise MachineMismatch(f"trainer.devices: {cfg.devices} asks for more GPUs than the {gpus} available here")
    else:
        _check_cpu_devices(cfg)
    if cfg.num_nodes > 1 or cfg.strategy != "auto" or world_size(cfg) > 1:
        _check_cluster(cfg)
    if cfg.precision.startswith("transformer-engine") and not on_gpu:
        raise MachineMismatch(f"trainer.precision: {cfg.precision!r} needs a GPU; use 32-true or bf16-mixed on CPU")
    if cfg.precision in ("16-true", "16") and not on_gpu:
        raise MachineMismatch(f"trainer.precision: {cfg.precision!r} (float16) needs a GPU; use 32-true or bf16-mixed on CPU")
    if cfg.strategy != "auto":
        from lightning.pytorch.strategies import StrategyRegistry

        names = StrategyRegistry.available_strategies()
        if cfg.strategy not in names:
            raise DegustaError(f"trainer.strategy: unknown strategy {cfg.strategy[:40]!r} (use auto, ddp, ddp_fork, "
                               f"fsdp, deepspeed, ...)")
        if cfg.strategy.startswith("ddp_spawn"):  # was a PicklingError traceback from inside Lightning
            raise DegustaError(f"trainer.strategy: {cfg.strategy!r} pickles the whole run into new processes, which "
                               f"this harness does not support; use ddp (ranks started from the command line) "
                               f"or ddp_fork")
        if (cfg.strategy.startswith("fsdp") or cfg.strategy.startswith("deepspeed")) and not on_gpu:
            raise MachineMismatch(f"trainer.strategy: {cfg.strategy!r} needs a GPU accelerator; use auto or ddp on CPU")
    _check_logger_packages(cfg)
    if monitors is not None and cfg.monitor is not None:
        known = sorted(set(monitors))
        if cfg.monitor not in known:
            raise DegustaError(f"trainer.monitor: {cfg.monitor[:60]!r} is never logged by this trainer "
                               f"(logged: {', '.join(known)}; or null for last.ckpt only)")


def _check_logger_names(names: Any) -> list[str]:
    """`trainer.loggers` as a list of distinct known names (a single name is taken as a list of one)."""
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise DegustaError(f"trainer.loggers: expected a list of {', '.join(LOGGERS)}, got {str(names)[:60]!r}")
    for n in names:
        if n not in LOGGERS:
            raise DegustaError(f"trainer.loggers: unknown logger {n[:40]!r} (choose from {', '.join(LOGGERS)})")
    if len(set(names)) != len(names):
        raise DegustaError(f"trainer.loggers: {list(names)} names a logger twice")
    return list(names)


def _check_logger_packages(cfg: TrainerConfig) -> None:
    """An optional logger's package is importable here, or one line with the pip command; MLflow online needs
    MLFLOW_TRACKING_URI (Lightning's default would be a `./mlruns` folder wherever the command runs)."""
    import importlib

    for name in cfg.loggers:
        module = LOGGERS[name]
        if module is None:
            continue
        try:
            importlib.import_module(module)
        except ImportError:
            raise MachineMismatch(f"trainer.loggers: {name!r} needs the {module} package, not installed here: "
                               f"pip install 'degusta_learn[{name}]' (or remove {name!r} from trainer.loggers)") from None
    if "mlflow" in cfg.loggers and not cfg.tracking_offline and not os.environ.get("MLFLOW_TRACKING_URI"):
        raise MachineMismatch("trainer.tracking_offline: false sends MLflow runs to MLFLOW_TRACKING_URI, which is not "
                           "set; set it (e.g. http://host:5000) or keep tracking_offline true (<run>/mlruns)")


def _check_cpu_devices(cfg: TrainerConfig) -> None:
    """On CPU every device is a process holding a full model copy: a count >= 1, at most the cores here.

    Lightning would start 64 processes for `devices: 64` on a 2-core machine (each one loads the model and
    they time-slice the cores: slower than one process, and memory x 64), so more processes than
    `os.cpu_count()` are refused; -1 ("all") and lists of indices mean GPUs and are refused on CPU too.
    """
    cores = os.cpu_count() or 1
    d = cfg.devices
    if d == "auto":
        return
    if isinstance(d, list) or d == -1:
        raise MachineMismatch(f"trainer.devices: {d} selects GPUs, but this run is on the CPU; give a number of "
                           f"CPU processes (1..{cores}) or use trainer.accelerator=gpu on a GPU machine")
    if d > cores:
        raise MachineMismatch(f"trainer.devices: {d} CPU processes asked for, but this machine has {cores} cores "
                           f"(each process holds a whole model and needs a core); use at most {cores}")


def world_size(cfg: TrainerConfig) -> int:
    """Processes of the run: devices per node x num_nodes ("auto": the visible GPUs, else 1)."""
    d = cfg.devices
    if isinstance(d, list):
        n = len(d)
    elif d in ("auto", -1):
        import torch

        gpu = cfg.accelerator in ("gpu", "cuda", "auto") and torch.cuda.is_available()
        n = torch.cuda.device_count() if gpu else 1
    else:
        n = int(d)
    return n * cfg.num_nodes


def _check_cluster(cfg: TrainerConfig) -> None:
    """A multi-node run needs a launcher that started the other machines' processes (else it would wait for
    them forever); under torchrun / SLURM the world it made must be devices x num_nodes."""
    env = os.environ
    launched = env.get("WORLD_SIZE", "")
    if cfg.num_nodes > 1 and not launched.isdigit() and not env.get("SLURM_NTASKS") and not env.get("MASTER_ADDR"):
        raise MachineMismatch(f"trainer.num_nodes: {cfg.num_nodes} machines, but this process was not started by a "
                           "multi-node launcher (torchrun --nnodes / SLURM srun: no WORLD_SIZE, SLURM_NTASKS or "
                           "MASTER_ADDR); it would wait for the other machines forever. See docs/finetune.md, "
                           "'Multi-GPU and multi-node'")
    want = world_size(cfg)
    if launched.isdigit() and int(launched) > 1 and int(launched) != want:  # torchrun (SLURM: Lightning checks)
        raise MachineMismatch(f"trainer.devices / trainer.num_nodes: the launcher started {launched} processes "
                           f"(WORLD_SIZE) but devices x num_nodes = {want}; make them agree (devices = processes "
                           "per node, num_nodes = machines)")


def trainer_key_in(message: str) -> str | None:
    """The TrainerConfig field a Lightning error message names (as `field` or field=), if any."""
    for f in dataclasses.fields(TrainerConfig):
        if f"`{f.name}`" in message or f"{f.name}=" in message:
            return f.name
    return None
