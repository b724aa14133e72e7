"""The answer grammar as a character automaton: which text may come next in a valid answer.

It accepts exactly the canonical text of `prompting.format_answer` (optionally after a little leading
whitespace), restricted to what can be right:

    grid:      [{'type': 'plate', 'id': 17, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}, ...]
    unmarked:  [{'type': 'plate', 'id': 17, 'position': [0.52, 0.6], 'rotation': 90}, ...]

types from the catalog, ids of *that* type not placed yet (an object goes down once; `allowing_repeats()`
lifts this, for decoding that lets the model name an object again and the reader drop it), cells of the grid
as the targets list them (`Grid.encode`): distinct, in row-major order (A1, B1, ..., A2, ...), and at
most as many as an object of that type can cover anywhere on the grid (`max_cells_of`, from the catalog's
footprints by `render.grid.max_cells`: 8 x 8 grid: plate 9, knife 7, fork 6, spoon 6, cup 4), the eight
directions, coordinates in [0, 1] with up to 3 decimals, whole-degree rotations 0-359. Every accepted
text parses with `parse_answer`, and every ground-truth answer of a dataset is accepted (tested on the
generated naturalistic and simulated datasets). Bounds (`max_items`, `max_cells_of`) and `closing=True`
(used when the token budget runs low) only allow the way to the end, and the grammar has no dead ends
(a comma is allowed only where another cell or object can follow), so a constrained generation always
finishes.

A state is a plain tuple (hashable: `constrain.py` caches the allowed tokens per state).

Example:
    g = AnswerGrammar("grid", catalog, grid)
    s = g.feed(g.start(), "[{'type': 'cup', 'id': 3")    # None if the text cannot start an answer
    g.is_complete(s)                                     # False
"""

from __future__ import annotations

import copy
import re

from degusta_learn.errors import DegustaError

_COORD_PREFIX = re.compile(r"0(\.\d{0,3})?|1(\.0{0,3})?")
_COORD = re.compile(r"0|1|0\.\d{1,3}|1\.0{1,3}")
_ROT = re.compile(r"0|[1-9]\d?|[12]\d\d|3[0-5]\d")

# An item is a sequence of literal text and slots; "cells" is the ['C1', 'C2', ...] loop of a grid item.
_ITEMS = {
    "grid": (("lit", "{'type': '"), ("slot", "type"), ("lit", "', 'id': "), ("slot", "id"),
             ("lit", ", 'position': ['"), ("cells", "cell"), ("lit", "], 'cardinal_direction': '"),
             ("slot", "dir"), ("lit", "'}")),
    "unmarked": (("lit", "{'type': '"), ("slot", "type"), ("lit", "', 'id': "), ("slot", "id"),
                 ("lit", ", 'position': ["), ("slot", "coord"), ("lit", ", "), ("slot", "coord"),
                 ("lit", "], 'rotation': "), ("slot", "rot"), ("lit", "}")),
}
_WS = " \n"
_MAX_WS = 2

# state = (phase, part, off, buf, type, cells, ids): cells of the current item, ids of all items so far
#   phase "pre": leading whitespace (off = count) before "["; "item": inside item part `part`
#   (literal offset `off`, slot text `buf`); "sep": inside ", " between items (off); "next": after an
#   item's "}" (expects "," or "]"); "done": after the closing "]".
#   In a "cells" part, off is 0 in a cell id, 1 after its closing quote, 2/3 inside the ", '" separator.


class AnswerGrammar:
    """Character-level automaton of valid answers for one catalog and grid."""

    def __init__(self, kind: str, catalog, grid=None, max_items: int = 20):
        """`max_items`: the most items an answer may list (at most the catalog's size)."""
        if kind not in _ITEMS:
            raise DegustaError(f"answer kind: expected one of {list(_ITEMS)}, got {kind!r}")
        self.kind, self.parts = kind, _ITEMS[kind]
        self.max_items = min(max_items, len(catalog))
        self.types = list(catalog.types)
        self.ids = {t: [str(o.id) for o in catalog.of_type(t)] for t in self.types}
        if kind == "grid":
            from degusta_learn.render.grid import DIRECTIONS, Grid
            from degusta_learn.render.grid import max_cells as footprint_cells
            from degusta_learn.scene import object_size

            grid = grid or Grid()
            self.cells = list(grid.cells)
            self.cell_index = {c: i for i, c in enumerate(self.cells)}
            self.directions = list(DIRECTIONS)
            self.max_cells_of = {t: max(footprint_cells(*object_size(o), grid.rows, grid.cols)
                                        for o in catalog.of_type(t)) for t in self.types}
            self.max_cells = max(self.max_cells_of.values(), default=0)
            """The most cells any object may list (the largest per-type bound)."""
        self.distinct = True
        """An id may be placed once (`allowing_repeats` turns this off)."""
        self._prefixes: dict = {}
        self._cell_prefixes: dict[int, set[str]] = {}
        self._repeating: AnswerGrammar | None = None

    def allowing_repeats(self) -> AnswerGrammar:
        """This grammar with `distinct` off: an item may name an already placed object (decoding's `on_repeat:
        skip`, where the answer reader drops such an item and the list goes on). Shares the caches."""
        if not self.distinct:
            return self
        if self._repeating is None:
            self._repeating = copy.copy(self)
            self._repeating.distinct = False
        return self._repeating

    # ------------------------------------------------------------------ slots
    def _options(self, name: str, type_: str | None) -> list[str]:
        return {"type": lambda: self.types, "id": lambda: self.ids.get(type_, []),
                "dir": lambda: self.directions}[name]()

    def _prefix_ok(self, name: str, buf: str, type_: str | None, exclude=()) -> bool:
        if name == "coord":
            return buf == "" or _COORD_PREFIX.fullmatch(buf) is not None
        if name == "rot":
            return buf == "" or _ROT.fullmatch(buf) is not None
        key = (name, type_)
        if key not in self._prefixes:
            self._prefixes[key] = {o[:i] for o in self._options(name, type_) for i in range(len(o) + 1)}
        if buf not in self._prefixes[key]:
            return False
        return not exclude or any(o.startswith(buf) and o not in exclude for o in self._options(name, type_))

    def _complete(self, name: str, buf: str, type_: str | None, exclude=()) -> bool:
        if name == "coord":
            return _COORD.fullmatch(buf) is not None
        if name == "rot":
            return _ROT.fullmatch(buf) is not None
        return buf in self._options(name, type_) and buf not in exclude

    # ------------------------------------------------------------------ automaton
    def start(self) -> tuple:
        return ("pre", 0, 0, "", None, (), ())

    def is_complete(self, state) -> bool:
        return state is not None and state[0] == "done"

    def feed(self, state, text: str, closing: bool = False):
        """The state after reading `text` from `state`, or None if the text leaves the grammar."""
        for ch in text:
            state = self.step(state, ch, closing)
            if state is None:
                return None
        return state

    def step(self, state, ch: str, closing: bool = False):
        phase, part, off, buf, type_, cells, n = state  # n: ids placed so far (an object goes down once)
        if phase == "pre":
            if ch == "[":
                return ("item", 0, 0, "", None, (), n)
            return ("pre", 0, off + 1, "", None, (), n) if ch in _WS and off < _MAX_WS else None
        if phase == "next":
            if ch == "]":
                return ("done", 0, 0, "", None, (), n)
            if ch == "," and not closing and len(n) < self.max_items:
                return ("sep", 0, 1, "", None, (), n)
            return None
        if phase == "sep":  # ", " then the item's "{"
            return ("sep", 0, 2, "", None, (), n) if ch == " " and off == 1 else \
                (self._enter(0, ch, n) if off == 2 else None)
        if phase == "done":
            return None
        kind, value = self.parts[part]
        if kind == "lit":
            if ch != value[off]:
                return None
            if off + 1 < len(value):
                return ("item", part, off + 1, "", type_, cells, n)
            if part + 1 == len(self.parts):
                return ("next", 0, 0, "", None, (), n)
            return ("item", part + 1, 0, "", type_, cells, n)
        if kind == "slot":
            exclude = ()  # ids placed (an object goes down once), types all of whose objects are placed
            if self.distinct:
                exclude = n if value == "id" else self._exhausted(n) if value == "type" else ()
            if self._prefix_ok(value, buf + ch, type_, exclude):
                return ("item", part, 0, buf + ch, type_, cells, n)
            if ch == self.parts[part + 1][1][0] and self._complete(value, buf, type_, exclude):
                type_ = buf if value == "type" else type_
                n = n + (buf,) if value == "id" else n
                return self.step(("item", part + 1, 0, "", type_, cells, n), ch, closing)
            return None
        # cells loop: 'C1', 'C2'  (the opening quote of the first cell is in the literal before); each cell
        # comes after the previous one in row-major order (distinct and sorted, as `Grid.encode` lists them)
        last = self.cell_index[cells[-1]] if cells else -1
        if off == 0:
            if buf + ch in self._cells_after(last):
                return ("item", part, 0, buf + ch, type_, cells, n)
            if ch == "'" and self.cell_index.get(buf, -1) > last:
                return ("item", part, 1, "", type_, cells + (buf,), n)
            return None
        if off == 1:
            if ch == "," and not closing and len(cells) < self.max_cells_of[type_] and last + 1 < len(self.cells):
                return ("item", part, 2, "", type_, cells, n)
            return self.step(("item", part + 1, 0, "", type_, cells, n), ch, closing)
        if off == 2:
            return ("item", part, 3, "", type_, cells, n) if ch == " " else None
        return ("item", part, 0, "", type_, cells, n) if ch == "'" else None

    def id_number(self, state, text: str):
        """(the id slot's number after `text` is read from `state`, the item's type, the ids placed before it,
        whether the text goes on past the number), or None if the text never reaches an id slot. A token may carry
        the literal's last characters before the number (" 16" after "'id':")."""
        i = 0
        while state is not None and not (state[0] == "item" and self.parts[state[1]] == ("slot", "id")):
            if i == len(text):
                return None
            state, i = self.step(state, text[i]), i + 1
        if state is None:
            return None
        digits = re.match(r"\d*", text[i:]).group()
        return state[3] + digits, state[4], state[6], i + len(digits) < len(text)

    def id_named(self, state, text: str) -> str | None:
        """The id that `text`, read from `state`, names in an id slot: the slot's number once it ends there (the
        text goes on past its digits, or no id of the type that is not yet placed extends it), else None (no id
        slot, no number, not an id of the type, or the number may still grow into another id)."""
        slot = self.id_number(state, text)
        if slot is None:
            return None
        number, type_, used, goes_on = slot
        if not number or number not in self.ids.get(type_, ()):
            return None
        if goes_on:
            return number
        longer = [o for o in self.ids[type_] if o != number and o.startswith(number) and o not in used]
        return None if longer else number

    def repeats(self, state, text: str) -> bool:
        """Whether `text`, read from `state`, names again an object an earlier item placed: the id slot's number
        ends (or can only end) on an id already in the answer (`id_named`). The distinct grammar refuses such text;
        a sampler may take it as the model's sign that the list is over (`constrain.Sampler`, `on_repeat: stop`)
        or give the item the model's best id not yet placed (`on_repeat: substitute`)."""
        name = self.id_named(state, text)
        return name is not None and name in (state[6] if state is not None else ())

    def _cells_after(self, last: int) -> set[str]:
        """Every non-empty prefix of a cell id that comes after cell number `last` (row-major), cached."""
        if last not in self._cell_prefixes:
            self._cell_prefixes[last] = {c[:i] for c in self.cells[last + 1:] for i in range(1, len(c) + 1)}
        return self._cell_prefixes[last]

    def _exhausted(self, used: tuple) -> tuple:
        """Types all of whose objects are already placed (choosing one would be a dead end)."""
        return tuple(t for t in self.types if all(i in used for i in self.ids[t])) if used else ()

    def _enter(self, part: int, ch: str, n: tuple):
        return self.step(("item", part, 0, "", None, (), n), ch)

    @property
    def max_chars_to_close(self) -> int:
        """An upper bound on the characters needed to finish an answer from any state with closing=True."""
        lits = sum(len(v) for k, v in self.parts if k == "lit")
        return lits + 4 * 8 + 8  # slot values are at most 5 chars; a cell id 3; the closing "]" and slack
