"""`copy_context_text`: the answer a model gives by copying one context table's text out of its prompt.

With `modality: text` or `both` (task/prompt.py) a VLM's prompt writes every context table out in the answer
format ("The objects in final_state_4.jpg, written as an answer: [{'type': 'plate', 'id': 93, 'position': ['D4',
'D5'], 'cardinal_direction': 'N'}, ...]"). This baseline answers with one of those texts, verbatim: the text
`task.prompt.context_answer` writes for that context (the function `build_prompt` writes the prompt's text with),
read by the parser the VLM's answers go through (`task.answers.read_answer`) and turned into placements on the
target table by the same grid -> position conversion (`task.aggregate.combine`, one answer). So it scores exactly
what a model that copies the text scores: the same cells, directions and object ids, wherever the cells fall on the
target table (nothing is moved onto it, as nothing moves a VLM's answer).

Which context (`source`):
- `last` (default): the last context table the prompt shows (final_state_K.jpg, the episode's last context trial);
- `nearest`: the context on the target's table, else on the most similar table (`copy_nearest`'s choice:
  `heuristic.nearest_context`).

It needs no model and no image, only the prompt's text: the zero-parameter row beside every VLM row whose prompt
writes the contexts as text (what the text alone gives). Context length 0 has nothing to copy: it falls back to
population_mean, as `copy_nearest` does (`diagnostics["fallback"]`).

Usage:
    degusta predict --config configs/baseline_copy_context_text.yaml
    degusta predict --config configs/baseline_copy_context_text.yaml --set source=nearest --set split=val \\
        --set out=runs/baseline_copy_context_text/nearest_val.jsonl
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from degusta_learn.baselines.heuristic import nearest_context, target_table, with_population_fallback
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.render.grid import Grid
from degusta_learn.scene import Arrangement, Dataset, Episode, Prediction
from degusta_learn.task.aggregate import combine
from degusta_learn.task.answers import answer_kind, read_answer
from degusta_learn.task.prompt import context_answer

SOURCES = ("last", "nearest")


@dataclass
class CopyContextTextConfig(PredictConfig):
    """Predict config of `copy_context_text`."""

    prompt_method: Literal["louma", "logma", "mouma", "mogma"] = "mogma"
    """The VLM method whose prompt text is copied (its answer format: grid cells and directions for logma / mogma,
    x, y and degrees for louma / mouma): the method of the VLM row it stands beside."""
    source: Literal["last", "nearest"] = "last"
    """Which context table's text: last (the last one the prompt shows) or nearest (on the target's table, else the
    most similar table, as copy_nearest)."""
    grid: Grid = field(default_factory=Grid)
    """Grid of grid methods: the VLM row's (its cells are the text's)."""


def source_context(ds: Dataset, ep: Episode, source: str) -> tuple[int, Arrangement]:
    """(its 1-based position in the prompt: final_state_k, the arrangement) of the context table `source` picks."""
    context = [ds.arrangement(ep.participant, t) for t in ep.context]
    if source == "last":
        return len(context), context[-1]
    chosen = nearest_context(ds, context, target_table(ds, ep))
    return context.index(chosen) + 1, chosen


def copied_prediction(cfg: CopyContextTextConfig, ds: Dataset, ep: Episode, grid: Grid) -> Prediction:
    """The prediction of one episode with context: the chosen context's answer text, parsed and placed."""
    k, arrangement = source_context(ds, ep, cfg.source)
    kind = answer_kind(cfg.prompt_method)
    text = context_answer(cfg.prompt_method, arrangement, ds.catalog, grid)
    answer = read_answer(text, kind, ds.catalog, grid)
    placements, agg = combine([answer.items], kind, grid, "steps")
    return Prediction(ep.id, ep.participant, ep.target, cfg.method, placements, failed=agg["failed"],
                      diagnostics={"source": cfg.source, "copied": f"final_state_{k}", "source_trial": arrangement.trial,
                                   "source_table": arrangement.table, "prompt_method": cfg.prompt_method,
                                   "n_items": answer.n_read, "n_item_errors": len(answer.item_errors),
                                   "response": text})


def run_copy_context_text(cfg: CopyContextTextConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    grid = Grid(cfg.grid.rows, cfg.grid.cols)
    return with_population_fallback(cfg, ds, episodes, lambda ep: copied_prediction(cfg, ds, ep, grid),
                                    reason="no context table to copy (context length 0)")


COPY_CONTEXT_TEXT = MethodSpec(CopyContextTextConfig, run_copy_context_text,
                               "one context table's text in the prompt, copied as the answer (the last one shown)")
