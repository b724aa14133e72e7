"""The dataset folder format: reading (with validation) and writing.

A dataset is a folder::

    catalog.json        list of objects (see catalog.py); optional "image" per entry
    tables.json         list of {"id", "width", "height", "surface": [[x, y], ...], optional "name", "image"}
    arrangements.jsonl  one arrangement a line: {"participant", "trial", "table", "placements": [...]}
    ratings.jsonl       optional jitter-study ratings
    meta.json           optional: {"synthetic": bool, "generator": str, "seed": int, "min_objects": int, ...}

`load_dataset` validates everything and raises `DegustaError` naming the file, the line and the field.
It never writes into the folder. `save_dataset` writes every file atomically.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.fileio import atomic_write_json, atomic_write_jsonl, read_json, read_jsonl
from degusta_learn.scene.catalog import Catalog, CatalogObject
from degusta_learn.scene.tables import Table
from degusta_learn.scene.types import Arrangement, Placement, Rating
from degusta_learn.scene.validate import Where, get, require_mapping, unit_interval

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

    def trials_of(self, participant: str) -> list[Arrangement]:
        return sorted((a for a in self.arrangements if a.participant == participant), key=lambda a: a.trial)

    def by_participant(self) -> dict[str, list[Arrangement]]:
        out = defaultdict(list)
        for a in self.arrangements:
            out[a.participant].append(a)
        return {p: sorted(v, key=lambda a: a.trial) for p, v in sorted(out.items())}


def load_dataset(root: str | Path) -> Dataset:
    """Read and validate a dataset folder; errors name file, line and field."""
    root = Path(root)
    if not root.is_dir():
        raise DegustaError(f"{root}: dataset folder not found")
    meta = {}
    if (root / "meta.json").exists():
        meta = read_json(root / "meta.json")
        if not isinstance(meta, dict):
            raise DegustaError(f"{root / 'meta.json'}: expected a JSON object")
    catalog = _load_catalog(root / "catalog.json", root)
    tables = _load_tables(root / "tables.json", root)
    min_objects = meta.get("min_objects", DEFAULT_MIN_OBJECTS)
    arrangements = _load_arrangements(root / "arrangements.jsonl", catalog, tables, min_objects)
    ratings = None
    if (root / "ratings.jsonl").exists():
        ratings = _load_ratings(root / "ratings.jsonl")
    return Dataset(catalog, tables, arrangements, ratings, meta, root)


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


def _check_image(value, root: Path, where: Where) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise where.fail("image", f"expected a relative path string, got {value!r}")
    if not (root / value).is_file():
        raise where.fail("image", f"file {root / value} not found")
    return value


def _load_catalog(path: Path, root: Path) -> Catalog:
    data = read_json(path)
    if not isinstance(data, list) or not data:
        raise DegustaError(f"{path}: expected a non-empty JSON list of objects")
    objects, seen = [], set()
    for i, entry in enumerate(data):
        w = Where(path, index=i)
        require_mapping(entry, w)
        oid = get(entry, "id", "int", w)
        if oid < 0:
            raise w.fail("id", f"expected a non-negative integer, got {oid}")
        if oid in seen:
            raise w.fail("id", f"duplicate object id {oid}")
        seen.add(oid)
        color1 = get(entry, "color1", "str", w)
        material1 = get(entry, "material1", "str", w)
        objects.append(CatalogObject(
            id=oid, type=get(entry, "class", "str", w), color1=color1,
            color2=get(entry, "color2", "str", w, optional=True, default=color1),
            material1=material1,
            material2=get(entry, "material2", "str", w, optional=True, default=material1),
            shape=get(entry, "shape", "str", w, optional=True, default="round"),
            pattern=get(entry, "pattern", "str", w, optional=True, default="solid"),
            texture=get(entry, "texture", "str", w, optional=True, default="smooth"),
            image=_check_image(entry.get("image"), root, w),
        ))
    return Catalog(tuple(objects))


def _load_tables(path: Path, root: Path) -> dict[int, Table]:
    data = read_json(path)
    if not isinstance(data, list) or not data:
        raise DegustaError(f"{path}: expected a non-empty JSON list of tables")
    tables = {}
    for i, entry in enumerate(data):
        w = Where(path, index=i)
        require_mapping(entry, w)
        tid = get(entry, "id", "int", w)
        if tid in tables:
            raise w.fail("id", f"duplicate table id {tid}")
        width, height = get(entry, "width", "int", w), get(entry, "height", "int", w)
        if width <= 0 or height <= 0:
            raise w.fail("width" if width <= 0 else "height", "expected a positive pixel size")
        surface = get(entry, "surface", "list", w)
        if len(surface) < 3:
            raise w.fail("surface", "expected a polygon of at least 3 [x, y] points")
        pts = []
        for j, pt in enumerate(surface):
            ok = isinstance(pt, list) and len(pt) == 2 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1 for v in pt)
            if not ok:
                raise w.fail("surface", f"point {j} must be [x, y] with both in [0, 1], got {pt!r}")
            pts.append((float(pt[0]), float(pt[1])))
        tables[tid] = Table(tid, width, height, tuple(pts), name=str(entry.get("name") or ""),
                            image=_check_image(entry.get("image"), root, w))
    return tables


def parse_placements(items: list, catalog: Catalog, where: Where, key: str = "placements") -> list[Placement]:
    """Validate a JSON list of placements against the catalog (ids known, x/y in [0, 1], no repeats)."""
    out, seen = [], set()
    for j, p in enumerate(items):
        if not isinstance(p, dict):
            raise where.fail(f"{key}[{j}]", f"expected an object, got {p!r}")
        sub = f"{key}[{j}]."
        oid = get(p, "object", "int", _Prefixed(where, sub))
        if oid not in catalog:
            raise where.fail(f"{sub}object", f"unknown object id {oid} (not in the catalog)")
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


def _load_arrangements(path: Path, catalog: Catalog, tables: dict[int, Table], min_objects: int) -> list[Arrangement]:
    out, seen = [], {}
    for lineno, entry in read_jsonl(path):
        w = Where(path, line=lineno)
        require_mapping(entry, w)
        participant = get(entry, "participant", "id", w)
        trial = get(entry, "trial", "int", w)
        if (participant, trial) in seen:
            raise w.fail("trial", f"duplicate trial {trial} of participant {participant!r} "
                                  f"(first on line {seen[(participant, trial)]})")
        seen[(participant, trial)] = lineno
        table = get(entry, "table", "int", w)
        if table not in tables:
            raise w.fail("table", f"table id {table} has no table in tables.json")
        placements = parse_placements(get(entry, "placements", "list", w), catalog, w)
        if len(placements) < min_objects:
            raise w.fail("placements", f"{len(placements)} objects, fewer than the minimum of {min_objects}")
        out.append(Arrangement(participant, trial, table, tuple(placements)))
    if not out:
        raise DegustaError(f"{path}: no arrangements")
    return out


def _load_ratings(path: Path) -> list[Rating]:
    out = []
    for lineno, entry in read_jsonl(path):
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
        out.append(Rating(get(entry, "participant", "id", w), get(entry, "trial", "int", w), **vals))
    return out
