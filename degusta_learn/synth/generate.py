"""`generate_dataset`: write an embedded SYNTHETIC dataset folder, atomically and deterministically.

Usage:
    degusta data generate naturalistic --out data/naturalistic [--seed 0] [--overwrite]
    degusta data generate simulated --out data/simulated
    degusta data generate naturalistic --legacy --out data/naturalistic_legacy   # the tables before plausibility
    degusta data generate relational --out data/relational [--set participants=400 --set noise=2]

    from degusta_learn.synth import generate_dataset
    generate_dataset("naturalistic", "data/naturalistic", seed=0)

The folder is built in a temporary sibling folder and swapped into place ((`files.folders`)), so a
reader never sees a half written dataset and a failed or killed run leaves the previous folder intact
(a killed run's hidden temp folder is removed by the next run). `--overwrite` replaces only a dataset
this tool generated (nothing foreign inside). The same seed gives byte-identical files.
Files: catalog.json, tables.json, arrangements.jsonl, ratings.jsonl (naturalistic, relational), meta.json,
latent_styles.json, and episodes.jsonl (simulated: its 72 experiments). docs/generators.md compares the families.
"""

from __future__ import annotations

import json
from pathlib import Path

from degusta_learn.config import check_seed
from degusta_learn.errors import DegustaError
from degusta_learn.files.folders import OutputKind, write_folder
from degusta_learn.scene import save_dataset, write_episodes
from degusta_learn.synth.naturalistic import naturalistic_with_styles
from degusta_learn.synth.relational import relational_options, relational_with_styles
from degusta_learn.synth.relational_style import write_relational_styles
from degusta_learn.synth.simulated import simulated_with_styles
from degusta_learn.synth.style import STYLES_FILE, write_styles

GENERATORS = ("naturalistic", "simulated", "relational")
GENERATOR_SIGNATURE = "degusta_learn.synth."
"""meta.json "generator" of every dataset this tool writes: `--overwrite` replaces only such a folder."""

DATASET_FILES = ("catalog.json", "tables.json", "arrangements.jsonl", "ratings.jsonl", "meta.json", STYLES_FILE,
                 "episodes.jsonl")


def _generated_by_us(folder: Path) -> bool:
    try:
        meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    generator = meta.get("generator") if isinstance(meta, dict) else None
    return isinstance(generator, str) and generator.startswith(GENERATOR_SIGNATURE)


DATASET = OutputKind("dataset", DATASET_FILES, check=_generated_by_us, merge=False)
"""A generated dataset folder: only its own files, and a meta.json naming a degusta generator."""


def generate_dataset(name: str, out: str | Path, seed: int = 0, overwrite: bool = False,
                     legacy: bool = False, options: dict | None = None) -> Path:
    """Write the `name` dataset ("naturalistic", "simulated" or "relational") to folder `out`; returns `out`.

    Every naturalistic table keeps the rules of plausible.py; `legacy` (naturalistic only) writes the tables
    this generator made before it kept them, byte for byte (about a fifth break one; docs/data.md).
    `options` (relational only; `--set KEY=VALUE`): the relational generator's options
    (relational.RelationalOptions), each checked, an unknown or impossible one named.

    Raises DegustaError for an unknown name, or when `out` exists and is not an empty folder (unless
    `overwrite`, which replaces it only once the new folder is complete, and only when it is a dataset
    this tool generated: its own files and nothing else, meta.json naming a degusta generator).
    Leftovers of a killed run (hidden `.NAME.*.tmp` folders beside `out`) are removed first.
    """
    if name not in GENERATORS:
        raise DegustaError(f"unknown dataset {name!r} (expected one of {', '.join(GENERATORS)})")
    if legacy and name != "naturalistic":
        raise DegustaError(f"legacy: only the naturalistic generator has legacy tables (not {name!r})")
    if options and name != "relational":
        key = next(iter(options)) if isinstance(options, dict) else "options"
        raise DegustaError(f"{key}: the {name} generator takes no options (only the relational "
                           "one: --set participants=N, noise=X, multi=P)")
    if name == "relational":
        options = relational_options(options)  # refused before anything is written
    seed = check_seed(seed)  # 0..2**32-1: meta.json then holds a seed `data validate` accepts
    out = Path(out)
    with write_folder(out, DATASET, replace=overwrite) as tmp:
        if name == "naturalistic":
            ds, styles = naturalistic_with_styles(seed, plausible=not legacy)
        elif name == "relational":
            ds, styles = relational_with_styles(seed, options)
        else:
            ds, styles, episodes = simulated_with_styles(seed)
            write_episodes(tmp / "episodes.jsonl", episodes)
        save_dataset(ds, tmp)
        (write_relational_styles if name == "relational" else write_styles)(tmp / STYLES_FILE, styles)
    return out
