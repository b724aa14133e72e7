"""A study of `degusta collect`: its config (YAML) and the dataset folder it collects into.

Usage:
    degusta collect --dataset studies/lab1 --new                 # a new folder: the default catalog and tables
    degusta collect --dataset studies/lab1 --config study.yaml   # tables, minimum objects, jitter, instructions

`StudyConfig` is the researcher's controls (the shipped `collect_study.yaml` has every key with its meaning);
`Study` is a config checked against its dataset folder: the catalog and tables the participants set, the tables
they are shown, and the arrangements already collected (a study may run over several days).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from degusta_learn.config.fields import bounded, seed_field
from degusta_learn.config.loading import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_json, read_jsonl
from degusta_learn.scene.catalog import Catalog, default_catalog
from degusta_learn.scene.dataset import DEFAULT_MIN_OBJECTS, check_arrangements, check_ratings, has_file, load_parts
from degusta_learn.scene.tables import Table, default_tables
from degusta_learn.scene.types import Arrangement, Rating

MAX_OBJECTS = 64
"""Objects a participant may place on one table (the planner's and the prompts' limit too)."""
MAX_INSTRUCTIONS = 20_000
"""Characters of the instructions text."""

DEFAULT_INSTRUCTIONS = """\
Thank you for taking part. You will set several tables, one at a time, the way you like a table set.

For each table: choose a kind of object (cup, fork, knife, plate, spoon), then one of those objects, then click on the \
table where it should go (or drag it there). Drag an object to move it; select it to turn it or remove it. Place at \
least {min_objects} objects, then press Submit.

After each table you will be asked how much you agree that a table is set as you prefer it: your own, then a copy \
that has been moved a little, which you may then put right and rate once more."""


@dataclass
class JitterConfig:
    """The jittered copy of the self-evaluation: drawn as the simulated study draws it (synth/ratings.py)."""

    shift: float = bounded(0.15, 0.0, 1.0)
    """Translation of the whole scene at magnitude t = 1 (normalized units); t is drawn from U[0, 1] per table."""
    turn: float = bounded(30.0, 0.0, 180.0)
    """Turn of the whole scene about its centroid at t = 1 (degrees, random sign); objects turn with it."""


@dataclass
class StudyConfig:
    """A study's controls: which tables, how many, the minimum objects, the self-evaluation, the instructions."""

    kind: Literal["collect"] = "collect"
    """Config kind (collect)."""
    title: str = "Set the table"
    """The page's title."""
    tables_per_participant: int = bounded(5, 1, 1000)
    """Tables each participant sets, each a different table (the paper: 5)."""
    tables: list[int] | None = None
    """Table ids participants are shown (null: every table of the dataset)."""
    table_order: Literal["random", "fixed"] = "random"
    """random: each participant gets their own order of the tables (the paper); fixed: the order of `tables`."""
    min_objects: int = bounded(DEFAULT_MIN_OBJECTS, 1, MAX_OBJECTS)
    """Objects a table needs before it can be submitted (the paper: 3)."""
    self_evaluation: bool = True
    """Rate the scene, rate a jittered copy, correct it and rate the correction, after every table (the paper)."""
    jitter: JitterConfig = field(default_factory=JitterConfig)
    """The jittered copy (self_evaluation)."""
    participant_ids: Literal["assign", "enter"] = "assign"
    """assign: the server numbers participants (c001, c002, ...); enter: the participant (or the researcher) types
    an id at the start."""
    instructions: str = DEFAULT_INSTRUCTIONS
    """The text shown at the start (plain text; blank lines separate paragraphs; {min_objects} is filled in)."""
    instructions_file: str | None = None
    """A text file with the instructions instead (relative to the config file's folder or absolute)."""
    seed: int = seed_field()
    """Seeds the table orders and the jitter draws (with the participant id: reproducible per participant)."""


def load_study_config(path: str | Path | None = None, overrides: list[str] | None = None) -> StudyConfig:
    """The study config from a YAML file (or the defaults), with `--set KEY=VALUE` overrides, checked."""
    cfg = load_config(StudyConfig, path, overrides)
    if cfg.instructions_file is not None:
        file = Path(cfg.instructions_file).expanduser()
        if not file.is_absolute() and path is not None:
            file = Path(path).resolve().parent / file
        try:
            text = file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise DegustaError(f"instructions_file: cannot read {file} ({getattr(e, 'strerror', None) or e})") from None
        cfg.instructions = text
    if len(cfg.instructions) > MAX_INSTRUCTIONS:
        raise DegustaError(f"instructions: {len(cfg.instructions):,} characters, more than {MAX_INSTRUCTIONS:,}")
    return cfg


def new_study_folder(root: str | Path, name: str | None = None) -> Path:
    """A new, empty study folder: the embedded default's catalog (125 objects) and tables, and a meta.json that
    marks it as collected (not synthetic). Refuses a folder that already has files."""
    root = Path(root)
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise DegustaError(f"{root}: --new needs a new or empty folder (this one has files; leave out --new to "
                           "go on collecting into it)")
    root.mkdir(parents=True, exist_ok=True)
    atomic_write_json(root / "catalog.json", default_catalog().to_json())
    atomic_write_json(root / "tables.json", [t.to_json() for t in default_tables()])
    atomic_write_json(root / "meta.json", {
        "name": name or root.resolve().name, "generator": "degusta collect", "synthetic": False,
        "min_objects": DEFAULT_MIN_OBJECTS,
        "description": "Arrangements and ratings collected from participants with `degusta collect` "
                       "(docs/collect.md), on the embedded default's catalog and tables."})
    return root


@dataclass
class Study:
    """A study config checked against its dataset folder."""

    root: Path
    config: StudyConfig
    catalog: Catalog
    tables: dict[int, Table]
    meta: dict
    shown_tables: list[int]
    arrangements: list[Arrangement]
    ratings: list[Rating]

    @property
    def min_objects(self) -> int:
        return self.config.min_objects

    @property
    def instructions(self) -> str:
        return self.config.instructions.replace("{min_objects}", str(self.min_objects))


def open_study(root: str | Path, config: StudyConfig) -> Study:
    """Read the folder's catalog, tables and what was collected so far, by the rules of `degusta data validate`,
    and check the config against them (tables that exist, enough of them, a minimum the dataset accepts)."""
    root = Path(root)
    if not root.is_dir():
        raise DegustaError(f"{root}: study folder not found (make one with: degusta collect --dataset {root} --new)")
    for name in ("catalog.json", "tables.json"):
        if not has_file(root / name):
            raise DegustaError(f"{root}: no {name} (a study folder needs the catalog and tables participants "
                               f"set; start a new one with: degusta collect --dataset NEW_FOLDER --new)")
    meta, catalog, tables = load_parts(root)
    if meta.get("synthetic"):
        raise DegustaError(f"{root}/meta.json: synthetic: true — this folder holds generated data; collect "
                           "people's arrangements into a folder of their own (degusta collect --dataset NEW --new)")
    dataset_min = meta.get("min_objects", DEFAULT_MIN_OBJECTS)
    if config.min_objects < dataset_min:
        raise DegustaError(f"min_objects: {config.min_objects} is below the dataset's minimum of {dataset_min} "
                           f"({root}/meta.json min_objects): such tables would not load")
    shown = list(config.tables) if config.tables is not None else sorted(tables)
    unknown = [t for t in shown if t not in tables]
    if unknown:
        raise DegustaError(f"tables: {unknown} are not tables of {root}/tables.json (its tables: {sorted(tables)})")
    if len(set(shown)) != len(shown):
        raise DegustaError(f"tables: {shown} names a table twice")
    if config.tables_per_participant > len(shown):
        raise DegustaError(f"tables_per_participant: {config.tables_per_participant} tables, each a different one, "
                           f"but only {len(shown)} tables are shown (tables: {shown})")
    arrangements, ratings = [], []
    if has_file(root / "arrangements.jsonl"):
        lines = list(read_jsonl(root / "arrangements.jsonl"))
        if lines:
            arrangements = check_arrangements(lines, root / "arrangements.jsonl", catalog, tables, dataset_min)
    if has_file(root / "ratings.jsonl"):
        ratings = check_ratings(read_jsonl(root / "ratings.jsonl"), root / "ratings.jsonl", arrangements)
    return Study(root, config, catalog, tables, meta, shown, arrangements, ratings)


__all__ = ["DEFAULT_INSTRUCTIONS", "MAX_OBJECTS", "JitterConfig", "Study", "StudyConfig", "load_study_config",
           "new_study_folder", "open_study"]
