"""Perception pretraining data: random scenes, questions, answers and dense labels (no model needed)."""

from __future__ import annotations

import numpy as np
import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.pretrain.scenes import random_scene
from degusta_learn.pretrain.score import score_answer, summarize
from degusta_learn.pretrain.tasks import PerceptionExamples, TaskMix
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import gomo_layout
from degusta_learn.scene import default_catalog, default_tables
from degusta_learn.synth.geometry import footprint_points, inside, max_overlap, sizes_of
from degusta_learn.task.answers import parse_answer
from degusta_learn.task.prompt import ImagePart

CATALOG = default_catalog()
TABLES = {t.id: t for t in default_tables()}
GRID = Grid(8, 8)


def examples(seed=0, n=64, block=4, mix=None, size=128) -> PerceptionExamples:
    return PerceptionExamples(CATALOG, TABLES, GRID, size, seed, n, mix or TaskMix(), block=block)


def test_random_scenes_lie_on_the_surface_without_hiding_objects():
    for i in range(60):
        scene = random_scene(np.random.default_rng(i), CATALOG, TABLES)
        table = TABLES[scene.table]
        xy = np.array([[p.x, p.y] for p in scene.placements])
        rot = np.array([p.rotation for p in scene.placements])
        sizes = sizes_of([CATALOG[p.object].type for p in scene.placements])
        assert 1 <= len(scene.placements) <= 14 and len({p.object for p in scene.placements}) == len(xy)
        assert inside(table, footprint_points(xy, rot, sizes)).all()
        assert max_overlap(xy, rot, sizes) <= 0.05 + 1e-9
    assert random_scene(np.random.default_rng(3), CATALOG, TABLES) == random_scene(np.random.default_rng(3), CATALOG, TABLES)


def test_examples_are_deterministic_and_come_in_blocks_of_one_shape():
    a, b = examples(), examples()
    for i in (0, 5, 17, 40):
        ea, eb = a[i], b[i]
        assert ea.answer == eb.answer and ea.meta["task"] == eb.meta["task"]
        assert [p.encode() for p in ea.prompt.images] == [p.encode() for p in eb.prompt.images]
    for block in range(0, 64, 4):
        shapes = {a.shape_of(i) for i in range(block, block + 4)}
        assert len(shapes) == 1  # one task and one number of images per block: little padding
    assert examples(seed=1)[0].answer != a[0].answer or examples(seed=1)[0].prompt.text != a[0].prompt.text
    with pytest.raises(IndexError):
        a[64]


def test_a_curriculum_draws_its_first_examples_from_its_own_mix():
    from degusta_learn.pretrain.train import PretrainData

    short = PretrainData().curriculum_mix  # the shipped default: one scene, no sheets, no gomo
    long = TaskMix(lists=0.5, describe=0.0, gomo=0.0, locate=0.5, scenes=[0, 0, 0, 1], objects_sheet=1.0,
                   empty_table=1.0)
    ex = PerceptionExamples(CATALOG, TABLES, GRID, 128, 0, 64, long, block=4, root=None, early=(32, short))
    early, late = [ex.shape_of(i) for i in range(32)], [ex.shape_of(i) for i in range(32, 64)]
    assert {(k, sheet, empty) for _, k, sheet, empty in early} == {(1, False, False)}
    assert {task for task, *_ in early} <= {"list", "describe", "locate"}
    assert {shape for shape in late} <= {("list", 4, True, True), ("locate", 4, True, True)}
    assert len(ex[31].prompt.images) == 1 and len(ex[32].prompt.images) == 1 + 4 + 1
    # the same indices without a curriculum are the long mix's examples: a curriculum changes nothing after it
    assert examples(mix=long)[40].answer == ex[40].answer
    # every setting of an example's task comes from the mix it was drawn from (questions per describe example)
    one, several = (TaskMix(lists=0, describe=1, gomo=0, describe_questions=n) for n in (1, 3))
    ex = PerceptionExamples(CATALOG, TABLES, GRID, 128, 0, 16, one, block=4, root=None, early=(8, several))
    assert any(ex[i].followups for i in range(8)) and not any(ex[i].followups for i in range(8, 16))


def test_no_question_is_the_preference_task():
    """The base must stay zero-shot on the DegustaBot question: no preferences, no setting a table."""
    ds = examples(n=120, block=1)
    seen = set()
    for i in range(len(ds)):
        ex = ds[i]
        seen.add(ex.meta["task"])
        text = ex.prompt.text.lower()
        assert "preference" not in text and "set the table" not in text and "helping me" not in text
    assert seen == {"list", "describe", "gomo"}


def test_answers_are_what_the_named_image_shows():
    ds = examples(n=80, block=1, mix=TaskMix(lists=1, describe=1, gomo=1, scenes=[1, 1, 1, 1]))
    for i in range(len(ds)):
        ex = ds[i]
        task = ex.meta["task"]
        images = ex.prompt.images
        assert len(ex.meta["cell_labels"]) == len(images)
        if task == "gomo":
            assert ex.answer == str(ex.meta["truth_id"]) and CATALOG[int(ex.answer)].type in images[0].name
            continue
        items = parse_answer(ex.answer, "grid", CATALOG, GRID)
        assert [(it.type, it.id, it.cells, it.direction) for it in items] == [
            (t["type"], t["id"], t["cells"], t["direction"]) for t in ex.meta["truth"]]
        if task == "list":  # the question names one of the scenes, whose order line lists these types
            name = next(n for n in (f"final_state_{k}.jpg" for k in range(1, 5)) if f"object in {n}" in ex.prompt.text)
            order = next(p for p in ex.prompt.parts if isinstance(p, str) and p.startswith(f"Placement order in {name}"))
            if ex.meta["order"] == "placement":
                assert order.endswith(", ".join(it.type for it in items) + ".")
            else:  # row by row from the top left, by each object's first grid cell
                assert "row by row" in ex.prompt.parts[-1]
                firsts = [GRID.parse_cell(it.cells[0])[::-1] for it in items]
                assert firsts == sorted(firsts)
                assert sorted(order.split(": ", 1)[1].rstrip(".").split(", ")) == sorted(it.type for it in items)
            labelled = ex.meta["cell_labels"][[p.name for p in images].index(name)]
            covered = {oid for objects in labelled for oid, _ in objects}
            assert covered == {it.id for it in items}  # every object of the scene has dense labels


def test_locate_answers_the_named_objects_of_the_named_scene_in_the_order_asked():
    ds = examples(n=24, block=1, mix=TaskMix(lists=0, describe=0, gomo=0, locate=1, locate_objects=3,
                                             scenes=[1, 1, 1, 1]))
    for i in range(len(ds)):
        ex = ds[i]
        assert ex.meta["task"] == "locate" and len(ex.meta["cell_labels"]) == len(ex.prompt.images)
        question = ex.prompt.parts[-1]
        name = question.split("Where are these objects in ")[1].split(":")[0]
        asked = [(t, int(oid)) for t, oid in
                 (chunk.split(" with object_reference_id ") for chunk in
                  question.split(": ", 1)[1].split("?")[0].removeprefix("the ").split(", the "))]
        items = parse_answer(ex.answer, "grid", CATALOG, GRID)
        assert [(it.type, it.id) for it in items] == asked and 1 <= len(asked) <= 3
        labelled = ex.meta["cell_labels"][[p.name for p in ex.prompt.images].index(name)]
        for it in items:  # the cells answered are the cells the named scene's dense labels put that object in
            assert {GRID.cells[k] for k, objects in enumerate(labelled) if it.id in {o for o, _ in objects}} == set(it.cells)
    perfect = summarize([score_answer(ds[i], ds[i].answer, CATALOG, GRID) for i in range(len(ds))])
    assert perfect["cells_exact"] == 1.0 and perfect["n_locate"] == len(ds)
    with pytest.raises(DegustaError, match="data.mix.locate_objects"):
        TaskMix(locate_objects=0)


def test_transcribe_copies_the_named_scenes_written_list_as_a_preference_prompt_writes_it():
    from degusta_learn.task.prompt import Prompt
    from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt

    ds = examples(n=24, block=1, mix=TaskMix(lists=0, describe=0, gomo=0, transcribe=1, scenes=[1, 1, 1, 1]))
    for i in range(len(ds)):
        ex = ds[i]
        assert ex.meta["task"] == "transcribe" and len(ex.meta["cell_labels"]) == len(ex.prompt.images)
        texts = [p for p in ex.prompt.parts if isinstance(p, str)]
        name = ex.prompt.parts[-1].split("List every object in ")[1].split(" ")[0]
        assert "in placement order" in ex.prompt.parts[-1] and ex.meta["order"] == "placement"
        written = {t.split(",", 1)[0].removeprefix("The objects in "): t.split("written as an answer: ", 1)[1]
                   for t in texts if t.startswith("The objects in final_state_")}
        assert len(written) == ex.meta["scenes"] and written[name] == ex.answer  # the answer is the named line
        for n, line in written.items():  # each line follows its scene's order line and lists that scene's types
            at = texts.index(f"The objects in {n}, written as an answer: {line}")
            assert texts[at - 1].startswith(f"Placement order in {n}:")
            assert texts[at - 1].endswith(", ".join(it.type for it in parse_answer(line, "grid", CATALOG, GRID)) + ".")
        labelled = ex.meta["cell_labels"][[p.name for p in ex.prompt.images].index(name)]
        assert {oid for objects in labelled for oid, _ in objects} == {t["id"] for t in ex.meta["truth"]}
        # exactly the sentence a preference prompt with data.context_answers gets (adding it again changes nothing)
        again = adapt_prompt(Prompt("perception", ex.prompt.parts, context_answers={name: ex.answer}),
                             PromptOptions(context_answers=True))
        assert again.parts == ex.prompt.parts
    scores = summarize([score_answer(ds[i], ds[i].answer, CATALOG, GRID) for i in range(len(ds))])
    assert scores["transcribe_f1"] == 1.0 and scores["n_transcribe"] == len(ds) and np.isnan(scores["object_f1"])
    # a mix without the task draws the examples it drew before the task existed (shapes recorded from that code)
    before = [("locate", 2, False, False), ("locate", 1, True, False), ("locate", 1, False, True),
              ("locate", 3, True, False), ("describe", 1, False, False), ("describe", 1, False, False),
              ("list", 1, True, True), ("describe", 1, False, False), ("gomo", 1, False, False),
              ("describe", 1, False, False), ("describe", 1, False, False), ("locate", 4, False, True),
              ("list", 1, True, True), ("list", 1, False, True), ("describe", 1, False, False),
              ("describe", 1, False, False)]
    shipped = examples(mix=TaskMix(lists=0.2, describe=0.45, gomo=0.15, locate=0.2))
    assert [shipped.shape_of(i) for i in range(0, 64, 4)] == before


def test_describe_asks_several_objects_of_one_scene_each_answered_in_turn():
    ds = examples(n=12, block=1, mix=TaskMix(lists=0, describe=1, gomo=0, describe_questions=4))
    for i in range(len(ds)):
        ex = ds[i]
        turns = [(ex.prompt.parts[-1], ex.answer)] + list(ex.followups)
        labelled = ex.meta["cell_labels"][0]
        scene_ids = {oid for objects in labelled for oid, _ in objects}
        assert 1 <= len(turns) <= 4 and (len(turns) == 4 or len(turns) == len(scene_ids))
        asked = []
        for question, answer in turns:
            (item,) = parse_answer(answer, "grid", CATALOG, GRID)
            assert f"the {item.type} with object_reference_id {item.id} in final_state_1.jpg?" in question
            assert {GRID.cells[k] for k, objects in enumerate(labelled) if item.id in {o for o, _ in objects}} == set(item.cells)
            asked.append(item.id)
        assert len(set(asked)) == len(asked)  # different objects
        assert "Answer with a one-item list" in turns[0][0] and all("Answer" not in q for q, _ in turns[1:])
    assert not examples(n=4, block=1, mix=TaskMix(lists=0, describe=1, gomo=0))[0].followups  # default: one
    with pytest.raises(DegustaError, match="data.mix.describe_questions"):
        TaskMix(describe_questions=0)


def test_gomo_sheet_marks_the_asked_position():
    ds = examples(n=40, block=1, mix=TaskMix(lists=0, describe=0, gomo=1))
    ex = ds[0]
    q = ex.prompt.parts[-1]
    n = int(q.split("(")[1].split(" objects")[0])
    row = int(q.split("row ")[1].split(",")[0])
    col = int(q.split("column ")[1].split(" ")[0])
    cols, rows = gomo_layout(n)
    assert 1 <= row <= rows and 1 <= col <= cols and isinstance(ex.prompt.parts[1], ImagePart)


def test_perception_scores():
    ds = examples(n=30, block=1, mix=TaskMix(lists=1, describe=1, gomo=1))
    exs = [ds[i] for i in range(len(ds))]
    perfect = summarize([score_answer(ex, ex.answer, CATALOG, GRID) for ex in exs])
    assert all(perfect[k] == 1.0 for k in ("object_f1", "cells_exact", "direction", "mark_id", "parse_rate"))
    bad = summarize([score_answer(ex, "no idea", CATALOG, GRID) for ex in exs])
    assert bad["object_f1"] == 0.0 and bad["mark_id"] == 0.0 and bad["parse_rate"] == 0.0
    assert np.isnan(bad["cells_exact"])  # nothing named: no cell to judge
    # one wrong cell of one object: named, not exact
    ex = next(e for e in exs if e.meta["task"] == "describe")
    item = ex.meta["truth"][0]
    wrong = ex.answer.replace(f"'{item['cells'][0]}'", "'A1'" if item["cells"][0] != "A1" else "'B1'")
    row = score_answer(ex, wrong, CATALOG, GRID)
    assert row["named"] == 1 and row["cells_ok"] == 0 and 0 <= row["cell_iou"] < 1


def test_task_mix_is_checked():
    with pytest.raises(DegustaError, match="data.mix"):
        TaskMix(lists=0, describe=0, gomo=0)
    with pytest.raises(DegustaError, match="data.mix.scenes"):
        TaskMix(scenes=[1, 1])
    with pytest.raises(DegustaError, match="objects_sheet"):
        TaskMix(objects_sheet=2)
