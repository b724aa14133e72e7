"""Prompt builders for the four zero-shot DegustaBot methods (louma, logma, mouma, mogma).

A `Prompt` is an ordered list of text strings and named images (`ImagePart`). The image names are the
file-like names the task text refers to, following the paper's appendix:

- context arrangements `final_state_1.jpg` .. `final_state_K.jpg` (GMA for grid methods, UmA otherwise),
  each followed by its placement-order line (`render.lifting.order_text`);
- the empty target table `initial_state_1.jpg` (with the grid for grid methods);
- for marked-object methods (mouma, mogma) one GoMO sheet per object type, `objects_cup.jpg`, ...;
  for language-object methods (louma, logma) the catalog as JSON text (`render.lifting.oal_text`).

Backends send the parts in order (text as text, images as images) and the model never sees file names,
so every image is preceded by a text part naming it ("final_state_1.jpg:").
A `Completion` is one sampled answer to a prompt (what every backend and `vlm.generate` return).

Example:
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer
    prompt = build_prompt("mogma", ds, episode, Renderer.for_dataset(ds, size=448), Grid(8, 8))
    print(prompt.text); [p.name for p in prompt.images]
"""

from __future__ import annotations

import base64
import hashlib
import io
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.scene import Dataset, Episode

if TYPE_CHECKING:
    from degusta_learn.render.grid import Grid

from degusta_learn.names import PROMPT_METHODS  # noqa: E402  (re-exported: the four methods)

IMAGE_FORMATS = {"jpeg": ("jpg", "image/jpeg"), "png": ("png", "image/png")}
JPEG_QUALITY = 90


@dataclass
class ImagePart:
    """One named image of a prompt; `name` is how the text refers to it (e.g. "final_state_1.jpg")."""

    name: str
    image: Image.Image
    format: str = "jpeg"
    """Encoding sent to the model: "jpeg" or "png"."""
    _bytes: bytes | None = field(default=None, init=False, repr=False, compare=False)

    def encode(self) -> bytes:
        """The encoded image (cached; deterministic for a deterministic image)."""
        if self._bytes is None:
            buf = io.BytesIO()
            if self.format == "png":
                self.image.save(buf, format="PNG", optimize=False)
            else:
                self.image.convert("RGB").save(buf, format="JPEG", quality=JPEG_QUALITY)
            self._bytes = buf.getvalue()
        return self._bytes

    @property
    def mime(self) -> str:
        return IMAGE_FORMATS[self.format][1]

    def data_url(self) -> str:
        """`data:image/jpeg;base64,...` (how OpenAI-compatible servers take images)."""
        return f"data:{self.mime};base64,{base64.b64encode(self.encode()).decode('ascii')}"

    def sha256(self) -> str:
        return hashlib.sha256(self.encode()).hexdigest()


@dataclass
class Prompt:
    """A method's prompt: text and images interleaved in the order they are sent."""

    method: str
    parts: list[str | ImagePart]
    episode: str | None = None
    """The episode id (the replay backend looks answers up by it; not part of what the model sees)."""
    context_answers: dict[str, str] = field(default_factory=dict)
    """Each context image's arrangement in the answer format, by image name (`final_state_1.jpg` -> answer
    text). Not part of what the model sees unless a small model's `PromptOptions.context_answers` puts it in
    the text (`vlm.prompt_options.adapt_prompt`)."""

    @property
    def text(self) -> str:
        """All text parts joined by blank lines (what a text-only view of the prompt reads)."""
        return "\n\n".join(p for p in self.parts if isinstance(p, str))

    @property
    def images(self) -> list[ImagePart]:
        return [p for p in self.parts if isinstance(p, ImagePart)]


@dataclass
class Completion:
    """One sampled answer; token counts are this sample's share of the request (None if unknown)."""

    text: str
    input_tokens: int | None = None
    output_tokens: int | None = None
    decoding: dict | None = None
    """What a local model's decoding did to this answer (`vlm.generate`: grammar, token budget); None when
    unknown (remote APIs, answers read back from the response cache)."""


def _check_method(method: str) -> None:
    if method not in PROMPT_METHODS:
        raise DegustaError(f"method: unknown prompting method {method!r} (known: {', '.join(PROMPT_METHODS)})")


def build_prompt(method: str, ds: Dataset, episode: Episode, renderer, grid: Grid | int | None = None,
                 image_format: str = "jpeg", structured: bool = False) -> Prompt:
    """Build the prompt of `method` for one episode.

    Args:
        method: louma, logma, mouma or mogma.
        ds: the dataset (catalog, tables, arrangements).
        episode: its context trials are drawn as final_state_k, the target's table as initial_state_1.
        renderer: a `render.lifting.Renderer` (its `size` sets the image size).
        grid: a `render.grid.Grid` (or an int n for n x n); required by logma / mogma, ignored otherwise.
        image_format: "jpeg" or "png" (also sets the file extension in the names).
        structured: ask for the JSON object `{"objects": [...]}` instead of a python list
            (`backend.structured_output`; the rest of the prompt is identical).

    Returns:
        The Prompt; `prompt.images` are in the order the text refers to them.
    """
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import oal_text, order_text

    _check_method(method)
    if image_format not in IMAGE_FORMATS:
        raise DegustaError(f"image_format: expected one of {list(IMAGE_FORMATS)}, got {image_format!r}")
    ext = IMAGE_FORMATS[image_format][0]
    gridded = method in ("logma", "mogma")
    marked = method in ("mouma", "mogma")
    if isinstance(grid, int):
        grid = Grid(grid, grid)
    if gridded and grid is None:
        grid = Grid()
    catalog = ds.catalog
    target = ds.arrangement(episode.participant, episode.target)
    parts: list[str | ImagePart] = []

    def image(name: str, img: Image.Image) -> None:
        parts.append(f"{name}:")
        parts.append(ImagePart(name=name, image=img, format=image_format))

    # 1. The objects on offer.
    if marked:
        parts.append("These are the objects I have, one image per object type. Each object is marked "
                     "with its object_reference_id.")
        for type_ in catalog.types:
            image(f"objects_{type_}.{ext}", renderer.gomo(type_))
    else:
        parts.append("These are the objects I have, as JSON; each object's object_reference_id is its "
                     "\"id\" and its object_type is its \"class\":\n" + oal_text(catalog))
    # 2. The context arrangements and their placement order.
    names, answers = [], {}
    for k, trial in enumerate(episode.context, start=1):
        arr = ds.arrangement(episode.participant, trial)
        name = f"final_state_{k}.{ext}"
        names.append(name)
        img = renderer.gma(arr.table, arr.placements, grid) if gridded else renderer.uma(arr.table, arr.placements)
        image(name, img)
        parts.append(order_text(arr, catalog, name))
        answers[name] = context_answer(method, arr, catalog, grid)
    # 3. The empty target table.
    target_name = f"initial_state_1.{ext}"
    image(target_name, renderer.table(target.table, grid=grid if gridded else None))
    # 4. The task.
    parts.append(task_text(method, names, target_name, grid, catalog.types, structured=structured))
    return Prompt(method=method, parts=parts, episode=episode.id, context_answers=answers)


def context_answer(method: str, arrangement, catalog, grid: Grid | None) -> str:
    """`arrangement` written as `method`'s answer (cells and directions, or positions and rotations, with ids)."""
    from degusta_learn.task.answer_format import answer_items, format_answer
    from degusta_learn.task.answers import answer_kind

    kind = answer_kind(method)
    return format_answer(answer_items(list(arrangement.placements), catalog, kind, grid), kind)


def task_text(method: str, context_names: list[str], target_name: str, grid: Grid | None,
              types: list[str], structured: bool = False) -> str:
    """The task paragraph: the paper's appendix prompt for the method's arrangement lifting.

    With no context images the first sentence (about preference images) is replaced by one that does
    not refer to images that do not exist. With `structured` the answer-format sentences ask for the
    JSON object `{"objects": [...]}` the schema of `answers.answer_schema` describes (same keys, same
    meaning); every other sentence is unchanged.
    """
    _check_method(method)
    gridded = method in ("logma", "mogma")
    if context_names:
        shown = ", ".join(context_names[:-1]) + (" and " if len(context_names) > 1 else "") + context_names[-1]
        noun = "images" if len(context_names) > 1 else "image"
        lead = (f"My preferences for setting a table are shown in the {noun} named {shown}. You are helping "
                f"me set the table in {target_name} according to my preferences. ")
    else:
        lead = (f"You are helping me set the table in {target_name} the way I would like it. You have not "
                f"seen any of my previous table settings. ")
    text = lead + ("What objects should I place in this image, where should I place them, and how should "
                   "they be oriented? ")
    if gridded:
        last_col = chr(ord("A") + grid.cols - 1)
        text += (f"The grid over {target_name} names columns A to {last_col} from the left and rows 1 to "
                 f"{grid.rows} from the top; a grid cell id is the column letter followed by the row "
                 "number, e.g. C7. Please list all grid cells the object will intersect after it is placed. "
                 "Give the orientation as the closest cardinal direction [N, NE, E, SE, S, SW, W, NW] the "
                 "object is pointing in after it is placed. The top of the image is N. ")
        item = ("{'type': object_type, 'id': object_reference_id, 'position': [grid_cell_ids], "
                "'cardinal_direction': direction}")
        text += _answer_format(item, structured) + "Give grid_cell_ids as a list of string. "
    else:
        text += ("Give a position in [x,y] where each value is a number between 0 and 1 (x from the left "
                 "edge, y from the top edge of the image). Give rotation as the number of degrees "
                 "clockwise from image north. ")
        text += _answer_format("{'type': object_type, 'id': object_reference_id, 'position': [x, y], "
                               "'rotation': degrees}", structured)
    text += (f"object_type is one of {', '.join(types)}. Give object_id as an integer. List the objects in "
             "the order I should place them. ")
    text += ("Include only this JSON object in your response." if structured
             else "Include only this list in your response.")
    return text


def _answer_format(item: str, structured: bool) -> str:
    """The sentence giving the answer's format: the paper's python list, or the structured JSON object."""
    if not structured:
        return f"Give your answer as a python list formatted as follows: [{item}]. "
    from degusta_learn.task.answers import STRUCTURED_KEY

    item = item.replace("'", '"')
    return f'Give your answer as a JSON object formatted as follows: {{"{STRUCTURED_KEY}": [{item}]}}. '

