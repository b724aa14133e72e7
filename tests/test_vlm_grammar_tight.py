"""The answer grammar is as tight as the targets: cells distinct and row-major sorted, at most as many per
object as its footprint can cover (derived from the catalog, not hard-coded), and still every ground-truth
answer of the generated datasets is accepted."""

from __future__ import annotations

import functools
import random

import numpy as np
import pytest

from degusta_learn.render.grid import Grid, max_cells
from degusta_learn.scene import Catalog, CatalogObject, default_catalog, object_size
from degusta_learn.task.answer_format import answer_items, format_answer
from degusta_learn.task.answers import parse_answer
from degusta_learn.task.grammar import AnswerGrammar

G8 = Grid(8, 8)


@functools.cache
def generated(name: str):
    from degusta_learn.synth.naturalistic import naturalistic
    from degusta_learn.synth.simulated import simulated

    return {"naturalistic": naturalistic, "simulated": simulated}[name](0)


def item(type_: str, id_: int, cells: list[str], direction: str = "N") -> str:
    return f"{{'type': '{type_}', 'id': {id_}, 'position': [{', '.join(repr(c) for c in cells)}], " \
           f"'cardinal_direction': '{direction}'}}"


@pytest.mark.parametrize("name, kind, grid", [("naturalistic", "grid", G8), ("naturalistic", "unmarked", G8),
                                              ("simulated", "grid", G8), ("simulated", "grid", Grid(6, 6)),
                                              ("simulated", "grid", Grid(12, 10))])
def test_every_ground_truth_answer_of_a_generated_dataset_is_accepted(name, kind, grid):
    ds = generated(name)
    g = AnswerGrammar(kind, ds.catalog, grid)
    rejected, most = [], {}
    for a in ds.arrangements:
        items = answer_items(list(a.placements), ds.catalog, kind, grid)
        text = format_answer(items, kind)
        if not g.is_complete(g.feed(g.start(), text)):
            rejected.append(text)
        for it in items if kind == "grid" else ():
            most[it.type] = max(most.get(it.type, 0), len(it.cells))
    assert not rejected, f"{len(rejected)} of {len(ds.arrangements)} rejected, first: {rejected[0]}"
    if (name, kind, grid) == ("naturalistic", "grid", G8):  # as tight as the targets: the bound is reached
        assert {t: most[t] for t in ("cup", "fork", "plate", "spoon")} == {"cup": 4, "fork": 6, "plate": 9, "spoon": 6}
        assert most["knife"] == 6 and g.max_cells_of["knife"] == 7  # 7: a rare angle and offset (the footprint box)


def test_cells_must_be_distinct_and_row_major_sorted():
    g = AnswerGrammar("grid", default_catalog(), G8)
    assert g.is_complete(g.feed(g.start(), "[" + item("plate", 80, ["D4", "E4", "D5", "E5"]) + "]"))
    for cells in (["D5", "D4"], ["E4", "D4"], ["D4", "D4"], ["D5", "E4"]):  # out of order, or repeated
        assert g.feed(g.start(), "[" + item("plate", 80, cells) + "]") is None, cells
    # After the last cell of the grid no comma is offered: nothing could follow it (no dead end).
    state = g.feed(g.start(), "[{'type': 'plate', 'id': 80, 'position': ['H8'")
    assert state is not None and g.step(state, ",") is None and g.step(state, "]") is not None
    # Multi-digit rows: 'A1' may go on to 'A10' on a 12-row grid, but never back to an earlier cell.
    g12 = AnswerGrammar("grid", default_catalog(), Grid(12, 10))
    assert g12.is_complete(g12.feed(g12.start(), "[" + item("knife", 50, ["J9", "A10", "A11"]) + "]"))
    assert g12.feed(g12.start(), "[" + item("knife", 50, ["A10", "J9"]) + "]") is None


def test_cells_per_object_are_bounded_by_its_type_footprint():
    cat = default_catalog()
    g = AnswerGrammar("grid", cat, G8)
    assert g.max_cells_of == {"cup": 4, "fork": 6, "knife": 7, "plate": 9, "spoon": 6}
    cells = G8.cells
    assert g.is_complete(g.feed(g.start(), "[" + item("cup", 3, cells[:4]) + "]"))
    assert g.feed(g.start(), "[" + item("cup", 3, cells[:5]) + "]") is None  # 5 cells: no cup covers 5
    assert g.is_complete(g.feed(g.start(), "[" + item("plate", 80, cells[:9]) + "]"))
    assert g.feed(g.start(), "[" + item("plate", 80, cells[:10]) + "]") is None
    # The bound follows the footprints: a catalog whose cups are as large as plates allows 9 cells for them.
    big = Catalog(tuple(CatalogObject(i, "cup", "red", "red", "glass", "glass") for i in range(3)))
    assert AnswerGrammar("grid", big, G8).max_cells_of == {"cup": 4}
    assert AnswerGrammar("grid", big, Grid(16, 16)).max_cells_of["cup"] > 4


@pytest.mark.parametrize("rows, cols", [(8, 8), (6, 6), (12, 10)])
def test_max_cells_is_never_exceeded(rows, cols):
    """The bound holds for random placements of every type: encode never lists more."""
    grid, cat = Grid(rows, cols), default_catalog()
    rng = np.random.default_rng(rows * 100 + cols)
    for t in cat.types:
        objs = cat.of_type(t)
        bound = max_cells(*object_size(objs[0]), rows, cols)
        seen = max(len(grid.encode(objs[i % len(objs)], *rng.uniform(0.2, 0.8, 2), rng.uniform(0, 360)))
                   for i in range(400))
        assert seen <= bound, (t, seen, bound)


def test_random_walks_with_the_tight_grammar_always_end_in_a_parseable_answer():
    cat = default_catalog()
    g = AnswerGrammar("grid", cat, G8)
    alphabet = sorted(set("[]{}',: \n.0123456789_abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"))
    rng = random.Random(1)
    for _ in range(20):
        state, text = g.start(), ""
        for step in range(3000):
            if g.is_complete(state):
                break
            options = [c for c in alphabet if g.step(state, c, closing=step > 400) is not None]
            assert options, text
            # favour commas so that cell lists run into their bounds and the grid's last cells
            c = "," if "," in options and rng.random() < 0.5 else rng.choice(options)
            state, text = g.step(state, c, closing=step > 400), text + c
        assert g.is_complete(state)
        for it in parse_answer(text, "grid", cat, G8):
            assert len(it.cells) <= g.max_cells_of[it.type]
            idx = [G8.cells.index(c) for c in it.cells]
            assert idx == sorted(set(idx))
