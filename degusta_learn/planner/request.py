"""The plan request: what a robot (or a person at a terminal) asks the planner, as JSON and as a typed value.

A request says whose table it is (their past arrangements: inline, in the dataset's arrangement form, or a
participant whose arrangements a dataset folder holds), which table to set (a known table id, or a new table given
by its image size and surface polygon), which objects are on hand (default: the whole catalog) and optionally how
many objects to place at most. docs/planner.md documents every key with an example.

`PlanRequest.from_json` checks the form and the bounds (`LIMITS`) alone; what needs the planner's catalog and tables
(object ids known, table ids known, the catalog the same) is checked when planning (planner/episode.py). Either way
an error is one `DegustaError` line naming the field path, e.g. ``request.table.surface[3]: ...``, the same line for
the command line and for HTTP (`loads_request` parses the bytes of either strictly: UTF-8, finite numbers, no key
given twice).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.scene import Arrangement, Placement
from degusta_learn.scene.validate import MAX_ID, MAX_TRIAL, Where, get
from degusta_learn.webio import shown, strict_json

MAX_REQUEST_BYTES = 2**20
"""Bytes of one request (a file for `degusta plan`, a body for `POST /plan`): a 125-object catalog, 8 arrangements
and a 1,000-point polygon take ~60 kB."""
MAX_CONTEXT = 8
"""Past arrangements one request may give (the methods were evaluated with 0, 2 and 4)."""
MAX_PLACEMENTS = 64
"""Objects in one past arrangement."""
MAX_OBJECTS = 1000
"""Objects on hand (and catalog entries) one request may list."""
MAX_STEPS = 64
"""The largest `n_objects`."""
MAX_TABLES = 32
"""Tables one request may add (`tables`)."""
MAX_POLYGON_POINTS = 1000
"""Points of one surface polygon."""
MAX_TABLE_PIXELS = 100_000
"""Width and height of a table image (as the dataset format bounds them)."""
MAX_METRES = 100.0
"""The largest table side in metres."""
MIN_SURFACE_AREA = 0.01
"""Area of a surface polygon, as a fraction of the table image (the dataset format's bound: a plate needs it)."""

LIMITS = {"request_bytes": MAX_REQUEST_BYTES, "context_arrangements": MAX_CONTEXT,
          "placements_per_arrangement": MAX_PLACEMENTS, "objects_on_hand": MAX_OBJECTS, "n_objects": MAX_STEPS,
          "tables": MAX_TABLES, "polygon_points": MAX_POLYGON_POINTS}
"""Every bound a request is checked against, by name (docs/planner.md, GET /health)."""

DEFAULT_PERSON = "person"
"""The participant id of an inline history that gives none."""

REQUEST_KEYS = ("arrangements", "participant", "trials", "dataset", "catalog", "tables", "table", "objects",
                "n_objects")


class At(Where):
    """Where a request value sits, as a field path (``request.table.surface[3]``); `fail` names it."""

    def __init__(self, path: str = "request"):
        super().__init__(path)

    def fail(self, field: str | int | None, message: str) -> DegustaError:
        return DegustaError(f"{self.key(field)}: {message}" if field is not None else f"{self.path}: {message}")

    def key(self, name: str | int) -> str:
        return f"{self.path}[{name}]" if isinstance(name, int) else f"{self.path}.{name}"

    def __truediv__(self, name: str | int) -> At:
        return At(self.key(name))


@dataclass(frozen=True)
class NewTable:
    """A table the planner does not know: its image size in pixels and its surface polygon (normalized image
    coordinates, x right, y down, both in [0, 1]); `name` picks the procedural look, `image` a picture inside the
    planner's dataset folder."""

    width: int
    height: int
    surface: tuple[tuple[float, float], ...]
    name: str = ""
    image: str | None = None
    id: int | None = None
    """Its id in the plan (default: one above every known table id)."""

    def to_json(self) -> dict:
        out: dict[str, Any] = {"width": self.width, "height": self.height, "surface": [list(p) for p in self.surface]}
        for key in ("name", "image", "id"):
            if getattr(self, key) not in (None, ""):
                out[key] = getattr(self, key)
        return out


@dataclass(frozen=True)
class PlanRequest:
    """One plan request (docs/planner.md, "The plan request"). Build it in Python or with `from_json`."""

    table: int | NewTable
    """The table to set: a known table id, or a new table."""
    metres: tuple[float, float] | None = None
    """The table image's width and height in metres: the plan then gives every position in metres too."""
    arrangements: tuple[Arrangement, ...] | None = None
    """The person's past arrangements, inline (None: from `participant`, or none at all)."""
    participant: str | None = None
    """Whose arrangements: with `arrangements`, their id; without, the participant of `dataset` to take them from."""
    trials: tuple[int, ...] | None = None
    """With `participant` and no `arrangements`: which of their trials (default: all), in this order."""
    dataset: str | None = None
    """With `participant`: the dataset folder that holds them (default: the planner's dataset)."""
    catalog: tuple[dict, ...] | None = None
    """The catalog as the dataset form writes it: checked to be the planner's, never another one."""
    tables: tuple[dict, ...] = ()
    """Tables (dataset form) the history or the target uses that the planner's dataset lacks."""
    objects: tuple[int, ...] | None = None
    """The ids of the objects on hand (default: the whole catalog)."""
    n_objects: int | None = None
    """At most this many steps (default: as many as the method plans)."""

    def to_json(self) -> dict:
        table = self.table if isinstance(self.table, int) else self.table.to_json()
        if self.metres is not None:
            table = {**({"id": table} if isinstance(table, int) else table), "metres": list(self.metres)}
        out: dict[str, Any] = {"table": table}
        if self.arrangements is not None:
            out["arrangements"] = [a.to_json() for a in self.arrangements]
        for key in ("participant", "dataset", "n_objects"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        for key in ("trials", "catalog", "objects"):
            if getattr(self, key) is not None:
                out[key] = list(getattr(self, key))
        if self.tables:
            out["tables"] = list(self.tables)
        return out

    @classmethod
    def from_json(cls, obj: Any) -> PlanRequest:
        """The request a JSON object describes; a malformed one raises DegustaError naming the field path."""
        at = At()
        if not isinstance(obj, dict):
            raise at.fail(None, f"expected a JSON object, got {type(obj).__name__}")
        unknown = sorted(set(obj) - set(REQUEST_KEYS), key=str)
        if unknown:
            raise at.fail(str(unknown[0])[:60], f"unknown key (expected some of {', '.join(REQUEST_KEYS)})")
        if "table" not in obj:
            raise at.fail("table", "missing: the table to set (a table id, or {\"width\", \"height\", \"surface\"})")
        table, metres = _table_key(obj["table"], at / "table")
        participant = get(obj, "participant", "id", at, optional=True)
        arrangements = None
        if obj.get("arrangements") is not None:
            arrangements = _arrangements(get(obj, "arrangements", "list", at), at / "arrangements", participant)
            participant = participant or (arrangements[0].participant if arrangements else DEFAULT_PERSON)
        trials = None
        if obj.get("trials") is not None:
            if participant is None or arrangements is not None:
                raise at.fail("trials", "only with `participant` and without `arrangements` (it picks the "
                                        "participant's trials from the dataset)")
            trials = _trials(get(obj, "trials", "list", at), at / "trials")
        dataset = get(obj, "dataset", "str", at, optional=True)
        if dataset is not None and (participant is None or arrangements is not None):
            raise at.fail("dataset", "only with `participant` and without `arrangements` (the folder to take the "
                                     "participant's arrangements from)")
        catalog = None
        if obj.get("catalog") is not None:
            catalog = tuple(_bounded_list(obj, "catalog", at, MAX_OBJECTS, dict))
        tables = tuple(_bounded_list(obj, "tables", at, MAX_TABLES, dict)) if obj.get("tables") is not None else ()
        objects = None
        if obj.get("objects") is not None:
            objects = tuple(_ids(get(obj, "objects", "list", at), at / "objects"))
        n_objects = get(obj, "n_objects", "int", at, optional=True, lo=1, hi=MAX_STEPS)
        return cls(table=table, metres=metres, arrangements=arrangements, participant=participant, trials=trials,
                   dataset=dataset, catalog=catalog, tables=tables, objects=objects, n_objects=n_objects)


def _bounded_list(obj: dict, key: str, at: At, limit: int, kind: type) -> list:
    items = get(obj, key, "list", at)
    if len(items) > limit:
        raise at.fail(key, f"{len(items)} entries, over the limit of {limit}")
    for i, item in enumerate(items):
        if not isinstance(item, kind):
            raise (at / key).fail(i, f"expected a JSON object, got {type(item).__name__}")
    return items


def _ids(items: list, at: At) -> list[int]:
    if not items:
        raise at.fail(None, "an empty list: no object on hand (leave the key out for the whole catalog)")
    if len(items) > MAX_OBJECTS:
        raise at.fail(None, f"{len(items)} objects, over the limit of {MAX_OBJECTS}")
    seen = set()
    for i, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_ID:
            raise at.fail(i, f"expected an object id (an integer 0..{MAX_ID}), got {shown(v)}")
        if v in seen:
            raise at.fail(i, f"object {v} is listed twice")
        seen.add(v)
    return items


def _trials(items: list, at: At) -> tuple[int, ...]:
    if len(items) > MAX_CONTEXT:
        raise at.fail(None, f"{len(items)} trials, over the limit of {MAX_CONTEXT} past arrangements")
    for i, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_TRIAL:
            raise at.fail(i, f"expected a trial number (an integer 0..{MAX_TRIAL}), got {shown(v)}")
    if len(set(items)) != len(items):
        raise at.fail(None, f"a trial appears twice in {shown(items)}")
    return tuple(items)


def _table_key(value: Any, at: At) -> tuple[int | NewTable, tuple[float, float] | None]:
    """`table`: an id, {"id", optional "metres"}, or a new table {"width", "height", "surface", ...}."""
    if isinstance(value, bool) or not isinstance(value, (int, dict)):
        raise at.fail(None, f"expected a table id or an object with width, height and surface, got {shown(value)}")
    if isinstance(value, int):
        if not 0 <= value <= MAX_ID:
            raise at.fail(None, f"{value} is out of range (a table id is 0..{MAX_ID})")
        return value, None
    metres = _metres(value["metres"], at / "metres") if value.get("metres") is not None else None
    if "surface" not in value:
        extra = sorted(set(value) - {"id", "metres"}, key=str)
        if extra:
            raise at.fail(str(extra[0])[:60], "a known table is given by its id (and metres); a new one needs "
                                              "width, height and surface")
        return get(value, "id", "int", at, lo=0, hi=MAX_ID), metres
    return new_table(value, at), metres


def new_table(value: dict, at: At) -> NewTable:
    """A table in the dataset's form ({"width", "height", "surface", optional "name", "image", "id"}), checked as the
    dataset checks tables: a real polygon of 3..MAX_POLYGON_POINTS points in [0, 1], of area >= MIN_SURFACE_AREA."""
    known = {"id", "width", "height", "surface", "name", "image", "metres"}
    extra = sorted(set(value) - known, key=str)
    if extra:
        raise at.fail(str(extra[0])[:60], f"unknown key (a table has {', '.join(sorted(known))})")
    width = get(value, "width", "int", at, lo=1, hi=MAX_TABLE_PIXELS)
    height = get(value, "height", "int", at, lo=1, hi=MAX_TABLE_PIXELS)
    surface = get(value, "surface", "list", at)
    if not 3 <= len(surface) <= MAX_POLYGON_POINTS:
        raise at.fail("surface", f"expected a polygon of 3 to {MAX_POLYGON_POINTS} [x, y] points, got {len(surface)}")
    pts = []
    for j, pt in enumerate(surface):
        ok = isinstance(pt, list) and len(pt) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= 1 for v in pt)
        if not ok:
            raise (at / "surface").fail(j, f"expected [x, y] with both in [0, 1] (normalized image coordinates), "
                                           f"got {shown(pt)}")
        pts.append((float(pt[0]), float(pt[1])))
    if len(set(pts)) < 3:
        raise at.fail("surface", f"a degenerate polygon: {len(set(pts))} distinct points (at least 3)")
    xy = np.asarray(pts)
    area = 0.5 * abs(float(np.dot(xy[:, 0], np.roll(xy[:, 1], -1)) - np.dot(xy[:, 1], np.roll(xy[:, 0], -1))))
    if area < MIN_SURFACE_AREA:
        raise at.fail("surface", f"a degenerate polygon: area {area:.4g} of the image (at least {MIN_SURFACE_AREA}: "
                                 "points collinear, repeated or too close)")
    name = get(value, "name", "str", at, optional=True, default="")
    if len(name) > 100:
        raise at.fail("name", f"{len(name)} characters, over the limit of 100")
    image = get(value, "image", "str", at, optional=True)
    tid = get(value, "id", "int", at, optional=True, lo=0, hi=MAX_ID)
    return NewTable(width, height, tuple(pts), name, image, tid)


def _metres(value: Any, at: At) -> tuple[float, float]:
    ok = isinstance(value, list) and len(value) == 2 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 < v <= MAX_METRES
        for v in value)
    if not ok:
        raise at.fail(None, f"expected [width, height] of the table image in metres, each in (0, {MAX_METRES:g}], "
                            f"got {shown(value)}")
    return float(value[0]), float(value[1])


def _arrangements(items: list, at: At, participant: str | None) -> tuple[Arrangement, ...]:
    """Inline past arrangements in the dataset's form; `participant` and `trial` are optional (default: the
    request's `participant` and the list index). Object and table ids are checked when planning."""
    if len(items) > MAX_CONTEXT:
        raise at.fail(None, f"{len(items)} arrangements, over the limit of {MAX_CONTEXT}")
    out, trials = [], set()
    for i, entry in enumerate(items):
        here = at / i
        if not isinstance(entry, dict):
            raise here.fail(None, f"expected a JSON object, got {type(entry).__name__}")
        extra = sorted(set(entry) - {"participant", "trial", "table", "placements"}, key=str)
        if extra:
            raise here.fail(str(extra[0])[:60], "unknown key (an arrangement has participant, trial, table, "
                                                "placements)")
        who = get(entry, "participant", "id", here, optional=True)
        participant = participant or who
        if who is not None and who != participant:
            raise here.fail("participant", f"{shown(who)}, but the history is {shown(participant)}'s: one "
                                           "request holds one person's arrangements")
        trial = get(entry, "trial", "int", here, optional=True, default=i, lo=0, hi=MAX_TRIAL)
        if trial in trials:
            raise here.fail("trial", f"trial {trial} appears twice")
        trials.add(trial)
        table = get(entry, "table", "int", here, lo=0, hi=MAX_ID)
        placements = get(entry, "placements", "list", here)
        if not 1 <= len(placements) <= MAX_PLACEMENTS:
            raise here.fail("placements", f"{len(placements)} objects (expected 1 to {MAX_PLACEMENTS})")
        out.append(Arrangement(participant or DEFAULT_PERSON, trial, table,
                               tuple(_placements(placements, here / "placements"))))
    return tuple(out)


def _placements(items: list, at: At) -> list[Placement]:
    out, seen = [], set()
    for j, p in enumerate(items):
        here = at / j
        if not isinstance(p, dict):
            raise here.fail(None, f"expected an object {{\"object\", \"x\", \"y\", \"rotation\"}}, got {shown(p)}")
        extra = sorted(set(p) - {"object", "x", "y", "rotation"}, key=str)
        if extra:
            raise here.fail(str(extra[0])[:60], "unknown key (a placement has object, x, y, rotation)")
        oid = get(p, "object", "int", here, lo=0, hi=MAX_ID)
        if oid in seen:
            raise here.fail("object", f"object {oid} is placed twice")
        seen.add(oid)
        x = get(p, "x", "number", here, lo=0.0, hi=1.0)
        y = get(p, "y", "number", here, lo=0.0, hi=1.0)
        rotation = get(p, "rotation", "number", here, optional=True, default=0.0)
        out.append(Placement(oid, x, y, rotation % 360.0))
    return out


def too_large(size: int, limit: int = MAX_REQUEST_BYTES, read: bool = False) -> str:
    """The one line for a request over `limit` bytes (`read`: `size` is what was read of a body of unknown length)."""
    amount = f"more than {limit:,} bytes" if read else f"{size:,} bytes"
    return f"request: {amount}, over the limit of {limit:,} bytes a plan request may take"


def loads_request(data: bytes) -> PlanRequest:
    """Parse a request's bytes strictly (at most MAX_REQUEST_BYTES, UTF-8, finite numbers, no key given twice, bounded
    nesting) and check it (`PlanRequest.from_json`); the one-line DegustaError of the CLI and of HTTP alike."""
    if len(data) > MAX_REQUEST_BYTES:
        raise DegustaError(too_large(len(data)))
    obj = strict_json(data)
    return PlanRequest.from_json(obj)


def read_request(path) -> PlanRequest:
    """A request file: a regular file of at most MAX_REQUEST_BYTES (else one line naming it), parsed by
    `loads_request` (its errors are the lines `POST /plan` answers; `degusta plan` puts the file's name first)."""
    from degusta_learn.files.jsonio import open_regular, read_at_most

    with open_regular(path, MAX_REQUEST_BYTES, "a plan request (JSON)") as f:
        try:
            data = read_at_most(f, MAX_REQUEST_BYTES + 1)
        except OSError as e:
            raise DegustaError(f"{path}: cannot read ({e.strerror or e})") from None
    return loads_request(data)


__all__ = ["LIMITS", "MAX_REQUEST_BYTES", "At", "NewTable", "PlanRequest", "loads_request", "read_request", "too_large"]
