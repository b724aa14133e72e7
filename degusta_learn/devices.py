"""The torch device a config names (`backend.device`, predict's `device`), checked before anything loads.

`resolve_device("auto")` is `cuda` where a GPU is visible, else `cpu`; any other value must be a device torch knows
and this machine has (`cpu`, `cuda`, `cuda:N` with N below the visible count, `mps` on a Mac that has it), or the
run stops with one line naming the config key.
"""

from __future__ import annotations

from degusta_learn.errors import DegustaError

CHOICES = "'auto', 'cpu', 'cuda' or 'cuda:N'"


def resolve_device(device: str = "auto", key: str = "device") -> str:
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise DegustaError(f"{key}: {device!r} is not a device; use {CHOICES}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise DegustaError(f"{key}: {device!r} requested but no CUDA device is visible (use 'cpu' or 'auto')")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise DegustaError(f"{key}: {device!r} requested but {torch.cuda.device_count()} CUDA device(s) are "
                               f"visible (cuda:0 to cuda:{torch.cuda.device_count() - 1})")
    elif dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise DegustaError(f"{key}: 'mps' requested but this machine has no Apple GPU; use {CHOICES}")
    elif dev.type != "cpu":
        raise DegustaError(f"{key}: {device!r}: this toolkit runs on {CHOICES}")
    return device
