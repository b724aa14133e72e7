"""Checkpoints written atomically inside the run folder (a hidden temp file, fsync, `os.replace`), and the
`last.ckpt` callback; a failed write is one line naming the file, the previous checkpoint stays whole.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any

from degusta_learn.files.write_errors import writing
from degusta_learn.training.run_dir import LAST, TMP_PREFIX, resume_note


def atomic_checkpoint_io():
    """A TorchCheckpointIO whose saves go to a temp file in the checkpoint's own folder, then `os.replace`.

    Lightning's default writes through an fsspec transaction whose temp file may sit on another filesystem
    (then the commit *copies* over last.ckpt, and a kill mid-copy leaves a truncated file); a rename inside
    one folder is atomic: readers see the old complete file or the new complete one, never a part.
    """
    import torch
    from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

    class AtomicCheckpointIO(TorchCheckpointIO):
        def save_checkpoint(self, checkpoint: dict, path, storage_options: Any = None) -> None:
            if storage_options is not None:
                raise TypeError("AtomicCheckpointIO takes no storage_options")
            path = Path(path)
            # a full disk, a file-size limit, a quota: one line naming the file; the previous one stays whole
            with writing(path, "checkpoint", after=resume_note(path.parent / LAST, path)):
                path.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f"{TMP_PREFIX}{path.name}.")
                try:
                    with os.fdopen(fd, "wb") as f:
                        torch.save(checkpoint, f)
                        f.flush()
                        os.fsync(f.fileno())
                    os.replace(tmp, path)
                except BaseException:
                    with contextlib.suppress(OSError):
                        os.unlink(tmp)
                    raise
            with contextlib.suppress(OSError):  # make the rename itself durable
                dfd = os.open(path.parent, os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)

    return AtomicCheckpointIO()


def last_checkpoint_class(base: type) -> type:
    """Lightning's ModelCheckpoint for last.ckpt, saving after every validation when `val_check_interval` is the
    whole number 1 (validate after every batch) too: Lightning compares it with 1.0 ("once an epoch") and would
    save only at the epoch's end, so a run stopped mid-epoch resumed from the epoch before. Same state key as a
    plain ModelCheckpoint (runs written before resume as they did)."""

    class LastCheckpoint(base):
        def _should_save_on_train_epoch_end(self, trainer) -> bool:
            vci, n = trainer.val_check_interval, trainer.num_val_batches
            validates = (sum(n) if isinstance(n, list) else n) > 0  # no validation: save at the epoch's end
            if (self._save_on_train_epoch_end is None and type(vci) is int and vci == 1 and validates
                    and trainer.check_val_every_n_epoch == 1):
                return False
            return super()._should_save_on_train_epoch_end(trainer)

    LastCheckpoint.__name__ = LastCheckpoint.__qualname__ = base.__name__
    return LastCheckpoint
