"""Fine-tuning examples rendered on the fly: the zero-shot prompt of an episode and its target answer.

An example is exactly what a zero-shot method sees — `prompting.build_prompt(method, ...)`: GoMO sheets
(or the catalog as text), the context arrangements as GMA (or UmA) images with their placement-order
lines, the empty target table (with grid), the task text — and the answer a perfect model gives, in
the zero-shot answer format (`format_answer(answer_items(...))`: cells from `Grid.encode`, directions
from `rotation_to_direction`, mark ids, in placement order). Nothing is pre-rendered: images are drawn
in `__getitem__` (in DataLoader workers), so grid size, image size or method change without a cache.

Options that matter for small models (`PromptOptions`, saved beside the adapter and re-applied by the hf
backend, so a fine-tuned model is always prompted the way it was trained):
- `include`: which image groups to send ("objects" = GoMO sheets, "context" = final_state_k, "target");
- `compose`: each listed group ("objects", "context") drawn as one labelled canvas, or "all" images in
  one canvas, to save image tokens.

Example:
    examples = LiftedExamples(ds, episodes, "mogma", Grid(8, 8), render_size=448)
    ex = examples[0]; ex.prompt.images, ex.answer
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from PIL import Image, ImageDraw

from degusta_learn.errors import DegustaError

GROUPS = ("objects", "context", "target")
COMPOSE = ("objects", "context", "all")


@dataclass
class PromptOptions:
    """How a prompt is cut down for a small model (see the module docstring)."""

    include: list[str] = field(default_factory=lambda: list(GROUPS))
    compose: list[str] = field(default_factory=list)

    def __post_init__(self):
        for g in self.include:
            if g not in GROUPS:
                raise DegustaError(f"data.include: unknown image group {g!r} (expected some of {list(GROUPS)})")
        for g in self.compose:
            if g not in COMPOSE:
                raise DegustaError(f"data.compose: unknown group {g!r} (expected some of {list(COMPOSE)})")

    def to_json(self) -> dict:
        return {"include": list(self.include), "compose": list(self.compose)}


@dataclass
class Example:
    """One training / validation example."""

    episode: str
    prompt: object  # prompting.Prompt
    answer: str
    participant: str = ""
    target: int = -1
    meta: dict = field(default_factory=dict)
    """What scoring needs beyond the answer text (perception examples: task and ground truth)."""


def image_group(name: str) -> str:
    """"objects" / "context" / "target" from an image name (objects_cup.jpg, final_state_2.jpg, ...)."""
    if name.startswith("objects"):
        return "objects"
    if name.startswith("final_state"):
        return "context"
    return "target"


def adapt_prompt(prompt, options: PromptOptions):
    """A copy of `prompt` with excluded image groups removed and composed groups drawn as one canvas."""
    from degusta_learn.prompting import ImagePart, Prompt

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
    return Prompt(method=prompt.method, parts=keep, episode=prompt.episode)


def _compose(parts: list, groups: set[str], label: str) -> list:
    """Replace the images of `groups` (and their "name:" labels) by one titled canvas at the first one."""
    from degusta_learn.prompting import ImagePart

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
    canvas = compose_canvas([(m.name, m.image) for m in members], size=members[0].image.size[0])
    out[slot:slot + 1] = [f"{name} shows the images {names} side by side, each titled with its name:",
                          ImagePart(name=name, image=canvas, format=members[0].format)]
    return out


def compose_canvas(images: list[tuple[str, Image.Image]], size: int) -> Image.Image:
    """Tile named images into one square canvas of `size` px, each tile titled with its name."""
    n = len(images)
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    tile = size // cols
    title = max(10, tile // 10)
    canvas = Image.new("RGB", (size, size), "white")
    draw = ImageDraw.Draw(canvas)
    y0 = (size - rows * tile) // 2
    for k, (name, im) in enumerate(images):
        r, c = divmod(k, cols)
        x, y = c * tile, y0 + r * tile
        body = im.convert("RGB").resize((tile - 2, tile - title - 2), Image.Resampling.LANCZOS)
        canvas.paste(body, (x + 1, y + title + 1))
        draw.rectangle([x, y, x + tile - 1, y + tile - 1], outline=(60, 60, 60))
        draw.text((x + 3, y + 1), name.rsplit(".", 1)[0], fill=(0, 0, 0))
    return canvas


class LiftedExamples:
    """A map-style dataset of `Example`s rendered on the fly (torch DataLoader compatible)."""

    def __init__(self, ds, episodes, method: str, grid, render_size: int = 448,
                 options: PromptOptions | None = None):
        from degusta_learn.prompting import answer_kind

        self.ds, self.episodes, self.method, self.grid = ds, list(episodes), method, grid
        self.kind = answer_kind(method)
        self.render_size = render_size
        self.options = options or PromptOptions()
        self._renderer = None  # built lazily: one per DataLoader worker (sprite cache)

    def __len__(self) -> int:
        return len(self.episodes)

    @property
    def renderer(self):
        if self._renderer is None:
            from degusta_learn.render.lifting import Renderer

            self._renderer = Renderer.for_dataset(self.ds, size=self.render_size)
        return self._renderer

    def prompt(self, i: int):
        from degusta_learn.prompting import build_prompt

        return adapt_prompt(build_prompt(self.method, self.ds, self.episodes[i], self.renderer, self.grid),
                            self.options)

    def answer(self, i: int) -> str:
        from degusta_learn.prompting import answer_items, format_answer

        ep = self.episodes[i]
        target = self.ds.arrangement(ep.participant, ep.target)
        return format_answer(answer_items(list(target.placements), self.ds.catalog, self.kind, self.grid), self.kind)

    def __getitem__(self, i: int) -> Example:
        ep = self.episodes[i]
        return Example(episode=ep.id, prompt=self.prompt(i), answer=self.answer(i), participant=ep.participant,
                       target=ep.target)

    def __getstate__(self):  # workers rebuild their own renderer
        state = dict(self.__dict__)
        state["_renderer"] = None
        return state
