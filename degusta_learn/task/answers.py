"""Parse and format model answers (python-list-like text), never executing model text.

Grid methods (logma, mogma) answer
    [{'type': 'plate', 'id': 17, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}, ...]
and unmarked methods (louma, mouma)
    [{'type': 'plate', 'id': 17, 'position': [0.5, 0.62], 'rotation': 90}, ...].

`parse_answer` reads that with a small tokenizer + recursive-descent parser for list/dict/string/number
literals (no `eval`, no `ast.literal_eval`). Tolerated: code fences, prose around the list, single,
double or typographic quotes (and backticks, which the paper's own prompt uses), trailing commas,
`direction` for `cardinal_direction`, lower-case or spaced grid cells ("d4"), object ids given as
digit strings ("17"), an empty list (an answer that places nothing).

Item policy: an item that is wrong on its own (unknown or missing keys, an id not in the catalog, an id
whose catalog type differs from `type` -- we reject rather than guess which of the two the model meant --,
an id already given by an earlier item, cells off the grid, unknown directions, positions outside [0, 1],
non-finite or absurdly long numbers, a non-object in the list) is DROPPED and its reason kept
(`read_answer(...).item_errors`); the answer fails only when no item is valid. The answer as a whole
fails (`AnswerParseError(reason)`) when there is no list, it is not closed, it is nested deeper than
`MAX_DEPTH`, longer than `MAX_CHARS`, or not text. Any other error met while reading model text
(RecursionError, ValueError, OverflowError, TypeError, ...) also becomes an `AnswerParseError` with a
short reason: model text never raises anything else.

Structured outputs (`backend.structured_output: true`): the model answers the JSON object
`{"objects": [<the same items>]}` constrained by `answer_schema(kind, catalog, grid)`, a JSON schema
built from the same definitions this parser checks (keys, object types, catalog ids by type, grid cells,
directions, [0, 1] positions). `read_answer` accepts that object (anywhere, in any mode) into the same
items under the same item policy, and still reads a free-text list (a server that ignores the schema).

Example:
    items = parse_answer(text, "grid", catalog, Grid(8, 8))       # valid items (bad ones dropped)
    answer = read_answer(text, "grid", catalog, Grid(8, 8))       # .items and .item_errors

Writing answers (`format_answer`, `answer_items`) and the structured-output schema (`answer_schema`) are in
answer_format.py.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from degusta_learn.errors import DegustaError

if TYPE_CHECKING:
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import Catalog

KINDS = ("grid", "unmarked")
_QUOTES = str.maketrans({"\u2018": "'", "\u2019": "'", "\u201a": "'", "\u201b": "'", "\u2032": "'", "`": "'",
                         "\u201c": '"', "\u201d": '"', "\u201e": '"', "\u201f": '"', "\u2033": '"'})
_FENCE = re.compile(r"```[ \t]*[A-Za-z0-9_+-]*[ \t]*\n?(.*?)```", re.S)
_TOKEN = re.compile(r"""\s*(?:(?P<punct>[\[\]{}:,])|(?P<str>'(?:[^'\\\n]|\\.)*'|"(?:[^"\\\n]|\\.)*")"""
                    r"""|(?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)|(?P<other>\S))""")
MAX_CHARS = 200_000
"""Longer answers fail as a whole (max_tokens keeps real answers far below this)."""
MAX_DEPTH = 16
"""Deepest list/dict nesting read (an answer needs 3)."""
MAX_NUMBER_CHARS = 40
"""Longest number literal read (longer ones are an item error, never a huge int or float)."""
MAX_CANDIDATES = 32
"""Most `[{` starts tried when looking for the answer list."""
MAX_REASON_CHARS = 200
ANSWER_KEYS = {"grid": ("type", "id", "position", "cardinal_direction"), "unmarked": ("type", "id", "position", "rotation")}
STRUCTURED_KEY = "objects"
"""The key of the list in a structured answer `{"objects": [...]}` (providers want an object at top level)."""
STRUCTURED_NAME = "degusta_answer"
"""The schema's name (OpenAI `json_schema.name`, the Anthropic tool's name)."""
MAX_ENUM_VALUES = 600
"""Most enum values a schema lists (OpenAI strict allows 1,000 in all); past it, cells become a pattern
and ids a [min, max] range (the item policy still drops what the looser schema lets through)."""
_WRAPPER = re.compile(r"\{\s*['\"](" + STRUCTURED_KEY + r")['\"]\s*:", re.I)
REPEATED = "was already placed by an earlier item"
"""The reason an item naming an object an earlier item placed is dropped (`is_repeat` tells it apart)."""


def is_repeat(reason: str) -> bool:
    """Whether an item error `reason` is a repeated object (decoding's `on_repeat: skip` writes them on purpose)."""
    return REPEATED in reason


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
        self.text, self.pos, self.depth = text, pos, 0

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
        if kind == "punct" and tok in "[{":
            if self.depth >= MAX_DEPTH:
                raise AnswerParseError(f"nested deeper than {MAX_DEPTH} levels")
            self.depth += 1
            try:
                if tok == "[":
                    return self._seq("]", self.value)
                out: dict = {}
                for key, value in self._seq("}", self._pair):
                    if key in out:  # a repeated key: keep the first value, flag the item
                        out[(_REPEATED, key)] = True
                    else:
                        out[key] = value
                return out
            finally:
                self.depth -= 1
        if kind == "str":
            return _unescape(tok[1:-1])
        if kind == "num":
            if len(tok) > MAX_NUMBER_CHARS:
                return _BadNumber(tok)
            return float(tok) if any(c in tok for c in ".eE") else int(tok)
        raise AnswerParseError(f"unexpected {_short(tok)} in the list" if tok else "the list is not closed")

    def _pair(self) -> tuple[Any, Any]:
        key = self.value()
        kind, tok = self._next()
        if tok != ":":
            raise AnswerParseError(f"expected ':' after key {_short(key)}")
        if not isinstance(key, (str, int, float)):  # a list or dict as a key: keep it as (unknown) text
            key = _BadKey(_short(key))
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
                raise AnswerParseError(f"expected ',' or '{close}', got {_short(tok)}" if tok
                                       else "the list is not closed")


class _BadNumber(str):
    """A number literal too long to convert (kept as text; any item using it is an item error)."""

    def __repr__(self) -> str:
        return f"a {len(self)}-character number"


class _BadKey(str):
    """A key that was a list or dict (unhashable): kept as its short text, an unknown key."""


_REPEATED = object()  # (_REPEATED, key) marks a key given twice in one object


def _short(v: Any, limit: int = 60) -> str:
    """repr(v), cut to `limit` characters (reasons stay one short line whatever the model wrote)."""
    try:
        r = repr(v)
    except Exception:  # a repr that fails (e.g. int too large to print)
        r = f"<{type(v).__name__}>"
    return r if len(r) <= limit else r[:limit - 3] + "..."


def _unescape(s: str) -> str:
    return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), s)


def _extract_list(text: str) -> list:
    """The items of the first `{"objects": [...]}` object (a structured answer), else the first `[...]`
    literal in the text whose items are dicts (or that is empty)."""
    fenced = [b for b in _FENCE.findall(text) if "[" in b]
    body = (fenced[0] if fenced else text).translate(_QUOTES)
    for n, m in enumerate(_WRAPPER.finditer(body)):
        if n >= MAX_CANDIDATES:
            break
        try:
            value = _Parser(body, m.start()).value()
        except AnswerParseError:
            continue  # not a readable object: the list search below reports why
        items = value.get(m.group(1)) if isinstance(value, dict) else None
        if isinstance(items, list) and all(isinstance(v, dict) for v in items):
            return items
    first_error = None
    for n, m in enumerate(re.finditer(r"\[\s*[{\]]", body)):
        if n >= MAX_CANDIDATES:
            break
        if body[m.end() - 1] == "]":  # an empty list inside a literal ([[]], {'a': []}) is not an answer
            before = body[:m.start()]
            last = before.rstrip()[-1:]
            if last in ("[", ",", "{") or (last == ":" and before.count("{") > before.count("}")):
                continue
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

@dataclass
class Answer:
    """A read answer: the valid items in order and, for each dropped item, `item N: reason`."""

    items: list[AnswerItem]
    item_errors: list[str] = field(default_factory=list)

    @property
    def n_read(self) -> int:
        """Items the model gave (valid + dropped)."""
        return len(self.items) + len(self.item_errors)


def read_answer(text: Any, kind: str, catalog: Catalog, grid: Grid | None = None) -> Answer:
    """Read a model answer: valid items plus the reasons bad items were dropped (see the module docstring).

    Args:
        text: the model's raw answer (anything: a non-string is a failure, not an exception).
        kind: "grid" or "unmarked" (`answer_kind(method)`).
        catalog: ids are checked against it (and their type against `type`).
        grid: the `render.grid.Grid` cells are checked against (grid kind only; default 8 x 8).

    Raises:
        AnswerParseError: with a short reason, when the answer has no valid item (an empty list is valid).
        DegustaError: only for a bad `kind` (a caller's mistake, not the model's).
    """
    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    if kind == "grid" and grid is None:
        from degusta_learn.render.grid import Grid
        grid = Grid()
    try:
        answer = _read(text, kind, catalog, grid)
    except AnswerParseError as e:
        raise AnswerParseError(_clip(str(e))) from None
    except RecursionError:
        raise AnswerParseError("the answer is nested too deeply to read") from None
    except MemoryError:
        raise AnswerParseError("the answer is too large to read") from None
    except Exception as e:  # ValueError, OverflowError, TypeError, ...: model text never raises these
        raise AnswerParseError(_clip(f"unreadable answer ({type(e).__name__}: {e})")) from None
    return answer


def parse_answer(text: Any, kind: str, catalog: Catalog, grid: Grid | None = None) -> list[AnswerItem]:
    """The valid items of a model answer (bad items dropped; see `read_answer` for their reasons).

    Raises:
        AnswerParseError: with the reason, when the answer has no valid item.
    """
    return read_answer(text, kind, catalog, grid).items


def _clip(reason: str) -> str:
    reason = " ".join(reason.split())
    return reason if len(reason) <= MAX_REASON_CHARS else reason[:MAX_REASON_CHARS - 3] + "..."


def _read(text: Any, kind: str, catalog: Catalog, grid: Grid | None) -> Answer:
    if not isinstance(text, str):
        raise AnswerParseError(f"the answer is not text ({type(text).__name__})")
    if len(text) > MAX_CHARS:
        raise AnswerParseError(f"the answer is {len(text)} characters long (at most {MAX_CHARS} are read)")
    raw_items = _extract_list(text)
    items: list[AnswerItem] = []
    errors: list[str] = []
    seen: set[int] = set()
    for i, raw in enumerate(raw_items):
        try:
            item = _item(raw, i, kind, catalog, grid)
            if item.id in seen:
                raise AnswerParseError(f"item {i}: id {item.id} {REPEATED}")
        except AnswerParseError as e:
            errors.append(_clip(str(e)))
            continue
        except (RecursionError, MemoryError, ValueError, OverflowError, TypeError, ArithmeticError) as e:
            errors.append(_clip(f"item {i}: unreadable ({type(e).__name__})"))
            continue
        seen.add(item.id)
        items.append(item)
    if raw_items and not items:
        shown = "; ".join(errors[:3]) + (f"; ... ({len(errors)} items)" if len(errors) > 3 else "")
        raise AnswerParseError(f"no valid item ({shown})" if len(errors) > 1 else errors[0])
    return Answer(items, errors)


def _item(raw: Any, i: int, kind: str, catalog: Catalog, grid: Grid | None) -> AnswerItem:
    def fail(msg: str) -> AnswerParseError:
        return AnswerParseError(f"item {i}: {msg}")

    if not isinstance(raw, dict):
        raise fail(f"expected an object, got {_short(raw)}")
    d: dict[str, Any] = {}
    for key, value in raw.items():
        if isinstance(key, tuple) and key and key[0] is _REPEATED:
            raise fail(f"key {_short(key[1])} given twice")
        k = str(key).strip().lower() if isinstance(key, str) else _short(key)
        if kind == "grid" and k == "direction":
            k = "cardinal_direction"
        if k not in ANSWER_KEYS[kind]:
            raise fail(f"unknown key {_short(str(key))} (expected {', '.join(ANSWER_KEYS[kind])})")
        if k in d:
            raise fail(f"key {k!r} given twice")
        d[k] = value
    for k in ANSWER_KEYS[kind]:
        if k not in d:
            raise fail(f"missing key {k!r}")
    type_ = d["type"]
    if not isinstance(type_, str) or isinstance(type_, _BadNumber):
        raise fail(f"type must be a string, got {_short(type_)}")
    type_ = type_.strip().lower()
    if type_ not in catalog.types:
        raise fail(f"unknown object type {_short(d['type'])} (expected one of {', '.join(catalog.types)})")
    oid = d["id"]
    if isinstance(oid, str) and not isinstance(oid, _BadNumber) and re.fullmatch(r"\s*\d{1,12}\s*", oid):
        oid = int(oid)
    if not isinstance(oid, int) or isinstance(oid, bool):
        raise fail(f"id must be an integer, got {_short(oid)}")
    if oid not in catalog:
        raise fail(f"unknown object id {_short(oid)}")
    if catalog[oid].type != type_:
        raise fail(f"id {oid} is a {catalog[oid].type}, not a {type_}")
    if kind == "grid":
        return AnswerItem(type=type_, id=oid, cells=_cells(d["position"], grid, fail),
                          direction=_direction(d["cardinal_direction"], fail))
    pos = d["position"]
    if not (isinstance(pos, list) and len(pos) == 2 and all(_is_num(v) for v in pos)):
        raise fail(f"position must be [x, y] with two numbers, got {_short(pos)}")
    x, y = float(pos[0]), float(pos[1])
    if not (0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
        raise fail(f"position {_short(pos)} is outside [0, 1]")
    rot = d["rotation"]
    if not _is_num(rot):
        raise fail(f"rotation must be a number of degrees, got {_short(rot)}")
    return AnswerItem(type=type_, id=oid, position=(x, y), rotation=float(rot) % 360.0)


def _is_num(v: Any) -> bool:
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v) and abs(float(v)) < 1e12
    except (OverflowError, ValueError):
        return False


def _cells(value: Any, grid: Grid, fail) -> list[str]:
    if not isinstance(value, list) or not value:
        raise fail(f"position must be a non-empty list of grid cell ids, got {_short(value)}")
    if len(value) > grid.rows * grid.cols:
        raise fail(f"position lists {len(value)} cells, more than the grid has")
    out: list[str] = []
    for c in value:
        if not isinstance(c, str) or isinstance(c, _BadNumber):
            raise fail(f"grid cell ids must be strings, got {_short(c)}")
        try:
            if len(c) > 12:
                raise DegustaError("too long")
            cell = grid.cell_id(*grid.parse_cell(c))
        except DegustaError:
            raise fail(f"{_short(c)} is not a cell of the {grid.cols}x{grid.rows} grid") from None
        if cell not in out:
            out.append(cell)
    return out


def _direction(value: Any, fail) -> str:
    from degusta_learn.render.grid import DIRECTIONS

    d = value.strip().upper() if isinstance(value, str) and len(value) < 20 else None
    if d not in DIRECTIONS:
        raise fail(f"unknown cardinal direction {_short(value)} (expected one of {', '.join(DIRECTIONS)})")
    return d


# ----------------------------------------------------------------------------- the answer's JSON schema
