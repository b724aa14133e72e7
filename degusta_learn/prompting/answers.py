"""Parse and format model answers (python-list-like text), never executing model text.

Grid methods (logma, mogma) answer
    [{'type': 'plate', 'id': 17, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}, ...]
and unmarked methods (louma, mouma)
    [{'type': 'plate', 'id': 17, 'position': [0.5, 0.62], 'rotation': 90}, ...].

`parse_answer` reads that with a small tokenizer + recursive-descent parser for list/dict/string/number
literals (no `eval`, no `ast.literal_eval`). Tolerated: code fences, prose around the list, single,
double or typographic quotes (and backticks, which the paper's own prompt uses), trailing commas,
`direction` for `cardinal_direction`, lower-case or spaced grid cells ("d4"), object ids given as
digit strings ("17"), an empty list (an answer that places nothing). Everything else raises
`AnswerParseError(reason)`: no list, unknown or missing keys, an id not in the catalog, an id whose
catalog type differs from `type` (we reject rather than guess which of the two the model meant),
cells off the grid, unknown directions, positions outside [0, 1], non-finite numbers.

Example:
    items = parse_answer(text, "grid", catalog, Grid(8, 8))
    format_answer(items, "grid")   # canonical text; parse_answer(format_answer(x)) == x
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from degusta_learn.errors import DegustaError

if TYPE_CHECKING:
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import Catalog, Placement

KINDS = ("grid", "unmarked")
_QUOTES = str.maketrans({"\u2018": "'", "\u2019": "'", "\u201a": "'", "\u201b": "'", "\u2032": "'", "`": "'",
                         "\u201c": '"', "\u201d": '"', "\u201e": '"', "\u201f": '"', "\u2033": '"'})
_FENCE = re.compile(r"```[ \t]*[A-Za-z0-9_+-]*[ \t]*\n?(.*?)```", re.S)
_TOKEN = re.compile(r"""\s*(?:(?P<punct>[\[\]{}:,])|(?P<str>'(?:[^'\\\n]|\\.)*'|"(?:[^"\\\n]|\\.)*")"""
                    r"""|(?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)|(?P<other>\S))""")
_KEYS = {"grid": ("type", "id", "position", "cardinal_direction"), "unmarked": ("type", "id", "position", "rotation")}


@dataclass
class AnswerItem:
    """One step of a model's task plan (grid answers fill cells/direction, unmarked ones position/rotation)."""

    type: str
    id: int
    cells: list[str] | None = None
    direction: str | None = None
    position: tuple[float, float] | None = None
    rotation: float | None = None


class AnswerParseError(ValueError):
    """A model answer that cannot be read; the message is the reason (counted as a failure)."""


def answer_kind(method: str) -> str:
    """"grid" for logma / mogma, "unmarked" for louma / mouma."""
    kinds = {"logma": "grid", "mogma": "grid", "louma": "unmarked", "mouma": "unmarked"}
    if method not in kinds:
        raise DegustaError(f"method: no answer format for {method!r} (known: {', '.join(kinds)})")
    return kinds[method]


# ----------------------------------------------------------------------------- literal parsing

class _Parser:
    """Recursive descent over tokens of a python/JSON literal: lists, dicts, strings, numbers."""

    def __init__(self, text: str, pos: int):
        self.text, self.pos = text, pos

    def _next(self) -> tuple[str, str]:
        m = _TOKEN.match(self.text, self.pos)
        if m is None:
            return "end", ""
        self.pos = m.end()
        kind = m.lastgroup or "end"
        return kind, m.group(kind) if kind != "end" else ""

    def _peek(self) -> tuple[str, str]:
        pos = self.pos
        tok = self._next()
        self.pos = pos
        return tok

    def value(self) -> Any:
        kind, tok = self._next()
        if kind == "punct" and tok == "[":
            return self._seq("]", lambda: self.value())
        if kind == "punct" and tok == "{":
            return dict(self._seq("}", self._pair))
        if kind == "str":
            return _unescape(tok[1:-1])
        if kind == "num":
            return float(tok) if any(c in tok for c in ".eE") else int(tok)
        raise AnswerParseError(f"unexpected {tok!r} in the list" if tok else "the list is not closed")

    def _pair(self) -> tuple[Any, Any]:
        key = self.value()
        kind, tok = self._next()
        if tok != ":":
            raise AnswerParseError(f"expected ':' after key {key!r}")
        return key, self.value()

    def _seq(self, close: str, item) -> list:
        out = []
        while True:
            if self._peek()[1] == close:  # empty sequence or trailing comma
                self._next()
                return out
            out.append(item())
            kind, tok = self._next()
            if tok == close:
                return out
            if tok != ",":
                raise AnswerParseError(f"expected ',' or '{close}', got {tok!r}" if tok else "the list is not closed")


def _unescape(s: str) -> str:
    return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), s)


def _extract_list(text: str) -> list:
    """The first `[...]` literal in the text whose items are dicts (or that is empty)."""
    fenced = [b for b in _FENCE.findall(text) if "[" in b]
    body = (fenced[0] if fenced else text).translate(_QUOTES)
    first_error = None
    for m in re.finditer(r"\[\s*[{\]]", body):
        try:
            value = _Parser(body, m.start()).value()
        except AnswerParseError as e:
            first_error = first_error or e
            continue
        if isinstance(value, list) and all(isinstance(v, dict) for v in value):
            return value
    if first_error is not None:
        raise first_error
    raise AnswerParseError("no list of objects found in the answer")


# ----------------------------------------------------------------------------- validation

def parse_answer(text: str, kind: str, catalog: Catalog, grid: Grid | None = None) -> list[AnswerItem]:
    """Read a model answer into validated items (see the module docstring for what is tolerated).

    Args:
        text: the model's raw answer.
        kind: "grid" or "unmarked" (`answer_kind(method)`).
        catalog: ids are checked against it (and their type against `type`).
        grid: the `render.grid.Grid` cells are checked against (grid kind only; default 8 x 8).

    Raises:
        AnswerParseError: with the reason, for anything that is not a valid answer.
    """
    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    if not isinstance(text, str):
        raise AnswerParseError(f"the answer is not text ({type(text).__name__})")
    if kind == "grid" and grid is None:
        from degusta_learn.render.grid import Grid
        grid = Grid()
    return [_item(raw, i, kind, catalog, grid) for i, raw in enumerate(_extract_list(text))]


def _item(raw: dict, i: int, kind: str, catalog: Catalog, grid: Grid | None) -> AnswerItem:
    def fail(msg: str) -> AnswerParseError:
        return AnswerParseError(f"item {i}: {msg}")

    d: dict[str, Any] = {}
    for key, value in raw.items():
        k = str(key).strip().lower()
        if kind == "grid" and k == "direction":
            k = "cardinal_direction"
        if k not in _KEYS[kind]:
            raise fail(f"unknown key {str(key)!r} (expected {', '.join(_KEYS[kind])})")
        if k in d:
            raise fail(f"key {k!r} given twice")
        d[k] = value
    for k in _KEYS[kind]:
        if k not in d:
            raise fail(f"missing key {k!r}")
    type_ = d["type"]
    if not isinstance(type_, str):
        raise fail(f"type must be a string, got {type_!r}")
    type_ = type_.strip().lower()
    if type_ not in catalog.types:
        raise fail(f"unknown object type {d['type']!r} (expected one of {', '.join(catalog.types)})")
    oid = d["id"]
    if isinstance(oid, str) and re.fullmatch(r"\s*\d+\s*", oid):
        oid = int(oid)
    if not isinstance(oid, int) or isinstance(oid, bool):
        raise fail(f"id must be an integer, got {oid!r}")
    if oid not in catalog:
        raise fail(f"unknown object id {oid}")
    if catalog[oid].type != type_:
        raise fail(f"id {oid} is a {catalog[oid].type}, not a {type_}")
    if kind == "grid":
        return AnswerItem(type=type_, id=oid, cells=_cells(d["position"], grid, fail),
                          direction=_direction(d["cardinal_direction"], fail))
    pos = d["position"]
    if not (isinstance(pos, list) and len(pos) == 2 and all(_is_num(v) for v in pos)):
        raise fail(f"position must be [x, y] with two numbers, got {pos!r}")
    x, y = float(pos[0]), float(pos[1])
    if not (0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
        raise fail(f"position {pos!r} is outside [0, 1]")
    rot = d["rotation"]
    if not _is_num(rot):
        raise fail(f"rotation must be a number of degrees, got {rot!r}")
    return AnswerItem(type=type_, id=oid, position=(x, y), rotation=float(rot) % 360.0)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _cells(value: Any, grid: Grid, fail) -> list[str]:
    if not isinstance(value, list) or not value:
        raise fail(f"position must be a non-empty list of grid cell ids, got {value!r}")
    out: list[str] = []
    for c in value:
        if not isinstance(c, str):
            raise fail(f"grid cell ids must be strings, got {c!r}")
        try:
            cell = grid.cell_id(*grid.parse_cell(c))
        except DegustaError:
            raise fail(f"{c!r} is not a cell of the {grid.cols}x{grid.rows} grid") from None
        if cell not in out:
            out.append(cell)
    return out


def _direction(value: Any, fail) -> str:
    from degusta_learn.render.grid import DIRECTIONS

    d = value.strip().upper() if isinstance(value, str) else None
    if d not in DIRECTIONS:
        raise fail(f"unknown cardinal direction {value!r} (expected one of {', '.join(DIRECTIONS)})")
    return d


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
