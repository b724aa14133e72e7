"""`generate_dataset`: write an embedded SYNTHETIC dataset folder, atomically and deterministically.

Usage:
    degusta data generate naturalistic --out data/naturalistic [--seed 0] [--overwrite]
    degusta data generate simulated --out data/simulated

    from degusta_learn.synth import generate_dataset
    generate_dataset("naturalistic", "data/naturalistic", seed=0)

The folder is built in a temporary sibling folder and renamed into place, so a reader never sees a half
written dataset and a failed run leaves nothing behind. The same seed gives byte-identical files.
Files: catalog.json, tables.json, arrangements.jsonl, ratings.jsonl (naturalistic), meta.json,
latent_styles.json, and episodes.jsonl (simulated: its 72 experiments).
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.scene import save_dataset, write_episodes
from degusta_learn.synth.naturalistic import naturalistic_with_styles
from degusta_learn.synth.simulated import simulated_with_styles
from degusta_learn.synth.style import STYLES_FILE, write_styles

GENERATORS = ("naturalistic", "simulated")


def generate_dataset(name: str, out: str | Path, seed: int = 0, overwrite: bool = False) -> Path:
    """Write the `name` dataset ("naturalistic" or "simulated") to folder `out`; returns `out`.

    Raises DegustaError for an unknown name, or when `out` exists and is not an empty folder (unless
    `overwrite`, which replaces it only once the new folder is complete).
    """
    if name not in GENERATORS:
        raise DegustaError(f"unknown dataset {name!r} (expected one of {', '.join(GENERATORS)})")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DegustaError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise DegustaError(f"{out}: folder exists and is not empty (pass --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; a dataset folder is an ordinary folder
    try:
        if name == "naturalistic":
            ds, styles = naturalistic_with_styles(seed)
        else:
            ds, styles, episodes = simulated_with_styles(seed)
            write_episodes(tmp / "episodes.jsonl", episodes)
        save_dataset(ds, tmp)
        write_styles(tmp / STYLES_FILE, styles)
        _replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _replace(tmp: Path, out: Path) -> None:
    """Move the finished folder `tmp` to `out`, replacing an existing `out` only after the move succeeds."""
    if not out.exists():
        tmp.rename(out)
        return
    old = out.with_name(f".{out.name}.old-{tmp.name}")
    out.rename(old)
    try:
        tmp.rename(out)
    except BaseException:
        with contextlib.suppress(OSError):
            old.rename(out)
        raise
    shutil.rmtree(old, ignore_errors=True)
