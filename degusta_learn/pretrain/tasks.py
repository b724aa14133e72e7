"""Perception questions about random scenes: the pretraining examples of the tiny base VLM.

Every example is rendered on the fly from random, style-free scenes (`scenes.random_scene`) and asks a
*generic* question whose answer is in the toolkit's answer vocabulary. None of them is the DegustaBot
preference question (no "my preferences", no "set the table"), so a model pretrained on them and then
prompted with the DegustaBot prompt is zero-shot on the task. The tasks:

- ``list``: one to four grid-marked scenes named final_state_1.jpg .. final_state_K.jpg, each followed by
  its placement-order line as in the DegustaBot prompt, optionally the composed object sheets in front
  and an empty grid-marked table (initial_state_1.jpg) behind; the question names ONE of the scenes:
  "List every object in final_state_2.jpg in its placement order ..." and the answer is that scene's
  objects in the grid answer format (type, id, the cells the footprint intersects, the direction).
- ``describe``: one scene; "Find the cup with object_reference_id 17 in final_state_1.jpg ..." and the
  answer is a one-item list (its cells and direction); with `mix.describe_questions` > 1, further such
  questions about other objects of the scene follow as new user turns, each answered in turn.
- ``locate``: like ``list`` (1-4 scenes, optional sheets and empty table) but the question names up to
  `mix.locate_objects` objects of one scene by type and id, in random order: "Where are these objects in
  final_state_2.jpg: the cup with object_reference_id 17, the fork with ...?" and the answer lists them
  in the order asked. Every object is a retrieval (find that id in that image, copy its cells and
  direction): many answers per rendered image, the skill the preference task needs to carry a context
  arrangement onto a new table.
- ``transcribe``: the ``list`` prompt with each scene's arrangement also written in the answer format after its
  placement-order line (the sentence `modality: both` adds to a preference prompt), and the
  ``list`` question in placement order about one of them: the answer is that scene's written list, copied.
  Reading a list from the prompt and writing it out again, item by item to its end, is what a preference
  prompt with the context tables written out asks of the decoder.
- ``gomo``: one GoMO sheet of a random subset of one type's objects in random order, so a position on
  the sheet says nothing about an id without looking; "Which object_reference_id is marked on the
  object in row 2, column 3 ...?" and the answer is the integer.

`PerceptionExamples` maps a global index to an example deterministically (seed, index), so training is
reproducible and resumable, any DataLoader worker renders the same example, and the validation and
benchmark streams (other seeds) are images the model never trained on. Consecutive indices come in
blocks of `block` examples of the same task and number of images, so a batch has little padding.
An example's meta holds, per image, the objects covering each grid cell (`cell_labels`, None for the
sheets) and which of those images the answer is about (`asked_image`), the targets of the dense loss,
the oracle teacher and the attention supervision (`dense.py`, `retrieval.py`).

Example:
    ex = PerceptionExamples(catalog, tables, grid=Grid(8, 8), render_size=256, seed=0, length=1000)[0]
    ex.prompt.parts, ex.answer, ex.meta["task"]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.finetune.data import Example
from degusta_learn.pretrain.scenes import random_scene
from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt

TASKS = ("list", "describe", "gomo", "locate", "transcribe")  # new tasks go last: earlier draws stay
GRID_FORMAT = ("[{'type': object_type, 'id': object_reference_id, 'position': [grid_cell_ids], "
               "'cardinal_direction': direction}]")
_DIRECTIONS_TEXT = "[N, NE, E, SE, S, SW, W, NW]"


@dataclass
class TaskMix:
    """How often each perception task is drawn (relative weights), and the shape of `list` prompts."""

    lists: float = 0.7
    """Weight of `list` questions (one named scene among 1-4, answered in the grid format)."""
    describe: float = 0.15
    """Weight of `describe` questions (one object of one scene by type and id)."""
    gomo: float = 0.15
    """Weight of `gomo` questions (the id marked at a row and column of a GoMO sheet)."""
    locate: float = 0.0
    """Weight of `locate` questions (several objects of one named scene by type and id, answered in that order)."""
    transcribe: float = 0.0
    """Weight of `transcribe` questions (a `list` prompt with every scene also written as an answer; the asked
    scene's written list is the answer)."""
    locate_objects: int = 8
    """The most objects one `locate` question asks about (all of the scene's when it has fewer)."""
    describe_questions: int = 1
    """How many `describe` questions one example asks about its scene (different objects, up to all of the
    scene's), each answered before the next is asked: the first in the prompt, the others as follow-up turns
    (`Example.followups`). Several one-object questions on one image teach the decoder to find an id among the
    image tokens far sooner than one."""
    scenes: list[float] = field(default_factory=lambda: [0.4, 0.2, 0.15, 0.25])
    """Relative weights of 1, 2, 3, 4 scenes in a `list` prompt."""
    reading_order: float = 0.5
    """Probability that a `list` question asks for reading order (by first cell) instead of placement order."""
    objects_sheet: float = 0.5
    """Probability that a `list` prompt starts with the composed object sheets (as DegustaBot prompts do)."""
    empty_table: float = 0.5
    """Probability that a `list` prompt ends with an empty grid-marked table (initial_state_1.jpg)."""

    def __post_init__(self):
        weights = [self.lists, self.describe, self.gomo, self.locate, self.transcribe]
        if any(w < 0 for w in weights) or sum(weights) <= 0:
            raise DegustaError("data.mix: task weights must be >= 0 and not all 0")
        if len(self.scenes) != 4 or any(w < 0 for w in self.scenes) or sum(self.scenes) <= 0:
            raise DegustaError("data.mix.scenes: expected 4 weights >= 0 (for 1, 2, 3, 4 scenes), not all 0")
        for key in ("locate_objects", "describe_questions"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise DegustaError(f"data.mix.{key}: expected an integer >= 1, got {value!r}")
        for key in ("reading_order", "objects_sheet", "empty_table"):
            if not 0 <= getattr(self, key) <= 1:
                raise DegustaError(f"data.mix.{key}: expected a probability in [0, 1], got {getattr(self, key)}")

    def probabilities(self) -> np.ndarray:
        w = np.array([self.lists, self.describe, self.gomo, self.locate, self.transcribe], dtype=float)
        return w / w.sum()


def list_question(name: str, types: list[str], reading: bool = False) -> str:
    order = "row by row from the top left (by the first grid cell it covers)" if reading else "in placement order"
    return (f"List every object in {name} {order}, each as {{'type': object_type "
            f"({', '.join(types)}), 'id': object_reference_id, 'position': [the grid cells it covers], "
            f"'cardinal_direction': the closest of {_DIRECTIONS_TEXT} it points to, the top being N}}.")


def describe_question(name: str, type_: str, object_id: int, followup: bool = False) -> str:
    """The question about one object; a follow-up (a later turn about the same image) is its short form."""
    question = f"Where is the {type_} with object_reference_id {object_id} in {name}?"
    if followup:
        return question
    return f"{question} Answer with a one-item list {GRID_FORMAT}, 'position' being the grid cells it covers."


def locate_question(name: str, objects: list[tuple[str, int]]) -> str:
    named = ", ".join(f"the {type_} with object_reference_id {object_id}" for type_, object_id in objects)
    return (f"Where are these objects in {name}: {named}? Answer with a list {GRID_FORMAT} in the order asked, "
            "'position' being the grid cells each covers.")


def gomo_question(name: str, type_: str, n: int, row: int, col: int) -> str:
    return (f"Which object_reference_id is marked on the {type_} in row {row}, column {col} of {name} "
            f"({n} objects, rows from the top, columns from the left)? Give only the integer.")


class PerceptionExamples:
    """A map-style dataset: global index -> perception `Example` (see the module docstring)."""

    def __init__(self, catalog, tables: dict, grid, render_size: int, seed: int, length: int,
                 mix: TaskMix | None = None, block: int = 8, root=None, early: tuple[int, TaskMix] | None = None):
        """`early`: (n, mix) draws examples 0 .. n-1 from `mix` instead (a curriculum's first steps)."""
        self.catalog, self.tables, self.grid = catalog, dict(tables), grid
        self.render_size, self.seed, self.length = render_size, seed, length
        self.mix, self.block, self.root = mix or TaskMix(), max(1, block), root
        self.early = early
        self.types = list(catalog.types)
        self._renderer = None

    def __len__(self) -> int:
        return self.length

    @property
    def renderer(self):
        if self._renderer is None:
            from degusta_learn.render.lifting import Renderer

            self._renderer = Renderer(self.catalog, self.tables, self.root, size=self.render_size)
        return self._renderer

    def __getstate__(self):  # DataLoader workers build their own renderer (sprite caches)
        return {**self.__dict__, "_renderer": None}

    def mix_at(self, i: int) -> TaskMix:
        """The mix example i is drawn from: the curriculum's (`early`) for its first examples, else `mix`."""
        return self.early[1] if self.early is not None and i < self.early[0] else self.mix

    def shape_of(self, i: int) -> tuple[str, int, bool, bool]:
        """(task, scenes, objects sheet, empty table) shared by the block of index i."""
        rng = np.random.default_rng([self.seed, 1, i // self.block])
        m = self.mix_at(i)
        task = TASKS[int(rng.choice(len(TASKS), p=m.probabilities()))]
        k = 1 + int(rng.choice(4, p=np.asarray(m.scenes, float) / sum(m.scenes)))
        sheet, empty = bool(rng.random() < m.objects_sheet), bool(rng.random() < m.empty_table)
        if task not in ("list", "locate", "transcribe"):
            return task, 1, False, False
        return task, k, sheet, empty

    def __getitem__(self, i: int) -> Example:
        if not 0 <= i < self.length:
            raise IndexError(i)
        task, k, sheet, empty = self.shape_of(i)
        rng = np.random.default_rng([self.seed, 2, i])
        build = {"list": self._list, "describe": self._describe, "gomo": self._gomo, "locate": self._locate,
                 "transcribe": self._transcribe}[task]
        parts, answer, meta = build(rng, self.mix_at(i), k, sheet, empty)
        from degusta_learn.task.prompt import Prompt
        meta["task"] = task
        return Example(episode=f"perception/{self.seed}/{i}", prompt=Prompt("perception", parts, f"perception/{i}"),
                       answer=answer, meta=meta, followups=tuple(meta.pop("followups", ())))

    # ------------------------------------------------------------------ tasks
    def _scene_parts(self, scene, name: str, labels: list) -> list:
        """The "name:" label, the GMA image and the order line of a scene; its cell labels go to `labels`."""
        from degusta_learn.render.lifting import order_text
        from degusta_learn.task.prompt import ImagePart

        image = self.renderer.gma(scene.table, scene.placements, self.grid)
        labels.append(self.cell_labels(scene.placements))
        return [f"{name}:", ImagePart(name=name, image=image), order_text(scene, self.catalog, name)]

    def cell_labels(self, placements) -> list[list[tuple[int, str]]]:
        """Per grid cell (row-major), the (id, direction) of every object whose footprint covers it: exactly
        the cells the answer format lists, so image token k of an 8 x 8 token grid stands for cell k."""
        from degusta_learn.render.grid import rotation_to_direction

        cells: list[list[tuple[int, str]]] = [[] for _ in range(self.grid.rows * self.grid.cols)]
        for p in placements:
            for cell in self.grid.encode(self.catalog[p.object], p.x, p.y, p.rotation):
                col, row = self.grid.parse_cell(cell)
                cells[row * self.grid.cols + col].append((p.object, rotation_to_direction(p.rotation)))
        return cells

    def _first_cell(self, p) -> tuple[int, int, float]:
        """Reading-order key: (row, column) of the first cell an object covers, then its x."""
        col, row = self.grid.parse_cell(self.grid.encode(self.catalog[p.object], p.x, p.y, p.rotation)[0])
        return row, col, p.x

    def _truth(self, placements) -> tuple[str, list[dict]]:
        from degusta_learn.task.answer_format import answer_items, format_answer
        items = answer_items(list(placements), self.catalog, "grid", self.grid)
        truth = [{"type": it.type, "id": it.id, "cells": list(it.cells), "direction": it.direction} for it in items]
        return format_answer(items, "grid"), truth

    def _scenes(self, rng, k: int, sheet: bool, empty: bool):
        """The parts of a prompt with k random scenes (see `list`), their cell labels and the scenes."""
        from degusta_learn.task.prompt import ImagePart
        parts: list = []
        labels: list = []
        if sheet:
            parts += self._object_sheets()
            labels.append(None)  # the composed sheets have no grid cells
        scenes = [random_scene(rng, self.catalog, self.tables, trial=j) for j in range(k)]
        for j, scene in enumerate(scenes, start=1):
            parts += self._scene_parts(scene, f"final_state_{j}.jpg", labels)
        if empty:
            table = sorted(self.tables)[int(rng.integers(len(self.tables)))]
            parts += ["initial_state_1.jpg:", ImagePart("initial_state_1.jpg", self.renderer.table(table, self.grid))]
            labels.append(self.cell_labels(()))
        return parts, labels, scenes

    def _list(self, rng, mix: TaskMix, k: int, sheet: bool, empty: bool):
        parts, labels, scenes = self._scenes(rng, k, sheet, empty)
        asked = int(rng.integers(k))
        name = f"final_state_{asked + 1}.jpg"
        reading = bool(rng.random() < mix.reading_order)
        parts.append(list_question(name, self.types, reading))
        placements = scenes[asked].placements
        if reading:
            placements = sorted(placements, key=lambda p: self._first_cell(p))
        answer, truth = self._truth(placements)
        return parts, answer, {"truth": truth, "scenes": k, "cell_labels": labels,
                               "asked_image": int(sheet) + asked, "order": "reading" if reading else "placement"}

    def _locate(self, rng, mix: TaskMix, k: int, sheet: bool, empty: bool):
        parts, labels, scenes = self._scenes(rng, k, sheet, empty)
        asked = int(rng.integers(k))
        name = f"final_state_{asked + 1}.jpg"
        placements = scenes[asked].placements
        chosen = [placements[j] for j in rng.permutation(len(placements))[:mix.locate_objects]]
        parts.append(locate_question(name, [(self.catalog[p.object].type, p.object) for p in chosen]))
        answer, truth = self._truth(chosen)
        return parts, answer, {"truth": truth, "scenes": k, "cell_labels": labels, "asked_image": int(sheet) + asked}

    def _transcribe(self, rng, mix: TaskMix, k: int, sheet: bool, empty: bool):
        from degusta_learn.task.prompt import Prompt
        parts, labels, scenes = self._scenes(rng, k, sheet, empty)
        truths = [self._truth(scene.placements) for scene in scenes]  # (answer text, truth items) per scene
        written = {f"final_state_{j}.jpg": text for j, (text, _) in enumerate(truths, start=1)}
        parts = adapt_prompt(Prompt("perception", parts, context_answers=written),
                             PromptOptions(modality="both")).parts
        asked = int(rng.integers(k))
        parts.append(list_question(f"final_state_{asked + 1}.jpg", self.types))
        answer, truth = truths[asked]
        return parts, answer, {"truth": truth, "scenes": k, "cell_labels": labels,
                               "asked_image": int(sheet) + asked, "order": "placement"}

    def _object_sheets(self) -> list:
        from degusta_learn.task.prompt import ImagePart, Prompt
        parts: list = ["These are the objects I have, one image per object type. Each object is marked with "
                       "its object_reference_id."]
        for t in self.types:
            parts += [f"objects_{t}.jpg:", ImagePart(f"objects_{t}.jpg", self.renderer.gomo(t))]
        return adapt_prompt(Prompt("perception", parts), PromptOptions(compose=["objects"])).parts

    def _describe(self, rng, mix: TaskMix, k: int, sheet: bool, empty: bool):
        scene = random_scene(rng, self.catalog, self.tables)
        name = "final_state_1.jpg"
        n, placements = min(mix.describe_questions, len(scene.placements)), scene.placements
        if n == 1:  # one question: the draw the single-question examples have always made
            asked = [placements[int(rng.integers(len(placements)))]]
        else:
            asked = [placements[j] for j in rng.permutation(len(placements))[:n]]
        questions = [describe_question(name, self.catalog[p.object].type, p.object, followup=j > 0)
                     for j, p in enumerate(asked)]
        answers = [self._truth([p]) for p in asked]
        labels: list = []
        parts = self._scene_parts(scene, name, labels) + [questions[0]]
        return parts, answers[0][0], {"truth": answers[0][1], "cell_labels": labels, "asked_image": 0,
                                      "followups": [(q, a) for q, (a, _) in zip(questions[1:], answers[1:])]}

    def _gomo(self, rng, mix: TaskMix, k: int, sheet: bool, empty: bool):
        from degusta_learn.render.lifting import gomo_layout
        from degusta_learn.task.prompt import ImagePart

        type_ = self.types[int(rng.integers(len(self.types)))]
        pool = self.catalog.of_type(type_)
        n = int(rng.integers(min(4, len(pool)), len(pool) + 1))
        objs = [pool[j] for j in rng.permutation(len(pool))[:n]]
        name = f"objects_{type_}.jpg"
        cols, _ = gomo_layout(n)
        pick = int(rng.integers(n))
        row, col = divmod(pick, cols)
        parts = [f"{name}:", ImagePart(name, self.renderer.gomo_sheet(type_, objs)),
                 gomo_question(name, type_, n, row + 1, col + 1)]
        return parts, str(objs[pick].id), {"truth_id": objs[pick].id, "cell_labels": [None]}
