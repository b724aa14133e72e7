"""Answer parsing: every tolerance, every rejection (with its reason), round trips, and no code execution."""

from __future__ import annotations

import ast

import pytest

from degusta_learn.render.grid import Grid
from degusta_learn.scene import Placement, default_catalog
from degusta_learn.task.answer_format import answer_items, format_answer
from degusta_learn.task.answers import AnswerItem, AnswerParseError, answer_kind, parse_answer

CAT = default_catalog()
G = Grid(8, 8)
PLATE = CAT.of_type("plate")[0].id   # 75
CUP = CAT.of_type("cup")[0].id       # 0
GOOD = [AnswerItem("plate", PLATE, cells=["D4", "D5"], direction="N"),
        AnswerItem("cup", CUP, cells=["F3"], direction="NE")]


def grid(text):
    return parse_answer(text, "grid", CAT, G)


@pytest.mark.parametrize("text", [
    f"[{{'type': 'plate', 'id': {PLATE}, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}}, "
    f"{{'type': 'cup', 'id': {CUP}, 'position': ['F3'], 'cardinal_direction': 'NE'}}]",
    # code fence with a language tag, prose around
    f"Sure! Here is my plan:\n```python\n[{{'type': 'plate', 'id': {PLATE}, 'position': ['D4', 'D5'], "
    f"'cardinal_direction': 'N'}}, {{'type': 'cup', 'id': {CUP}, 'position': ['F3'], "
    f"'cardinal_direction': 'NE'}}]\n```\nI hope that's what you wanted.",
    # prose (with apostrophes and brackets) around, no fence; JSON double quotes
    f"I'd put [the plate] first: [{{\"type\": \"plate\", \"id\": {PLATE}, \"position\": [\"D4\", \"D5\"], "
    f"\"cardinal_direction\": \"N\"}}, {{\"type\": \"cup\", \"id\": {CUP}, \"position\": [\"F3\"], "
    f"\"cardinal_direction\": \"NE\"}}] -- that's it.",
    # typographic quotes, backticks (as in the paper's prompt), trailing commas, `direction`,
    # lower-case and spaced cells, ids as strings, lower-case direction
    f"[{{\u2018type\u2019: \u2018plate\u2019, `id': \u201c{PLATE}\u201d, 'position': ['d4', ' D5 ',], "
    f"'direction': 'n',}}, {{'Type': 'Cup', 'id': '{CUP}', 'position': ['f3'], 'cardinal_direction': 'ne'}},]",
    # a first list that is the prompt's template (not an answer) is skipped
    f"Format: [{{'type':object_type, 'id': object_reference_id}}]\n[{{'type': 'plate', 'id': {PLATE}, "
    f"'position': ['D4', 'D5', 'D4'], 'cardinal_direction': 'N'}}, {{'type': 'cup', 'id': {CUP}, "
    f"'position': ['F3'], 'cardinal_direction': 'NE'}}]",
])
def test_grid_tolerances(text):
    assert grid(text) == GOOD


def test_unmarked_answer_and_rotation_wraps():
    items = parse_answer(f"[{{'type': 'plate', 'id': {PLATE}, 'position': [0.25, 1], 'rotation': -90}}]",
                         "unmarked", CAT)
    assert items == [AnswerItem("plate", PLATE, position=(0.25, 1.0), rotation=270.0)]


def test_empty_list_is_an_answer_that_places_nothing():
    assert grid("```\n[]\n```") == []


@pytest.mark.parametrize("text, reason", [
    ("I cannot help with that.", "no list of objects"),
    ("[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}", "not closed"),
    ("[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N', 'why': 'x'}]", "unknown key 'why'"),
    ("[{'type': 'plate', 'position': ['D4'], 'cardinal_direction': 'N'}]", "missing key 'id'"),
    ("[{'type': 'plate', 'id': 999, 'position': ['D4'], 'cardinal_direction': 'N'}]", "unknown object id 999"),
    ("[{'type': 'cup', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]", "id 75 is a plate, not a cup"),
    ("[{'type': 'bowl', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]", "unknown object type"),
    ("[{'type': 'plate', 'id': 75.5, 'position': ['D4'], 'cardinal_direction': 'N'}]", "id must be an integer"),
    ("[{'type': 'plate', 'id': 'seventy', 'position': ['D4'], 'cardinal_direction': 'N'}]", "id must be an integer"),
    ("[{'type': 'plate', 'id': 75, 'position': ['I9'], 'cardinal_direction': 'N'}]", "not a cell of the 8x8 grid"),
    ("[{'type': 'plate', 'id': 75, 'position': 'D4', 'cardinal_direction': 'N'}]", "non-empty list of grid cell"),
    ("[{'type': 'plate', 'id': 75, 'position': [], 'cardinal_direction': 'N'}]", "non-empty list of grid cell"),
    ("[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'up'}]", "unknown cardinal direction"),
    ("[{'type': 'plate', 'id': 75, 'position': ['D4'], 'rotation': 0}]", "unknown key 'rotation'"),
    ("[{'type': 'plate', 'id': 75, 'position': ['D4'], 'direction': 'N', 'cardinal_direction': 'N'}]", "given twice"),
    ("[{'type': 'plate', 'id': __import__('os'), 'position': ['D4'], 'cardinal_direction': 'N'}]", "unexpected"),
])
def test_grid_rejections_name_the_reason(text, reason):
    with pytest.raises(AnswerParseError, match=reason):
        grid(text)


@pytest.mark.parametrize("text, reason", [
    ("[{'type': 'plate', 'id': 75, 'position': [1.5, 0.2], 'rotation': 0}]", "outside"),
    ("[{'type': 'plate', 'id': 75, 'position': [0.5], 'rotation': 0}]", "two numbers"),
    ("[{'type': 'plate', 'id': 75, 'position': ['0.5', 0.5], 'rotation': 0}]", "two numbers"),
    ("[{'type': 'plate', 'id': 75, 'position': [0.5, 0.5], 'rotation': 'N'}]", "rotation must be a number"),
    ("[{'type': 'plate', 'id': 75, 'position': [0.5, 0.5], 'rotation': 1e999}]", "rotation must be a number"),
    ("[{'type': 'plate', 'id': 75, 'position': ['D4'], 'cardinal_direction': 'N'}]", "unknown key 'cardinal"),
])
def test_unmarked_rejections(text, reason):
    with pytest.raises(AnswerParseError, match=reason):
        parse_answer(text, "unmarked", CAT)


def test_model_text_is_never_executed(tmp_path):
    marker = tmp_path / "pwned"
    text = f"[{{'type': 'plate', 'id': __import__('os').system('touch {marker}'), 'position': ['D4'], " \
           f"'cardinal_direction': 'N'}}]"
    with pytest.raises(AnswerParseError):
        grid(text)
    assert not marker.exists()


def test_format_is_a_python_literal_and_round_trips():
    text = format_answer(GOOD, "grid")
    assert text.startswith("[{'type': 'plate', 'id': 75, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}")
    # reference reader we did not write: Python's literal parser
    assert ast.literal_eval(text)[1] == {"type": "cup", "id": CUP, "position": ["F3"], "cardinal_direction": "NE"}
    assert grid(text) == GOOD
    unmarked = [AnswerItem("knife", 50, position=(0.123456789, 0.5), rotation=90.0)]
    text = format_answer(unmarked, "unmarked")
    assert ast.literal_eval(text) == [{"type": "knife", "id": 50, "position": [0.123456789, 0.5], "rotation": 90}]
    assert parse_answer(text, "unmarked", CAT) == unmarked


def test_answer_items_of_a_placement_round_trip():
    placements = [Placement(PLATE, 0.5, 0.5, 0.0), Placement(60, 0.7, 0.5, 95.0)]
    g = answer_items(placements, CAT, "grid", G)
    assert g[0].cells == G.encode(CAT[PLATE], 0.5, 0.5, 0.0) and g[1].direction == "E"
    assert grid(format_answer(g, "grid")) == g
    u = answer_items(placements, CAT, "unmarked")
    assert u[1] == AnswerItem("knife", 60, position=(0.7, 0.5), rotation=95.0)
    assert parse_answer(format_answer(u, "unmarked"), "unmarked", CAT) == u


def test_answer_kind():
    assert [answer_kind(m) for m in ("louma", "logma", "mouma", "mogma")] == ["unmarked", "grid", "unmarked", "grid"]
    with pytest.raises(Exception, match="no answer format"):
        answer_kind("random")
