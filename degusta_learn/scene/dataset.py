"""The dataset folder format: reading (with validation) and writing.

A dataset is a folder::

    catalog.json        list of objects (see catalog.py); optional "image" per entry
    tables.json         list of {"id", "width", "height", "surface": [[x, y], ...], optional "name", "image"}
    arrangements.jsonl  one arrangement a line: {"participant", "trial", "table", "placements": [...]}
    ratings.jsonl       optional jitter-study ratings
    meta.json           optional: {"synthetic": bool, "generator": str, "seed": int, "min_objects": int,
                        "vocabulary": {"classes"|"colors"|"materials": [extra words]}, ...}

`load_dataset` validates everything and raises `DegustaError` naming the file, the line and the field;
`validate_dataset` applies the same rules to a dataset in memory (the generators check their output
with it). The rules, in one place: JSON types; ids 0..MAX_ID, trials 0..MAX_TRIAL, coordinates in
[0, 1], finite numbers (the readers refuse NaN/inf and oversized numbers); classes, colours and
materials from the vocabulary; printable text (no control or invisible characters in any name, word, id
or path: validate.printable_text; a meta.json `description` may hold newlines and tabs); table
surfaces that are real polygons (>= 3 distinct points, area >= MIN_SURFACE_AREA); pictures and named
files that stay inside the dataset folder (no '..', no absolute paths, no symbolic links out) and, for
PNG, at most MAX_IMAGE_PIXELS pixels. An optional file
that is present but unreadable (a symlink loop, a folder) is an error, never skipped.
It never writes into the folder. `save_dataset` writes every file atomically; `dataset_identity` is its
fingerprint (what a fine-tuned adapter records it was trained on).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.files.identity import file_sha256, stat_tree
from degusta_learn.files.jsonio import atomic_write_json, atomic_write_jsonl, read_json, read_jsonl
from degusta_learn.files.paths import path_problem, shown_path
from degusta_learn.scene.catalog import COLORS, MATERIALS, TYPES, Catalog, CatalogObject
from degusta_learn.scene.tables import Table
from degusta_learn.scene.types import Arrangement, Placement, Rating
from degusta_learn.scene.validate import (
    MAX_ID,
    MAX_TRIAL,
    Where,
    check_picture,
    file_inside,
    get,
    in_vocabulary,
    printable_text,
    relative_path,
    require_mapping,
    unit_interval,
)

DEFAULT_MIN_OBJECTS = 3


@dataclass
class Dataset:
    """A loaded dataset: catalog, tables, arrangements (with lookup) and optional ratings."""

    catalog: Catalog
    tables: dict[int, Table]
    arrangements: list[Arrangement]
    ratings: list[Rating] | None = None
    meta: dict = field(default_factory=dict)
    root: Path | None = None
    _by_key: dict = field(init=False, repr=False)

    def __post_init__(self):
        self._by_key = {(a.participant, a.trial): a for a in self.arrangements}

    @property
    def synthetic(self) -> bool:
        return bool(self.meta.get("synthetic", False))

    @property
    def label(self) -> str:
        """How reports name this data: generator and 'synthetic' where it is."""
        name = self.meta.get("name") or (self.root.name if self.root else "dataset")
        return f"{name} (SYNTHETIC data)" if self.synthetic else name

    @property
    def participants(self) -> list[str]:
        return sorted({a.participant for a in self.arrangements})

    def arrangement(self, participant: str, trial: int) -> Arrangement:
        try:
            return self._by_key[(participant, trial)]
        except KeyError:
            raise DegustaError(f"no arrangement for participant {participant!r}, trial {trial}") from None

    def object_counts(self, participant: str, trials) -> list[int]:
        """How many objects each of `participant`'s `trials` places (e.g. an episode's context tables)."""
        return [len(self.arrangement(participant, t).placements) for t in trials]

    def trials_of(self, participant: str) -> list[Arrangement]:
        return sorted((a for a in self.arrangements if a.participant == participant), key=lambda a: a.trial)

    def by_participant(self) -> dict[str, list[Arrangement]]:
        out = defaultdict(list)
        for a in self.arrangements:
            out[a.participant].append(a)
        return {p: sorted(v, key=lambda a: a.trial) for p, v in sorted(out.items())}


def load_dataset(root: str | Path) -> Dataset:
    """Read and validate a dataset folder; errors name file, line and field (see `validate_dataset`)."""
    problem = path_problem(root)  # a NUL byte, a name too long, non-UTF-8, a broken link, a parent that is a file ...
    if problem:
        raise DegustaError(f"{shown_path(root)}: {problem}")
    root = Path(root)
    if not root.is_dir():
        if root.exists() or root.is_symlink():
            raise DegustaError(f"{root}: not a dataset folder (not a readable folder)")
        raise DegustaError(f"{root}: dataset folder not found")
    meta, catalog, tables = load_parts(root)
    arrangements = _parse_arrangements(read_jsonl(root / "arrangements.jsonl"), root / "arrangements.jsonl",
                                       catalog, tables, meta.get("min_objects", DEFAULT_MIN_OBJECTS))
    ratings = None
    if _present(root / "ratings.jsonl"):
        ratings = _parse_ratings(read_jsonl(root / "ratings.jsonl"), root / "ratings.jsonl", arrangements)
    return Dataset(catalog, tables, arrangements, ratings, meta, root)


def load_parts(root: Path) -> tuple[dict, Catalog, dict[int, Table]]:
    """(meta, catalog, tables) of a dataset folder, checked as `load_dataset` checks them: what a folder holds before
    anyone's arrangement (a study of `degusta collect`)."""
    meta = _parse_meta(read_json(root / "meta.json") if _present(root / "meta.json") else {}, root / "meta.json", root)
    vocab = _vocabulary(meta, root / "meta.json")
    catalog = _parse_catalog(read_json(root / "catalog.json"), root / "catalog.json", root, vocab)
    tables = _parse_tables(read_json(root / "tables.json"), root / "tables.json", root)
    return meta, catalog, tables


def check_arrangements(lines, path: Path, catalog: Catalog, tables: dict[int, Table],
                       min_objects: int = DEFAULT_MIN_OBJECTS) -> list[Arrangement]:
    """(line number, entry) pairs of arrangements.jsonl checked by the dataset's rules (errors name `path`, the line
    and the field); at least one entry."""
    return _parse_arrangements(lines, path, catalog, tables, min_objects)


def check_ratings(lines, path: Path, arrangements=None) -> list[Rating]:
    """(line number, entry) pairs of ratings.jsonl checked by the dataset's rules (with `arrangements`: each rates
    one of them)."""
    return _parse_ratings(lines, path, arrangements)


def has_file(path: Path) -> bool:
    """Whether an optional file of a dataset is there (anything at the path counts, a broken link too: it is then
    read and fails loudly)."""
    return _present(path)


def dataset_identity(ds: Dataset) -> str:
    """The dataset fingerprint (SHA-256 hex): of the bytes of the folder's top-level files and the size and
    time of the files in its subfolders (pictures), or, for a dataset never saved (`root` None), of its
    arrangements. Compare's staleness records and the fine-tuning record (`vlm/record.py`) use it."""
    if ds.root is None:
        return _sha([a.to_json() for a in ds.arrangements])
    parts = []
    for p in sorted(Path(ds.root).iterdir()):
        if p.is_file():
            parts.append([p.name, file_sha256(p)])
        elif p.is_dir():
            parts.append([p.name, stat_tree(p)])
    return _sha(parts)


def _sha(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def validate_dataset(ds: Dataset) -> Dataset:
    """Check an in-memory dataset by the same rules as `load_dataset` (e.g. a generator's output).

    The dataset is put through the exact JSON form `save_dataset` writes, so whatever passes here loads.
    Errors name the file the entry would be written to. Pictures are checked only when `ds.root` is set.
    """
    base = ds.root if ds.root is not None else Path("<in memory>")
    meta = _parse_meta(ds.meta, base / "meta.json", ds.root)
    catalog = _parse_catalog(ds.catalog.to_json(), base / "catalog.json", ds.root, _vocabulary(meta, base / "meta.json"))
    tables = _parse_tables([t.to_json() for t in ds.tables.values()], base / "tables.json", ds.root)
    for tid, table in ds.tables.items():
        if table.id != tid:
            raise DegustaError(f"{base / 'tables.json'}: table {table.id} is stored under id {tid}")
    _parse_arrangements(((i, a.to_json()) for i, a in enumerate(ds.arrangements, start=1)),
                        base / "arrangements.jsonl", catalog, tables, meta.get("min_objects", DEFAULT_MIN_OBJECTS))
    if ds.ratings is not None:
        _parse_ratings(((i, r.to_json()) for i, r in enumerate(ds.ratings, start=1)), base / "ratings.jsonl",
                       ds.arrangements)
    return ds


def off_surface(ds: Dataset) -> list[tuple[Arrangement, Placement]]:
    """Placements whose centre lies outside their table's surface polygon (inside [0, 1], so they load).

    Not an error (a real plate may hang over a round table's edge), but many of them usually mean coordinates
    given in another frame than the table's (`degusta data validate` reports them)."""
    out = []
    for arr in ds.arrangements:
        if not arr.placements:
            continue
        on = ds.tables[arr.table].contains([p.x for p in arr.placements], [p.y for p in arr.placements])
        out += [(arr, p) for p, ok in zip(arr.placements, on) if not ok]
    return out


def save_dataset(ds: Dataset, root: str | Path) -> Path:
    """Write `ds` as a dataset folder (atomically, file by file); returns the folder."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    atomic_write_json(root / "catalog.json", ds.catalog.to_json())
    atomic_write_json(root / "tables.json", [t.to_json() for t in ds.tables.values()])
    atomic_write_jsonl(root / "arrangements.jsonl", (a.to_json() for a in ds.arrangements))
    if ds.ratings is not None:
        atomic_write_jsonl(root / "ratings.jsonl", (r.to_json() for r in ds.ratings))
    if ds.meta:
        atomic_write_json(root / "meta.json", ds.meta)
    return root


def _present(path: Path) -> bool:
    """Whether an optional file is there: anything at the path, even a broken or looping symbolic link,
    counts (and is then read, so that it fails loudly instead of being silently skipped)."""
    return os.path.lexists(path)


META_KEYS = {"name": "str", "generator": "str", "description": "prose", "latent_styles": "str", "episodes": "str"}
PATH_KEYS = ("latent_styles", "episodes")
VOCABULARY_KEYS = {"classes": TYPES, "colors": COLORS, "materials": MATERIALS}


def _parse_meta(meta, path: Path, root: Path | None) -> dict:
    """meta.json: optional, a JSON object; known keys are type-checked, others are kept as they are."""
    if not isinstance(meta, dict):
        raise DegustaError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    w = Where(path)
    get(meta, "synthetic", "bool", w, optional=True)
    get(meta, "seed", "int", w, optional=True)
    get(meta, "min_objects", "int", w, optional=True, lo=1, hi=1000)
    for key, kind in META_KEYS.items():
        get(meta, key, kind, w, optional=True)
    for key in PATH_KEYS:  # files the dataset names (the oracle reads latent_styles): inside the folder
        if meta.get(key) is None:
            continue
        relative_path(meta[key], key, w)
        if root is not None and _present(root / meta[key]):
            file_inside(root, meta[key], key, w)
    vocab = meta.get("vocabulary")
    if vocab is not None:
        if not isinstance(vocab, dict):
            raise w.fail("vocabulary", f"expected an object with lists {', '.join(VOCABULARY_KEYS)}")
        for key, words in vocab.items():
            if key not in VOCABULARY_KEYS:
                raise w.fail(f"vocabulary.{key}", f"unknown key (expected one of {', '.join(VOCABULARY_KEYS)})")
            if not isinstance(words, list) or not all(isinstance(x, str) and 0 < len(x) <= 100 for x in words):
                raise w.fail(f"vocabulary.{key}", "expected a list of non-empty words")
            for word in words:  # words are drawn on sheets and written into prompts and reports: printable
                printable_text(word, f"vocabulary.{key}", w)
    return meta


def _vocabulary(meta: dict, path: Path) -> dict[str, tuple[str, ...]]:
    """The dataset's words: the design's classes, colours and materials plus any meta.json `vocabulary` adds."""
    extra = meta.get("vocabulary") or {}
    return {key: tuple(dict.fromkeys([*base, *extra.get(key, [])])) for key, base in VOCABULARY_KEYS.items()}


def _check_image(value, root: Path | None, where: Where) -> str | None:
    """An optional picture: a path relative to the dataset folder that stays inside it and is an image."""
    if value is None:
        return None
    if root is None:
        return relative_path(value, "image", where)
    return check_picture(root, value, "image", where)


def _parse_catalog(data, path: Path, root: Path | None, vocab: dict) -> Catalog:
    if not isinstance(data, list) or not data:
        raise DegustaError(f"{path}: expected a non-empty JSON list of objects")
    objects, seen = [], set()
    for i, entry in enumerate(data):
        w = Where(path, index=i)
        require_mapping(entry, w)
        oid = get(entry, "id", "int", w, lo=0, hi=MAX_ID)
        if oid in seen:
            raise w.fail("id", f"duplicate object id {oid}")
        seen.add(oid)
        words = {}
        for key, kind in (("class", "classes"), ("color1", "colors"), ("color2", "colors"),
                          ("material1", "materials"), ("material2", "materials")):
            default = words.get(key[:-1] + "1") if key.endswith("2") else None
            value = get(entry, key, "str", w, optional=key.endswith("2"), default=default)
            words[key] = in_vocabulary(value, vocab[kind], key, w)
        objects.append(CatalogObject(
            id=oid, type=words["class"], color1=words["color1"], color2=words["color2"],
            material1=words["material1"], material2=words["material2"],
            shape=get(entry, "shape", "str", w, optional=True, default="round"),
            pattern=get(entry, "pattern", "str", w, optional=True, default="solid"),
            texture=get(entry, "texture", "str", w, optional=True, default="smooth"),
            image=_check_image(entry.get("image"), root, w),
        ))
    return Catalog(tuple(objects))


MIN_SURFACE_AREA = 0.01  # of the table image: smaller surfaces cannot hold a plate
MAX_SURFACE_POINTS = 10_000
MAX_TABLE_PIXELS = 100_000  # width and height of a table image


def _parse_tables(data, path: Path, root: Path | None) -> dict[int, Table]:
    if not isinstance(data, list) or not data:
        raise DegustaError(f"{path}: expected a non-empty JSON list of tables")
    tables = {}
    for i, entry in enumerate(data):
        w = Where(path, index=i)
        require_mapping(entry, w)
        tid = get(entry, "id", "int", w, lo=0, hi=MAX_ID)
        if tid in tables:
            raise w.fail("id", f"duplicate table id {tid}")
        width = get(entry, "width", "int", w, lo=1, hi=MAX_TABLE_PIXELS)
        height = get(entry, "height", "int", w, lo=1, hi=MAX_TABLE_PIXELS)
        surface = get(entry, "surface", "list", w)
        if not 3 <= len(surface) <= MAX_SURFACE_POINTS:
            raise w.fail("surface", f"expected a polygon of 3 to {MAX_SURFACE_POINTS} [x, y] points, got {len(surface)}")
        pts = []
        for j, pt in enumerate(surface):
            ok = isinstance(pt, list) and len(pt) == 2 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1 for v in pt)
            if not ok:
                raise w.fail("surface", f"point {j} must be [x, y] with both in [0, 1], got {pt!r}"[:200])
            pts.append((float(pt[0]), float(pt[1])))
        _check_surface(pts, w)
        name = entry.get("name")
        if name is not None and not isinstance(name, str):
            raise w.fail("name", f"expected a string, got {type(name).__name__}")
        if name and len(name) > 100:
            raise w.fail("name", f"name of {len(name)} characters is too long (at most 100)")
        if name:
            printable_text(name, "name", w)
        tables[tid] = Table(tid, width, height, tuple(pts), name=name or "",
                            image=_check_image(entry.get("image"), root, w))
    return tables


def _check_surface(pts: list[tuple[float, float]], w: Where) -> None:
    """Reject degenerate surfaces: fewer than 3 distinct points, collinear points, (almost) no area."""
    if len(set(pts)) < 3:
        raise w.fail("surface", f"degenerate polygon: only {len(set(pts))} distinct points (at least 3 needed)")
    xy = np.asarray(pts, dtype=float)
    area = 0.5 * abs(float(np.dot(xy[:, 0], np.roll(xy[:, 1], -1)) - np.dot(xy[:, 1], np.roll(xy[:, 0], -1))))
    if area < MIN_SURFACE_AREA:
        raise w.fail("surface", f"degenerate polygon: area {area:.4g} of the image (points collinear, repeated "
                                f"or too close; a table surface must cover at least {MIN_SURFACE_AREA})")


def parse_placements(items: list, catalog: Catalog, where: Where, key: str = "placements") -> list[Placement]:
    """Validate a JSON list of placements against the catalog (ids known, x/y in [0, 1], no repeats)."""
    out, seen = [], set()
    for j, p in enumerate(items):
        if not isinstance(p, dict):
            raise where.fail(f"{key}[{j}]", f"expected an object, got {p!r}"[:200])
        sub = f"{key}[{j}]."
        oid = get(p, "object", "int", _Prefixed(where, sub))
        if oid not in catalog:
            raise where.fail(f"{sub}object", f"unknown object id {oid} (not in the catalog)"[:200])
        if oid in seen:
            raise where.fail(f"{sub}object", f"object {oid} is placed twice")
        seen.add(oid)
        x = unit_interval(get(p, "x", "number", _Prefixed(where, sub)), f"{sub}x", where)
        y = unit_interval(get(p, "y", "number", _Prefixed(where, sub)), f"{sub}y", where)
        rot = get(p, "rotation", "number", _Prefixed(where, sub), optional=True, default=0.0)
        out.append(Placement(oid, x, y, rot % 360.0))
    return out


class _Prefixed(Where):
    """A Where whose field names get a prefix (for nested entries such as placements[2].x)."""

    def __init__(self, base: Where, prefix: str):
        super().__init__(base.path, base.line, base.index)
        self.prefix = prefix

    def fail(self, field, message):
        return super().fail(self.prefix + field if field else None, message)


def _parse_arrangements(lines, path: Path, catalog: Catalog, tables: dict[int, Table],
                        min_objects: int) -> list[Arrangement]:
    out, seen = [], {}
    for lineno, entry in lines:
        w = Where(path, line=lineno)
        require_mapping(entry, w)
        participant = get(entry, "participant", "id", w)
        trial = get(entry, "trial", "int", w, lo=0, hi=MAX_TRIAL)
        if (participant, trial) in seen:
            raise w.fail("trial", f"duplicate trial {trial} of participant {participant!r} "
                                  f"(first on line {seen[(participant, trial)]})")
        seen[(participant, trial)] = lineno
        table = get(entry, "table", "int", w)
        if table not in tables:
            raise w.fail("table", f"table id {table} has no table in tables.json"[:200])
        placements = parse_placements(get(entry, "placements", "list", w), catalog, w)
        if len(placements) < min_objects:
            raise w.fail("placements", f"{len(placements)} objects, fewer than the minimum of {min_objects}")
        out.append(Arrangement(participant, trial, table, tuple(placements)))
    if not out:
        raise DegustaError(f"{path}: no arrangements")
    return out


def _parse_ratings(lines, path: Path, arrangements=None) -> list[Rating]:
    """ratings.jsonl: one jitter-study trial per arrangement (with `arrangements`, each must be one of them)."""
    out, seen = [], set()
    known = {(a.participant, a.trial) for a in arrangements} if arrangements is not None else None
    for lineno, entry in lines:
        w = Where(path, line=lineno)
        require_mapping(entry, w)
        vals = {}
        for key in ("b_initial", "b_jitter", "b_correct"):
            v = get(entry, key, "number", w, optional=key == "b_correct")
            if v is not None and not 0 <= v <= 100:
                raise w.fail(key, f"rating {v} is outside 0..100")
            vals[key] = v
        for key in ("rmsd_jitter", "rmsd_correct"):
            v = get(entry, key, "number", w, optional=key == "rmsd_correct")
            if v is not None and v < 0:
                raise w.fail(key, f"RMSD {v} is negative")
            vals[key] = v
        participant, trial = get(entry, "participant", "id", w), get(entry, "trial", "int", w, lo=0, hi=MAX_TRIAL)
        if (participant, trial) in seen:
            raise w.fail("trial", f"participant {participant!r} trial {trial} is rated twice")
        if known is not None and (participant, trial) not in known:
            raise w.fail("trial", f"participant {participant!r} has no trial {trial} in arrangements.jsonl")
        seen.add((participant, trial))
        out.append(Rating(participant, trial, **vals))
    return out
