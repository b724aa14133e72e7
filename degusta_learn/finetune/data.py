"""Fine-tuning examples rendered on the fly: the zero-shot prompt of an episode and its target answer.

An example is exactly what a zero-shot method sees — `prompting.build_prompt(method, ...)`: GoMO sheets
(or the catalog as text), the context arrangements as GMA (or UmA) images with their placement-order
lines, the empty target table (with grid), the task text — and the answer a perfect model gives, in
the zero-shot answer format (`format_answer(answer_items(...))`: cells from `Grid.encode`, directions
from `rotation_to_direction`, mark ids, in placement order). Nothing is pre-rendered: images are drawn
in `__getitem__` (in DataLoader workers), so grid size, image size or method change without a cache.

Each prompt is cut down by the config's `PromptOptions` (`vlm/prompt_options.py`: image groups sent,
composed canvases), the same options the hf backend re-applies at prediction time.

Example:
    examples = LiftedExamples(ds, episodes, "mogma", Grid(8, 8), render_size=448)
    ex = examples[0]; ex.prompt.images, ex.answer
"""

from __future__ import annotations

from dataclasses import dataclass, field

from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt


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
