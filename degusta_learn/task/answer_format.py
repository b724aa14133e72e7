"""Answers written out: the canonical answer text, a plan as answer items, and the structured-output JSON schema.

`format_answer(items, kind)` writes the text `answers.parse_answer` reads back (`parse_answer(format_answer(x)) ==
x`); `answer_items` turns placements into the items an answer would list (the cells a footprint covers, the
direction it points); `answer_schema` is the JSON schema of `{"objects": [...]}` built from the same definitions the
parser checks (answers.ANSWER_KEYS, object types, catalog ids by type, grid cells, directions, [0, 1] positions).

Example:
    text = format_answer(answer_items(placements, catalog, "grid", Grid(8, 8)), "grid")
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from degusta_learn.errors import DegustaError
from degusta_learn.task.answers import ANSWER_KEYS, KINDS, MAX_ENUM_VALUES, STRUCTURED_KEY, AnswerItem

if TYPE_CHECKING:
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import Catalog, Placement


def answer_schema(kind: str, catalog: Catalog, grid: Grid | None = None) -> dict:
    """The JSON schema of a structured answer `{"objects": [item, ...]}` (OpenAI strict-mode subset).

    Built from the parser's own definitions: an item is one branch per object type (`anyOf`, the type
    first as the discriminator) whose `id` enum holds only that type's catalog ids, so a schema-conforming
    item is never "id 75 is a plate, not a cup"; grid items list cells of `grid` (enum) and one of the
    8 `DIRECTIONS`, unmarked items a position [x, y] in [0, 1] and a rotation in [0, 360]. Every object
    has `additionalProperties: false` and lists all its properties as required (strict mode's rules).
    What no JSON schema says (an id given by two items) stays with the item policy: the later item is
    dropped, the answer still parses. Deterministic for a given catalog and grid (it is part of the
    cache key).
    """
    from degusta_learn.render.grid import DIRECTIONS, Grid

    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    grid = grid or Grid()
    types = list(catalog.types)
    ids = {t: sorted(o.id for o in catalog if o.type == t) for t in types}
    n_cells = grid.rows * grid.cols
    n_enum = len(types) + sum(len(v) for v in ids.values()) + (len(types) * len(DIRECTIONS) if kind == "grid" else 0)
    cells_as_enum = kind == "grid" and n_enum + len(types) * n_cells <= MAX_ENUM_VALUES
    ids_as_enum = n_enum + (len(types) * n_cells if cells_as_enum else 0) <= MAX_ENUM_VALUES
    if kind == "grid":
        if cells_as_enum:
            cell = {"type": "string", "enum": [grid.cell_id(c, r) for r in range(grid.rows) for c in range(grid.cols)]}
        else:
            rows = "|".join(str(r) for r in range(grid.rows, 0, -1))
            cell = {"type": "string", "pattern": f"^[A-{chr(ord('A') + grid.cols - 1)}](?:{rows})$"}
        rest = {"position": {"type": "array", "items": cell, "minItems": 1, "maxItems": n_cells},
                "cardinal_direction": {"type": "string", "enum": list(DIRECTIONS)}}
    else:
        rest = {"position": {"type": "array", "items": {"type": "number", "minimum": 0, "maximum": 1},
                             "minItems": 2, "maxItems": 2},
                "rotation": {"type": "number", "minimum": 0, "maximum": 360}}
    branches = []
    for t in types:
        oid = ({"type": "integer", "enum": ids[t]} if ids_as_enum
               else {"type": "integer", "minimum": min(ids[t]), "maximum": max(ids[t])})
        props = {"type": {"type": "string", "enum": [t]}, "id": oid, **rest}
        assert tuple(props) == ANSWER_KEYS[kind]
        branches.append({"type": "object", "properties": props, "required": list(props),
                         "additionalProperties": False})
    items = branches[0] if len(branches) == 1 else {"anyOf": branches}
    return {"type": "object",
            "properties": {STRUCTURED_KEY: {"type": "array", "items": items,
                                            "description": "the objects to place, in placement order"}},
            "required": [STRUCTURED_KEY], "additionalProperties": False}


def format_answer_json(items: list[AnswerItem], kind: str) -> str:
    """A structured answer as the JSON text a schema-constrained model emits (tests, replays)."""

    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    out = []
    for it in items:
        if kind == "grid":
            out.append({"type": it.type, "id": int(it.id), "position": list(it.cells or []),
                        "cardinal_direction": it.direction})
        else:
            out.append({"type": it.type, "id": int(it.id), "position": [float(v) for v in it.position],
                        "rotation": float(it.rotation)})
    return json.dumps({STRUCTURED_KEY: out})


# ----------------------------------------------------------------------------- formatting

def _num(v: float) -> str:
    s = repr(float(v))
    return s[:-2] if s.endswith(".0") else s


def format_answer(items: list[AnswerItem], kind: str) -> str:
    """The canonical answer text (what a fine-tuned model is trained to emit).

    Example: `[{'type': 'plate', 'id': 17, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}]`.
    Numbers are written exactly (shortest repr), so round positions first for short targets.
    """
    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    out = []
    for it in items:
        if kind == "grid":
            cells = ", ".join(f"'{c}'" for c in it.cells or [])
            out.append(f"{{'type': '{it.type}', 'id': {int(it.id)}, 'position': [{cells}], "
                       f"'cardinal_direction': '{it.direction}'}}")
        else:
            x, y = it.position
            out.append(f"{{'type': '{it.type}', 'id': {int(it.id)}, 'position': [{_num(x)}, {_num(y)}], "
                       f"'rotation': {_num(it.rotation)}}}")
    return "[" + ", ".join(out) + "]"


def answer_items(placements: list[Placement], catalog: Catalog, kind: str, grid: Grid | None = None,
                 decimals: int = 3) -> list[AnswerItem]:
    """The items a perfect answer would give for `placements` (fine-tuning targets, tests).

    Grid answers get the cells of each rotated footprint (`grid.encode`) and the nearest direction;
    unmarked answers get x, y rounded to `decimals` and the rotation rounded to whole degrees.
    """
    from degusta_learn.render.grid import Grid, rotation_to_direction

    grid = grid or Grid()
    items = []
    for p in placements:
        obj = catalog[p.object]
        if kind == "grid":
            items.append(AnswerItem(type=obj.type, id=obj.id, cells=grid.encode(obj, p.x, p.y, p.rotation),
                                    direction=rotation_to_direction(p.rotation)))
        else:
            items.append(AnswerItem(type=obj.type, id=obj.id, position=(round(p.x, decimals), round(p.y, decimals)),
                                    rotation=float(round(p.rotation)) % 360.0))
    return items
