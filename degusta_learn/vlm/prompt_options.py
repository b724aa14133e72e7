"""How a prompt is cut down for a small VLM: `PromptOptions` and `adapt_prompt`.

Used wherever a local VLM is prompted: fine-tuning examples (`finetune/data.py`, the perception tasks of
`pretrain/tasks.py`) and the hf backend, which re-applies the options saved beside an adapter
(`degusta_finetune.json`), so a fine-tuned model is always prompted the way it was trained:
- `include`: which image groups to send ("objects" = GoMO sheets, "context" = final_state_k, "target");
- `compose`: each listed group ("objects", "context") drawn as one labelled canvas, or "all" images in
  one canvas, to save image tokens. Composed GoMO sheets are redrawn as one legible object sheet
  (`render.compose.objects_canvas`: id digits 8 px tall on a 448 px canvas); other groups are tiled
  (`render.compose.tile_canvas`).
- `modality`: how the context tables are shown (`task.prompt.MODALITIES`, `with_modality`): `images` (the
  paper's prompt, the default), `text` (each context written in the answer format after its placement-order line:
  types, ids, cells, directions; the context images left out) or `both`. With text, the model is told which
  objects the person used instead of reading their ids from the pictures (a recorded history a robot has; what
  the structured baselines `copy_nearest` and `consensus` are given). A prompt whose modality was chosen when it was
  built (`build_prompt(modality=...)`: a predict config's `modality`) keeps it. Records written before `modality`
  existed say `context_answers` (true: both, false: images); they are read so.

The prompt's text style (`clarified` or the paper's verbatim `paper`, `task.prompt.PROMPT_STYLES`) is chosen when
the prompt is built (`build_prompt(style=...)`, a predict config's `prompt_style`); `adapt_prompt` keeps it.

Example:
    opts = PromptOptions(include=["context", "target"], compose=["context"], modality="both")
    small = adapt_prompt(build_prompt("mogma", ds, episode, renderer, Grid(8, 8)), opts)
"""

from __future__ import annotations

from dataclasses import dataclass, field

from degusta_learn.errors import DegustaError
from degusta_learn.render.compose import objects_canvas, sheet_source, tile_canvas
from degusta_learn.task.prompt import check_modality

GROUPS = ("objects", "context", "target")
COMPOSE = ("objects", "context", "all")


@dataclass
class PromptOptions:
    """How a prompt is cut down for a small model (see the module docstring)."""

    include: list[str] = field(default_factory=lambda: list(GROUPS))
    """Image groups sent: objects (GoMO sheets), context (final_state_k), target (initial_state_1)."""
    compose: list[str] = field(default_factory=list)
    """Groups drawn as one labelled canvas: objects, context, all."""
    modality: str = "images"
    """How the context tables are shown: images, text or both (`task.prompt.MODALITIES`)."""
    context_answers: bool | None = None
    """The spelling of records written before `modality`: true is both (with the context images included; else
    images), false images. Read, then always null (`modality` holds it)."""

    def __post_init__(self):
        for g in self.include:
            if g not in GROUPS:
                raise DegustaError(f"data.include: unknown image group {g!r} (expected some of {list(GROUPS)})")
        for g in self.compose:
            if g not in COMPOSE:
                raise DegustaError(f"data.compose: unknown group {g!r} (expected some of {list(COMPOSE)})")
        if self.context_answers is not None:  # what the old flag computed: text only where context images were sent
            self.modality = "both" if self.context_answers and "context" in self.include else "images"
            self.context_answers = None
        check_modality(self.modality, "data.modality")
        if self.modality == "both" and "context" not in self.include:
            raise DegustaError("data.modality: both shows the context images, which data.include leaves out; add "
                               "context to data.include, or use modality text")

    def to_json(self) -> dict:
        return {"include": list(self.include), "compose": list(self.compose), "modality": self.modality}


def image_group(name: str) -> str:
    """"objects" / "context" / "target" from an image name (objects_cup.jpg, final_state_2.jpg, ...)."""
    if name.startswith("objects"):
        return "objects"
    if name.startswith("final_state"):
        return "context"
    return "target"


def adapt_prompt(prompt, options: PromptOptions):
    """A copy of `prompt` with its context tables shown as `options.modality` says (unless the prompt's modality
    was chosen already: it keeps it), excluded image groups removed and composed groups drawn as one canvas."""
    from degusta_learn.task.prompt import ImagePart, Prompt, with_modality
    if prompt.modality is None:
        prompt = with_modality(prompt, options.modality)
    parts = list(prompt.parts)
    keep: list = []
    for i, part in enumerate(parts):
        nxt = parts[i + 1] if i + 1 < len(parts) else None
        after = parts[i + 2] if i + 2 < len(parts) else None
        if "objects" not in options.include and isinstance(part, str) and isinstance(nxt, str) \
                and isinstance(after, ImagePart) and image_group(after.name) == "objects" and i == 0:
            continue  # the "These are the objects I have" line of dropped object sheets
        if isinstance(part, str) and isinstance(nxt, ImagePart) and part == f"{nxt.name}:" \
                and image_group(nxt.name) not in options.include:
            continue  # the label of a dropped image
        if isinstance(part, ImagePart) and image_group(part.name) not in options.include:
            continue
        keep.append(part)
    if "all" in options.compose:
        keep = _compose(keep, set(GROUPS), "all")
    else:
        for g in GROUPS:
            if g in options.compose:
                keep = _compose(keep, {g}, g)
    return Prompt(method=prompt.method, parts=keep, episode=prompt.episode, context_answers=prompt.context_answers,
                  style=prompt.style, modality=prompt.modality)


def _compose(parts: list, groups: set[str], label: str) -> list:
    """Replace the images of `groups` (and their "name:" labels) by one titled canvas at the first one."""
    from degusta_learn.task.prompt import ImagePart
    out: list = []
    members: list = []
    slot = None
    for i, part in enumerate(parts):
        nxt = parts[i + 1] if i + 1 < len(parts) else None
        if isinstance(part, str) and isinstance(nxt, ImagePart) and part == f"{nxt.name}:" \
                and image_group(nxt.name) in groups:
            continue
        if isinstance(part, ImagePart) and image_group(part.name) in groups:
            if slot is None:
                slot = len(out)
                out.append(None)
            members.append(part)
            continue
        out.append(part)
    if len(members) < 2:  # nothing to compose: keep the original layout
        return parts
    name = f"{label}.{members[0].name.rsplit('.', 1)[-1]}"
    names = ", ".join(m.name for m in members)
    size = members[0].image.size[0]
    sources = [sheet_source(m.image) for m in members]
    if label == "objects":  # the same caption whichever way it is drawn (dry-run token counts use blank images)
        caption = f"{name} shows the objects of {names} in one image, in this order:"
    else:
        caption = f"{name} shows the images {names} side by side, each titled with its name:"
    if label == "objects" and all(sources):  # GoMO sheets: every object redrawn legibly at the canvas scale
        canvas = objects_canvas(sources, size)
    else:
        canvas = tile_canvas([(m.name, m.image) for m in members], size)
    out[slot:slot + 1] = [caption, ImagePart(name=name, image=canvas, format=members[0].format)]
    return out
