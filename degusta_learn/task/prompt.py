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

Two prompt styles (`PROMPT_STYLES`; the same images in the same order, only the text differs):
- `clarified` (the default): the appendix prompt with cell naming, the object types, the coordinate convention
  and the placement-order request added, a preamble line before the objects, and its own context-0 sentence
  (`task_text`);
- `paper`: the appendix prompts verbatim (`PAPER_PROMPTS`, `paper_task_text`), no preamble lines.

How the context tables are shown (`MODALITIES`, `with_modality`; `build_prompt(modality=...)`, a predict config's
`modality`, a fine-tuning config's `data.modality`; the same text style, images and order otherwise):
- `images`: each context table as its image with its placement-order line (the paper's prompt);
- `text`: each context table written out in the answer format after its placement-order line
  (`CONTEXT_ANSWER_LINE`, the text of `Prompt.context_answers`); the context images and their "name:" labels are
  left out, not blanked (the prompt's text still names final_state_k.jpg: the table's name, written as text);
- `both`: the images and the text.

A `Completion` is one sampled answer to a prompt (what every backend and `vlm.generate` return).

Example:
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer
    prompt = build_prompt("mogma", ds, episode, Renderer.for_dataset(ds, size=448), Grid(8, 8))
    print(prompt.text); [p.name for p in prompt.images]
"""

from __future__ import annotations

import base64
import dataclasses
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
PROMPT_STYLES = ("clarified", "paper")
"""The prompt texts `build_prompt` writes (`prompt_style` of a predict config): see the module docstring."""
MODALITIES = ("images", "text", "both")
MODALITY_RENAMED = ("modality, at the top level of a predict config (the old context_answers: true was both, "
                    "images + text; false was images; null: as the model was trained)")
"""How a prompt shows the context tables (`modality` of predict configs, `data.modality` of fine-tuning): as images,
written as text only, or both (module docstring)."""
CONTEXT_ANSWER_LINE = "The objects in {name}, written as an answer: {answer}"
"""The sentence that writes a context table out (modalities text and both), after its placement-order line."""

PAPER_PROMPTS = {
    "objects_as_language": (
        "My preferences for setting a table are shown in the first images. You are helping me set the table in the "
        "final image according to my preferences. What objects should I place in this image, where should I place "
        "them, and how should they be oriented? Give a position in [x,y] where each value is a number between 0 and "
        "1. Give rotation as the number of degrees clockwise from image north. Give your answer as a python list "
        "formatted as follows: [{'type':object_type, 'id': object_reference_id, 'position': [x, y], 'rotation': "
        "degrees}]. Give object_id as an integer. Include only this list in your response."),
    "unmarked": (
        "My preferences for setting a table are shown in the images named final_state_K.jpg. You are helping me set "
        "the table in initial_state_1.jpg according to my preferences. What objects should I place in this image, "
        "where should I place them, and how should they be oriented? Give a position in [x,y] where each value is a "
        "number between 0 and 1. Give rotation as the number of degrees clockwise from image north. Give your answer "
        "as a python list formatted as follows: [{'type':object_type, 'id': object_reference_id, 'position': [x, y], "
        "'rotation': degrees}]. Give object_id as an integer. Include only this list in your response."),
    "grid": (
        "My preferences for setting a table are shown in the images named final_state_N.jpg. You are helping me set "
        "the table in initial_state_1.jpg according to my preferences. What objects should I place in this image, "
        "where should I place them, and how should they be oriented? Please list all grid cells the object will "
        "intersect after it is placed. Give the orientation as the closest cardinal direction [N, NE, E, SE, S, SW, "
        "W, NW] the object is pointing in after it is placed. The top of the image is N. Give your answer as a python "
        "list formatted as follows: [{'type':object_type, 'id': object_reference_id, 'position':[grid_cell_ids], "
        "'cardinal_direction':direction}]. Give grid_cell_ids as a list of string. Give object_id as an integer. "
        "Include only this list in your response."),
}
"""The three prompts of the paper's appendix ("Prompts": Objects as Language, Unmarked Arrangements, Grid Marked
Arrangements) as plain text: the `spverbatim` blocks with surrounding whitespace stripped and every quote mark
written as ' (the appendix mixes `type', 'type' and typographic quotes inside one python dict: typesetting, not
content). `final_state_K.jpg` / `final_state_N.jpg` are the appendix's placeholders for the context images."""
_QUESTION = "What objects should I place in this image, where should I place them, and how should they be oriented? "


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
    text). Part of what the model sees only in modalities text and both (`with_modality`)."""
    style: str = "clarified"
    """The text's style (`PROMPT_STYLES`): what the dry run and the predictions' diagnostics report."""
    modality: str | None = None
    """How the context tables are shown (`MODALITIES`, `with_modality`); None: not chosen yet (the images, as
    `build_prompt` draws them, until `with_modality` or `vlm.prompt_options.adapt_prompt` chooses)."""

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


def check_style(style: str, key: str = "prompt_style") -> None:
    """Refuse a prompt style that is not one of `PROMPT_STYLES` (one line naming `key`)."""
    if style not in PROMPT_STYLES:
        raise DegustaError(f"{key}: expected one of {list(PROMPT_STYLES)}, got {style!r}")


def check_modality(modality: str, key: str = "modality") -> None:
    """Refuse a modality that is not one of `MODALITIES` (one line naming `key`)."""
    if modality not in MODALITIES:
        raise DegustaError(f"{key}: expected one of {list(MODALITIES)}, got {modality!r}")


def build_prompt(method: str, ds: Dataset, episode: Episode, renderer, grid: Grid | int | None = None,
                 image_format: str = "jpeg", structured: bool = False, style: str = "clarified",
                 modality: str | None = None) -> Prompt:
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
        style: "clarified" (`task_text`, a preamble line before the objects) or "paper" (`paper_task_text`, the
            objects with no preamble: the GoMO sheets alone, or the catalog JSON alone). Both keep the images, their
            order, the "name:" label before each image (the paper's text names final_state_k.jpg and
            initial_state_1.jpg, which a model only sees written out) and each context image's placement-order line
            (the paper includes the placement order in the prompt without giving its wording).
        modality: how the context tables are shown (`with_modality`: images, text or both); None: the images,
            the modality left to choose (a local model's `PromptOptions`, applied by `adapt_prompt`).

    Returns:
        The Prompt; `prompt.images` are in the order the text refers to them.
    """
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import oal_text, order_text

    _check_method(method)
    check_style(style, "style")
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

    paper = style == "paper"
    # 1. The objects on offer.
    if marked:
        if not paper:
            parts.append("These are the objects I have, one image per object type. Each object is marked "
                         "with its object_reference_id.")
        for type_ in catalog.types:
            image(f"objects_{type_}.{ext}", renderer.gomo(type_))
    elif paper:
        parts.append(oal_text(catalog))
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
    if paper:
        parts.append(paper_task_text(method, names, target_name, structured=structured))
    else:
        parts.append(task_text(method, names, target_name, grid, catalog.types, structured=structured))
    prompt = Prompt(method=method, parts=parts, episode=episode.id, context_answers=answers, style=style)
    return prompt if modality is None else with_modality(prompt, modality)


def with_modality(prompt: Prompt, modality: str) -> Prompt:
    """`prompt` with its context tables shown as `modality` says (module docstring), `prompt.modality` set.

    text and both add each context table's `CONTEXT_ANSWER_LINE` right after its placement-order line (a line
    already there is not added twice); text then leaves out the context images with their "name:" labels. Only the
    context tables change: the objects, the target table and the task text are the same in every modality. A
    prompt whose modality is chosen already is returned as it is if it is the same, refused if not.
    """
    check_modality(modality, "modality")
    if prompt.modality is not None:
        if prompt.modality != modality:
            raise DegustaError(f"modality: this prompt shows its context tables as {prompt.modality!r} already; "
                               f"build it again for {modality!r}")
        return prompt
    parts = list(prompt.parts)
    if modality in ("text", "both"):
        parts = _with_context_lines(parts, prompt.context_answers)
    if modality == "text":
        drop = {i for i, p in enumerate(parts) if isinstance(p, ImagePart) and p.name in prompt.context_answers}
        drop |= {i - 1 for i in drop if i and parts[i - 1] == f"{parts[i].name}:"}  # their "name:" labels
        parts = [p for i, p in enumerate(parts) if i not in drop]
    return dataclasses.replace(prompt, parts=parts, modality=modality)


def _with_context_lines(parts: list, answers: dict[str, str]) -> list:
    """`parts` with each context image's `CONTEXT_ANSWER_LINE` after its placement-order line (`build_prompt` puts
    that line right after the image); unchanged if the lines are there already."""
    lines = {name: CONTEXT_ANSWER_LINE.format(name=name, answer=text) for name, text in answers.items()}
    if set(lines.values()) & {p for p in parts if isinstance(p, str)}:
        return parts  # already there (e.g. a perception prompt that writes its scenes out itself)
    out: list = []
    for i, part in enumerate(parts):
        out.append(part)
        if isinstance(part, ImagePart) and part.name in answers:
            after = parts[i + 1] if i + 1 < len(parts) else None
            if not (isinstance(after, str) and after.startswith(f"Placement order in {part.name}:")):
                raise DegustaError(f"prompt: context image {part.name} is not followed by its placement-order line")
        elif i and isinstance(parts[i - 1], ImagePart) and parts[i - 1].name in answers:
            out.append(lines[parts[i - 1].name])
    return out


def context_answer(method: str, arrangement, catalog, grid: Grid | None) -> str:
    """`arrangement` written as `method`'s answer (cells and directions, or positions and rotations, with ids)."""
    from degusta_learn.task.answer_format import answer_items, format_answer
    from degusta_learn.task.answers import answer_kind

    kind = answer_kind(method)
    return format_answer(answer_items(list(arrangement.placements), catalog, kind, grid), kind)


def task_text(method: str, context_names: list[str], target_name: str, grid: Grid | None,
              types: list[str], structured: bool = False) -> str:
    """The task paragraph of the `clarified` style: the paper's appendix prompt for the method's arrangement lifting
    (Unmarked or Grid Marked Arrangements) with cell naming, the object types, the coordinate convention and the
    placement-order request added.

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


def paper_task_text(method: str, context_names: list[str], target_name: str, structured: bool = False) -> str:
    """The task paragraph of the `paper` style: the appendix prompt of the method, verbatim (`PAPER_PROMPTS`).

    - louma: the Objects as Language prompt, whole.
    - mouma: the Unmarked Arrangements prompt, whole; mogma: the Grid Marked Arrangements prompt, whole.
    - logma (no prompt of its own in the appendix): the Objects as Language prompt up to its question (objects as
      language, the images referred to as "the first images" and "the final image"), then the Grid Marked
      Arrangements prompt from "Please list all grid cells" to its end (cells and directions, the answer the
      method's grid-marked arrangements ask for).

    Substitutions, only where the appendix writes a placeholder or a file name:
    - `final_state_K.jpg` / `final_state_N.jpg`: the context images' names joined by ", " (final_state_1.jpg,
      final_state_2.jpg, ...); with no context image the placeholder is left as the appendix writes it (the
      appendix has no zero-context prompt).
    - `initial_state_1.jpg`: `target_name` (the same name unless the images are PNG: initial_state_1.png).
    - `structured`: "Give your answer as a python list formatted as follows: [ITEM]." becomes "Give your answer as
      a JSON object formatted as follows: {"objects": [ITEM]}." (ITEM in double quotes) and "Include only this list
      in your response." becomes "Include only this JSON object in your response.": the JSON the schema of
      `answers.answer_schema` forces; every other sentence is unchanged.
    """
    _check_method(method)
    objects_as_language = method in ("louma", "logma")
    gridded = method in ("logma", "mogma")
    own = PAPER_PROMPTS["grid" if gridded else "unmarked"]
    if objects_as_language:
        oal = PAPER_PROMPTS["objects_as_language"]
        text = oal[:oal.index(_QUESTION)] + own[own.index(_QUESTION):] if gridded else oal
    else:
        placeholder = "final_state_N.jpg" if gridded else "final_state_K.jpg"
        text = own.replace(placeholder, ", ".join(context_names)) if context_names else own
        text = text.replace("initial_state_1.jpg", target_name)
    if structured:
        start = text.index("Give your answer as a python list")
        end = text.index("]. ", start) + len("]. ")
        item = text[text.index("[{", start) + 1:end - len("]. ")]
        text = text[:start] + _answer_format(item, True) + text[end:]
        text = text.replace("Include only this list in your response.",
                            "Include only this JSON object in your response.")
    return text


def _answer_format(item: str, structured: bool) -> str:
    """The sentence giving the answer's format: the paper's python list, or the structured JSON object."""
    if not structured:
        return f"Give your answer as a python list formatted as follows: [{item}]. "
    from degusta_learn.task.answers import STRUCTURED_KEY

    item = item.replace("'", '"')
    return f'Give your answer as a JSON object formatted as follows: {{"{STRUCTURED_KEY}": [{item}]}}. '

