"""Token counts of fine-tuning examples without drawing them: the dry run's and length grouping's budget.

`token_budget` counts every example exactly in seconds: each example's text by the tokenizer alone (the chat
template applied, blank stand-ins for the images), and the image tokens once per image layout by the processor;
a seeded sample, the heaviest-looking and the longest example are counted in full by the processor to check (any
disagreement recounts everything and says why). `count_tokens` is the slow exhaustive count (the processor on every
example, blank images of each image's real size). `heaviest_draw` is the longest-looking example, which the real
run collates before training (`train.check_budget`).

Usage:
    budget = token_budget(train_examples, collator, sample=32, seed=cfg.seed)
    refuse_budget(budget, collator)          # the collator's one-line data.max_length error, if over
    print(token_summary(budget.counts, cfg.data.max_length, "training examples", budget.heavier))
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

from degusta_learn.errors import DegustaError


def set_budget(cfg, processor, model_config) -> None:
    """Set the processor's image budget, then check it against the grid and `data.max_length` against the
    model's context (one-line errors naming the key)."""
    from degusta_learn.task.answers import answer_kind
    from degusta_learn.vlm.inputs import check_grid_resolution, set_image_budget
    set_image_budget(processor, model_config, cfg.model.image_size)
    if answer_kind(cfg.method) == "grid":
        check_grid_resolution(processor, model_config, cfg.data.grid, key="model.image_size")
    context = getattr(model_config.get_text_config(), "max_position_embeddings", None)
    if context and cfg.data.max_length > context:
        raise DegustaError(f"data.max_length: {cfg.data.max_length} exceeds the model's context of {context} "
                           "tokens; lower it (and the image budget: model.image_size, data.compose, data.include)")



def heaviest_draw(examples) -> tuple[int, object]:
    """(index, episode) of the longest-looking example: the most context arrangements, then objects (context and
    target tables), each example with (when contexts are redrawn each epoch) the heaviest context any epoch could
    draw for it (`LiftedExamples.heaviest`)."""
    ds = examples.ds
    heaviest = [examples.heaviest(i) for i in range(len(examples))]
    size = [(len(ep.context), sum(len(ds.arrangement(ep.participant, t).placements) for t in (*ep.context, ep.target)))
            for ep in heaviest]
    i = max(range(len(heaviest)), key=size.__getitem__)
    return i, heaviest[i]



class _Blank:
    """A blank prompt image's size (and `info`) without its pixels: all that counting a prompt's text needs.
    Converting it keeps the stand-in; resizing it (a tiled canvas pastes it) gives a real blank image."""

    mode = "RGB"

    def __init__(self, size, info: dict | None = None):
        self.size, self.info = (int(size[0]), int(size[1])), dict(info or {})

    width = property(lambda self: self.size[0])
    height = property(lambda self: self.size[1])

    def convert(self, mode: str | None = None) -> _Blank:
        return self

    def copy(self) -> _Blank:
        return _Blank(self.size, self.info)

    def resize(self, size, *args, **kwargs):
        from PIL import Image

        return Image.new("RGB", tuple(size), "white")


class _SizeOnlyRenderer:
    """Stands in for the lifted-image renderer when only token counts are needed: blank images of the size
    `renderer` draws each one (its own geometry: `Renderer._fit`, the grid margin; the processor's token count
    depends only on the images' sizes), GoMO sheets carrying what they show (so composed object sheets are the
    cached `objects_canvas`, as in training). `pixels=False`: `_Blank` stand-ins, no pixel drawn (counting
    text). Counting every training example takes seconds instead of drawing every scene."""

    def __init__(self, renderer, pixels: bool = True):
        self.geometry, self.size, self.pixels = renderer, renderer.size, pixels

    def _blank(self, size, info: dict | None = None):
        if not self.pixels:
            return _Blank(size, info)
        from PIL import Image

        im = Image.new("RGB", tuple(size), "white")
        im.info.update(info or {})
        return im

    def _fit(self, table_id: int, box: int) -> tuple[int, int]:
        return self.geometry._fit(self.geometry._table(table_id), box)

    def uma(self, table_id: int, placements=(), **kwargs):
        return self._blank(self._fit(table_id, self.size))

    def gma(self, table_id: int, placements=(), grid=None, **kwargs):
        m = self.geometry.margin
        w, h = self._fit(table_id, self.size - 2 * m)
        return self._blank((w + 2 * m, h + 2 * m))

    def table(self, table_id: int, grid=None):
        return self.uma(table_id) if grid is None else self.gma(table_id, (), grid)

    def gomo(self, type_: str):
        return self.gomo_sheet(type_, self.geometry.catalog.of_type(type_))

    def gomo_sheet(self, type_: str, objs):
        from degusta_learn.render.compose import GOMO_SOURCE

        return self._blank((self.size, self.size), {GOMO_SOURCE: (type_, tuple(objs), self.geometry.root)})


def _counting(examples, pixels: bool = True):
    """A shallow copy of `examples` drawing with `_SizeOnlyRenderer`."""
    import copy

    view = copy.copy(examples)
    view._renderer = _SizeOnlyRenderer(copy.copy(examples).renderer, pixels)
    return view


def count_tokens(examples, collator, limit: int | None = None, batch: int = 16) -> list[dict]:
    """`Collator.token_counts` of every example (or the first `limit`), the processor running on each: prompts
    built as in training, the lifted images blank at their size. Exact and slow (the processor prepares every
    image: ~0.1 s a SmolVLM example); `token_budget` gives the same counts in seconds."""
    n = len(examples) if limit is None else min(limit, len(examples))
    if n == 0:
        return []
    counting = _counting(examples)
    out: list[dict] = []
    for start in range(0, n, batch):
        out += collator.token_counts([counting[i] for i in range(start, min(start + batch, n))])
    return out


def _memo_grid(grid):
    """`grid` as a `Grid` that remembers each placement's cells: counting text builds every context arrangement's
    answer (`Prompt.context_answers`) once per example showing it, the same few hundred arrangements over and
    over. Anything else is returned as it is."""
    from degusta_learn.render.grid import Grid

    if not isinstance(grid, Grid):
        return grid
    memo: dict = {}

    class MemoGrid(Grid):
        def encode(self, obj, x: float, y: float, rotation: float) -> list[str]:
            key = (obj.id, x, y, rotation)
            if key not in memo:
                memo[key] = super().encode(obj, x, y, rotation)
            return list(memo[key])

    return MemoGrid(grid.rows, grid.cols)


@dataclass
class TokenBudget:
    """The token counts of a set of `LiftedExamples` (`token_budget`)."""

    counts: list[dict]
    """Every example with its epoch-0 contexts, in order (what `count_tokens` gives): {"total", "image", "text",
    "answer"}."""
    heavier: list[dict] = field(default_factory=list)
    """Each example whose heaviest contexts (`LiftedExamples.heaviest`: contexts redrawn each epoch) differ from
    epoch 0's, with those contexts."""
    worst: tuple | None = None
    """(Example, counts) of the longest of `counts` and `heavier`, counted by the processor itself."""
    layouts: int = 0
    """Distinct image layouts (the images' sizes, in order) among the examples."""
    checked: int = 0
    """Examples the processor counted in full beyond one per layout, each agreeing with the layout's count."""
    sample: int = 0
    """Of `checked`, the seeded random sample."""
    exhaustive: bool = False
    """The processor counted every example (asked for, or the layout counts disagreed with it)."""
    mismatch: str = ""
    """Why the layout counts were dropped ("" if they were not)."""

    @property
    def everything(self) -> list[dict]:
        return self.counts + self.heavier


def token_budget(examples, collator, sample: int | None = 32, seed: int = 0, heaviest: bool = True,
                 calibration: dict | None = None, batch: int = 64) -> TokenBudget:
    """Every example's exact token counts (`Collator.token_counts`, as `count_tokens`) without running the image
    processor on every example: what the dry run and length grouping count.

    What varies from example to example: the image tokens by the number and size of the prompt images only (the
    processor expands each image placeholder by the image's size), and the text by more than counts of tables and
    objects: the placement-order line of each context table (object types, one a placement), the task text (the
    context images' names) and the answer (each object's type, id, cells and direction). So the text is
    tokenized for EVERY example (`Collator.text_counts`: the chat template and the tokenizer, no image touched),
    and the processor runs on one example per image layout, which fixes that layout's image tokens and the
    placeholder expansion; every count is then exact, the maximum and the mean alike. Checked, not assumed: the
    processor also counts `sample` examples drawn with `seed`, the longest-looking example (`heaviest_draw`, what
    `check_budget` collates) and the longest one found; if any disagrees, the processor counts every example
    (`exhaustive`, `mismatch` says why). With `heaviest` each example is also counted with the heaviest contexts
    an epoch could draw for it (`TokenBudget.heavier`, `LiftedExamples.heaviest`). `sample=None`: the processor
    counts every example (slow; comparisons). `calibration` (layout -> counts) carries measured layouts from
    one call to the next (training, then validation examples of the same collator)."""
    n = len(examples)
    if n == 0:
        return TokenBudget([])
    draws = [(i, examples.episode(i)) for i in range(n)]
    if heaviest:
        draws += [(i, ep) for i, ep in enumerate(examples.heaviest(i) for i in range(n))
                  if tuple(ep.context) != tuple(draws[i][1].context)]
    exact_view = _counting(examples)
    exact: dict[int, dict] = {}

    def measure(keys) -> None:
        keys = [k for k in dict.fromkeys(keys) if k not in exact]
        for start in range(0, len(keys), 16):
            chunk = keys[start:start + 16]
            exact.update(zip(chunk, collator.token_counts([exact_view.example(*draws[k]) for k in chunk])))

    def result(counts: list[dict], **kw) -> TokenBudget:
        worst = max(range(len(counts)), key=lambda k: counts[k]["total"])
        measure([worst])
        return TokenBudget(counts[:n], counts[n:], (exact_view.example(*draws[worst]), exact[worst]), **kw)

    if sample is None:
        measure(range(len(draws)))
        return result([exact[k] for k in range(len(draws))], exhaustive=True)
    text_view = _counting(examples, pixels=False)
    text_view.grid = _memo_grid(examples.grid)
    texts: list[dict] = []
    for start in range(0, len(draws), batch):
        texts += collator.text_counts([text_view.example(*d) for d in draws[start:start + batch]])
    first: dict = {}  # layout -> its first example
    for k, t in enumerate(texts):
        first.setdefault(t["layout"], k)
    if () in first and len(first) > 1:  # the collator's own error for a batch mixing image and text-only prompts
        collator.token_counts([exact_view.example(*draws[k]) for k in (first[()], next(v for v in first.values()
                                                                                       if texts[v]["layout"]))])
    calibration = {} if calibration is None else calibration
    fresh = [k for layout, k in first.items() if layout not in calibration]
    measure(fresh)
    for k in fresh:  # the prompt's tokens beyond the text's placeholders, and its image tokens, for this layout
        calibration[texts[k]["layout"]] = (exact[k]["total"] - exact[k]["answer"] - texts[k]["prompt"],
                                           exact[k]["image"])

    def predicted(t: dict) -> dict:
        extra, image = calibration[t["layout"]]
        prompt = t["prompt"] + extra
        return {"total": prompt + t["answer"], "image": image, "text": prompt - image, "answer": t["answer"]}

    counts = [predicted(t) for t in texts]
    picked = random.Random(seed).sample(range(n), min(sample, n))
    i, _ = heaviest_draw(examples)
    longest = next((k for k in range(n, len(draws)) if draws[k][0] == i), i) if heaviest else i
    worst = max(range(len(counts)), key=lambda k: counts[k]["total"])
    checks = [k for k in dict.fromkeys(picked + [longest, worst]) if k not in fresh]
    measure(checks)
    wrong = [k for k in checks if exact[k] != counts[k]]
    if wrong:
        w = wrong[0]
        why = (f"episode {draws[w][1].id}: the processor counted {exact[w]}, the text and its image layout "
               f"{counts[w]}")
        measure(range(len(draws)))
        return result([exact[k] for k in range(len(draws))], layouts=len(first), exhaustive=True, mismatch=why)
    return result(counts, layouts=len(first), checked=len(checks), sample=len([k for k in picked if k in checks]))


def token_summary(counts: list[dict], max_length: int, what: str, heavier: list[dict] | None = None) -> str:
    """"max M / mean m of data.max_length L (p% used) over N <what>; image, text, answer max / mean": means over
    `counts`, maxima over `counts` and `heavier` (the same examples with heavier contexts, `TokenBudget.heavier`)."""
    every = counts + list(heavier or [])

    def mm(key: str) -> str:
        return f"{max(c[key] for c in every)} / {sum(c[key] for c in counts) / len(counts):.1f}"

    top = max(c["total"] for c in every)
    drawn = " (means with epoch 0's contexts, maxima also with the heaviest any epoch could draw)" if heavier else ""
    return (f"max {top} / mean {sum(c['total'] for c in counts) / len(counts):.1f} tokens of data.max_length "
            f"{max_length} ({top / max_length:.0%} used) over {len(counts)} {what}{drawn} (max / mean: image "
            f"{mm('image')}, other prompt {mm('text')}, answer {mm('answer')})")


def refuse_over_budget(examples, counts: list[dict], collator) -> None:
    """The collator's own one-line `data.max_length` error for the longest example over the budget."""
    if not counts:
        return
    worst = max(range(len(counts)), key=lambda i: counts[i]["total"])
    if counts[worst]["total"] > collator.max_length:
        raise collator.budget_error(examples[worst], counts[worst])


def refuse_budget(budget: TokenBudget, collator) -> None:
    """`refuse_over_budget` for a `TokenBudget`: the same error, for its longest example (epoch 0's contexts or
    the heaviest an epoch could draw)."""
    if budget.worst is not None and budget.worst[1]["total"] > collator.max_length:
        raise collator.budget_error(*budget.worst)


def describe_budget(train: TokenBudget, val: TokenBudget, seed: int) -> str:
    """What the dry run's token counts counted, in one line."""
    examples = f"all {len(train.counts):,} training examples"
    if train.heavier:
        examples += f", {len(train.heavier):,} of them also with the heaviest contexts an epoch could draw,"
    examples += f" and the {len(val.counts):,} validation examples" if val.counts else ""
    if train.exhaustive or val.exhaustive:
        why = "; ".join(b.mismatch for b in (train, val) if b.mismatch)
        return (f"the processor counted {examples} in full"
                + (f" (the text's tokens plus its image layout's disagreed with it: {why})" if why else ""))
    return (f"every example, exactly (no estimate): the text of {examples} by the tokenizer alone; the image "
            f"tokens once per image layout ({max(train.layouts, val.layouts)} layouts) by the processor, which "
            f"recounted {train.checked + val.checked} examples in full to check ({train.sample + val.sample} "
            f"sampled with seed {seed}, the heaviest-looking and the longest): all agreed")
