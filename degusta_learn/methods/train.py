"""`degusta train`: build the configured trainer and run it (or its dry run).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from degusta_learn.errors import DegustaError
from degusta_learn.methods.registry import build_config, get_trainer

if TYPE_CHECKING:
    from degusta_learn.dryrun import DryRunReport

def run_train(path: str | Path | None, overrides: list[str] | None = None, dry_run: bool = False,
              log=print) -> Path | DryRunReport:
    """`degusta train`: build the configured trainer and run it; returns its output folder.

    With `dry_run`, the trainer kind's `dry_run` prints the model size, trainable parameters, the
    per-example budget against its limit, steps per epoch and a predicted memory, loading no weights and
    writing nothing; it refuses (DegustaError naming the key) a config whose examples cannot fit. Returns
    the `dryrun.DryRunReport` of the checks that FAIL on this machine (empty `failures`: none; the CLI
    then exits 3).
    """
    spec, cfg = build_config(path, overrides, "kind", get_trainer)
    if dry_run:
        from degusta_learn.dryrun import recording

        if spec.dry_run is None:
            raise DegustaError(f"kind: {cfg.kind!r} has no dry run")
        with recording() as report:  # every kind's FAILS line (dryrun.fails) lands here
            spec.dry_run(cfg, log=log)
        return report
    return spec.run(cfg)
