"""Combine n sampled answers into one task plan (DESIGN.md section 4, the paper's appendix A).

- plan length = mode of the lengths of the parsed responses;
- for each step s: type = mode of the types at step s (over responses that have a step s); object id =
  mode of the ids among the responses of that type at step s;
- position = mean of their [x, y] (unmarked) or the weighted mean of all listed cell centres (grid,
  `Grid.decode_weighted`); rotation = circular mean of their rotations (grid: of their directions).

Ties in any mode go to the value seen first in response order (responses are ordered by sample index,
so this is deterministic). An object id already placed at an earlier step is replaced by the next most
frequent unused id of that type at that step; if every candidate is used, the step is dropped (an
object cannot be placed twice). Unparseable responses are `None`; if all are, the result is empty and
`diagnostics["failed"]` is True (never an exception).

Example:
    placements, diag = aggregate([parse_answer(t, "grid", catalog, grid) for t in texts], "grid", grid)
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.answers import KINDS, AnswerItem
from degusta_learn.scene import Placement


def _ranked(values: list) -> list:
    """Distinct values by decreasing count, ties in order of first appearance."""
    counts = Counter(values)
    first = {v: i for i, v in reversed(list(enumerate(values)))}
    return sorted(counts, key=lambda v: (-counts[v], first[v]))


def aggregate(responses: list[list[AnswerItem] | None], kind: str, grid=None) -> tuple[list[Placement], dict[str, Any]]:
    """Aggregate parsed responses (None = unparseable) into placements and per-step diagnostics.

    Args:
        responses: one entry per sampled answer, in sample order.
        kind: "grid" or "unmarked".
        grid: the `render.grid.Grid` of grid answers (default 8 x 8).

    Returns:
        (placements in plan order, diagnostics with n_responses, n_parsed, failed, length,
        length_agreement and per-step type/id agreement).
    """
    from degusta_learn.render.grid import Grid, circular_mean, direction_to_rotation

    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    grid = grid or Grid()
    parsed = [r for r in responses if r is not None]
    diag: dict[str, Any] = {"n_responses": len(responses), "n_parsed": len(parsed), "failed": not parsed}
    if not parsed:
        return [], diag
    lengths = [len(r) for r in parsed]
    length = _ranked(lengths)[0]
    diag["length"] = length
    diag["length_agreement"] = round(lengths.count(length) / len(parsed), 4)
    placements: list[Placement] = []
    used: set[int] = set()
    steps, dropped = [], []
    for s in range(length):
        at_step = [r[s] for r in parsed if len(r) > s]  # never empty: the mode length is reached
        type_ = _ranked([it.type for it in at_step])[0]
        members = [it for it in at_step if it.type == type_]
        ranked_ids = _ranked([it.id for it in members])
        free = [i for i in ranked_ids if i not in used]
        step = {"step": s, "n": len(at_step), "type": type_,
                "type_agreement": round(len(members) / len(at_step), 4), "id_mode": ranked_ids[0]}
        if not free:
            step["dropped"] = "every proposed id was placed at an earlier step"
            dropped.append(s)
            steps.append(step)
            continue
        oid = free[0]
        used.add(oid)
        step["id"] = oid
        step["id_agreement"] = round(sum(it.id == oid for it in members) / len(members), 4)
        if kind == "grid":
            x, y = grid.decode_weighted([it.cells for it in members])
            rot = circular_mean([direction_to_rotation(it.direction) for it in members])
        else:
            xy = np.array([it.position for it in members], dtype=float)  # (M, 2)
            x, y = xy.mean(axis=0)
            rot = circular_mean([it.rotation for it in members])
        placements.append(Placement(object=int(oid), x=float(x), y=float(y), rotation=float(rot) % 360.0))
        steps.append(step)
    diag["steps"] = steps
    if dropped:
        diag["dropped_steps"] = dropped
    return placements, diag


def failure_summary(predictions) -> str:
    """One line for the end of `degusta predict`: failed episodes, and where answers were parsed (zero-shot,
    fine-tuned models) failed samples and dropped items, each with its rate.

    Example: "9 episodes, 1 failed (11.1%); samples: 3 of 45 failed (6.7%); items: 2 of 120 dropped (1.7%)".
    """
    n = len(predictions)
    failed = sum(bool(p.failed) for p in predictions)
    line = f"{n} episodes, {failed} failed ({_pct(failed, n)})"
    diags = [p.diagnostics for p in predictions if isinstance(p.diagnostics, dict)]
    if any("n_responses" in d for d in diags):
        samples = sum(_count(d.get("n_responses")) for d in diags)
        bad = samples - sum(_count(d.get("n_parsed")) for d in diags)
        line += f"; samples: {bad} of {samples} failed ({_pct(bad, samples)})"
    if any("n_items" in d for d in diags):
        items = sum(_count(d.get("n_items")) for d in diags)
        dropped = sum(_count(d.get("n_item_errors")) for d in diags)
        line += f"; items: {dropped} of {items} dropped ({_pct(dropped, items)})"
    return line


def _count(v) -> int:
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else 0


def _pct(k: int, n: int) -> str:
    return f"{100.0 * k / n:.1f}%" if n else "n/a"
