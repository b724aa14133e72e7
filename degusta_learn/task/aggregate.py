"""Combine n sampled answers into one task plan: the paper's per-step aggregation (DESIGN.md section 4, the paper's
appendix A; `aggregation: steps`, predict's default) or the greedy answer lengthened by object votes
(`aggregation: greedy_votes_pooled`, the shipped fine-tuned predict config's).

The paper's, `aggregate`:
- plan length = mode of the lengths of the parsed responses;
- for each step s: type = mode of the types at step s (over responses that have a step s); object id =
  mode of the ids among the responses of that type at step s;
- position = mean of their [x, y] (unmarked) or the mean of their cell centroids (grid,
  `Grid.decode_weighted`: each response weighs the same, however many cells it lists); rotation =
  circular mean of their rotations (grid: of their directions).

Ties in any mode go to the value seen first in response order (responses are ordered by sample index,
so this is deterministic). An object id already placed at an earlier step is replaced by the next most
frequent unused id of that type at that step; if every candidate is used, the step is dropped (an
object cannot be placed twice). Unparseable responses are `None`; if all are, the result is empty and
`diagnostics["failed"]` is True (never an exception).

Greedy + votes, `anchored_votes` (`aggregation: greedy_votes_pooled`): the model's greedy answer (one more answer,
at temperature 0) keeps its objects and is lengthened, never shortened, to the n samples' median length (rounded
half to even) by the best-voted objects it lacks; every object is placed from every answer naming it (the greedy
one and the samples, as above). For a model whose greedy lists end early but whose samples' lengths follow the
person's count (a small fine-tuned model names the same objects in different orders across its samples, so a
step's mode mixes different objects). An unparseable greedy answer falls back to object votes, `aggregate_votes`:

- plan length = median of the lengths of the parsed responses (rounded half to even; 0 where most are empty);
- objects = that many ids, ranked by how many responses name them (ties: the lower mean step, then the one seen
  first), placed in the order of their mean step, each from every response that names it.

An answer names an object at most once (`read_answer` drops an item naming one again), so a vote is one answer's.

Example:
    placements, diag = aggregate([parse_answer(t, "grid", catalog, grid) for t in texts], "grid", grid)
    placements, diag = combine(sampled, "grid", grid, how="greedy_votes_pooled", anchor=greedy_items)
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Literal, get_args

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.scene import Placement
from degusta_learn.task.answers import KINDS, AnswerItem


def _ranked(values: list) -> list:
    """Distinct values by decreasing count, ties in order of first appearance."""
    counts = Counter(values)
    first = {v: i for i, v in reversed(list(enumerate(values)))}
    return sorted(counts, key=lambda v: (-counts[v], first[v]))


Aggregation = Literal["steps", "greedy_votes_pooled"]
"""How n answers become one plan: the paper's per-step modes, or the greedy answer lengthened by votes, every object
placed from every answer naming it (module docstring); the configs' `decoding.aggregation` type."""
AGGREGATIONS = get_args(Aggregation)
ANCHORED = ("greedy_votes_pooled",)
"""The aggregations that ask for one more answer, at temperature 0 (the anchor)."""


def combine(responses: list[list[AnswerItem] | None], kind: str, grid=None, how: str = "steps",
            anchor: list[AnswerItem] | None = None) -> tuple[list[Placement], dict[str, Any]]:
    """`aggregate` (how="steps") or `anchored_votes` (how="greedy_votes_pooled", with the greedy answer's items as
    `anchor`, None if it did not parse); the diagnostics name the aggregation."""
    if how not in AGGREGATIONS:
        raise DegustaError(f"aggregation: expected one of {list(AGGREGATIONS)}, got {how!r}")
    if how in ANCHORED:
        placements, diag = anchored_votes(anchor, responses, kind, grid)
    else:
        placements, diag = aggregate(responses, kind, grid)
    return placements, {"aggregation": how, **diag}


def _start(responses: list, kind: str, grid) -> tuple:
    """(grid or the 8 x 8 default, the parsed responses, the diagnostics every aggregation starts with)."""
    from degusta_learn.render.grid import Grid

    if kind not in KINDS:
        raise DegustaError(f"answer kind: expected one of {list(KINDS)}, got {kind!r}")
    parsed = [r for r in responses if r is not None]
    return grid or Grid(), parsed, {"n_responses": len(responses), "n_parsed": len(parsed), "failed": not parsed}


def placed(oid: int, members: list[AnswerItem], kind: str, grid) -> Placement:
    """Object `oid` at the mean of the places `members` (answer items) give it: the mean of their cell centroids
    (grid; each item weighs the same) or of their positions, and the circular mean of their rotations."""
    from degusta_learn.render.grid import circular_mean, direction_to_rotation

    if kind == "grid":
        x, y = grid.decode_weighted([it.cells for it in members])
        rot = circular_mean([direction_to_rotation(it.direction) for it in members])
    else:
        xy = np.array([it.position for it in members], dtype=float)  # (M, 2)
        x, y = xy.mean(axis=0)
        rot = circular_mean([it.rotation for it in members])
    return Placement(object=int(oid), x=float(x), y=float(y), rotation=float(rot) % 360.0)


def aggregate_votes(responses: list[list[AnswerItem] | None], kind: str, grid=None
                    ) -> tuple[list[Placement], dict[str, Any]]:
    """Object votes (module docstring): the median length's most-named objects, in their mean order.

    Returns (placements in plan order, diagnostics with n_responses, n_parsed, failed, length, length_agreement and
    per chosen object its votes and mean step, `objects`).
    """
    grid, parsed, diag = _start(responses, kind, grid)
    if not parsed:
        return [], diag
    lengths = [len(r) for r in parsed]
    length = median_length(parsed)
    diag["length"] = length
    diag["length_agreement"] = round(lengths.count(length) / len(parsed), 4)
    named, mean_step, ranked = object_votes(parsed)
    chosen = sorted(ranked[:length], key=lambda oid: mean_step[oid])
    diag["objects"] = [{"id": oid, "votes": len(named[oid]), "mean_step": round(mean_step[oid], 4)} for oid in chosen]
    return [placed(oid, named[oid], kind, grid) for oid in chosen], diag


def anchored_votes(anchor: list[AnswerItem] | None, responses: list[list[AnswerItem] | None], kind: str, grid=None
                   ) -> tuple[list[Placement], dict[str, Any]]:
    """The greedy answer `anchor` lengthened by votes to the samples' median length, never cut (module docstring);
    `aggregate_votes` when it is None. Each of the anchor's objects is placed from the anchor and every sample
    naming it.

    Returns (the anchor's placements, then the added objects in order of their votes; diagnostics with n_responses,
    n_parsed, failed, `anchor` (its length, or "unparsed"), length (the samples' median; the anchor's without
    samples) and per added object its votes and mean step, `added`).
    """
    if anchor is None:
        placements, diag = aggregate_votes(responses, kind, grid)
        return placements, {**diag, "anchor": "unparsed"}
    grid, parsed, diag = _start(responses, kind, grid)
    diag.update(failed=False, anchor=len(anchor))
    if not parsed:
        return [placed(it.id, [it], kind, grid) for it in anchor], {**diag, "length": len(anchor), "added": []}
    named, mean_step, ranked = object_votes(parsed)
    length = median_length(parsed)
    own = [placed(it.id, [it] + named.get(it.id, []), kind, grid) for it in anchor]
    have = {it.id for it in anchor}
    extra = [oid for oid in ranked if oid not in have][:max(0, length - len(anchor))]
    diag["length"] = length
    diag["added"] = [{"id": oid, "votes": len(named[oid]), "mean_step": round(mean_step[oid], 4)} for oid in extra]
    return own + [placed(oid, named[oid], kind, grid) for oid in extra], diag


def median_length(parsed: list[list[AnswerItem]]) -> int:
    """The median of the parsed answers' lengths, rounded half to even (0 where most answers are empty)."""
    return int(round(float(np.median([len(r) for r in parsed]))))


def object_votes(parsed: list[list[AnswerItem]]) -> tuple[dict[int, list[AnswerItem]], dict[int, float], list[int]]:
    """The votes of parsed answers: id -> the items naming it, id -> its mean step, and the ids by decreasing
    votes (ties: the lower mean step, then the one seen first)."""
    named: dict[int, list[AnswerItem]] = {}
    steps: dict[int, list[int]] = {}
    for items in parsed:
        for step, it in enumerate(items):
            named.setdefault(it.id, []).append(it)
            steps.setdefault(it.id, []).append(step)
    mean_step = {oid: float(np.mean(v)) for oid, v in steps.items()}
    ranked = sorted(named, key=lambda oid: (-len(named[oid]), mean_step[oid]))  # stable: first seen breaks ties
    return named, mean_step, ranked


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
    grid, parsed, diag = _start(responses, kind, grid)
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
        placements.append(placed(oid, members, kind, grid))
        steps.append(step)
    diag["steps"] = steps
    if dropped:
        diag["dropped_steps"] = dropped
    return placements, diag


def decoding_diagnostics(samples: list, kind: str, catalog, grid=None) -> dict[str, Any]:
    """What a local model's decoding did to one episode's answers, from their `Completion.decoding`
    (`vlm.generate`); {} when no answer says (remote APIs, answers read back from the response cache).

    Keys: `constrained` (decoded inside the answer grammar: a "+ grammar" row), `known` (answers that say),
    `forced_closes` (answers the token budget closed early, constrained; or cut off before their end,
    free), and for constrained answers `grammar_changed` (answers free decoding would have written
    otherwise), `repeat_stops` (answers that ended where the model named an object again: `on_repeat: stop`),
    `substitutions` and `substituted` (`on_repeat: substitute`: items that named an object again and were given
    the model's best unused id instead; per answer, [item, named id, given id or null] for each repeated item),
    `free_known` / `free_parsed` (answers whose free version is known / parses: what the same model would
    score without the grammar, comparable with free-text parse rates), `free_items` / `free_item_errors`
    (items read from the free answers that parse / of those dropped by the item policy) and `free_responses`
    (the free answer where the grammar changed it, else null).
    """
    from degusta_learn.task.answers import AnswerParseError, read_answer

    decs = [s.decoding if s is not None and isinstance(s.decoding, dict) else None for s in samples]
    known = [d for d in decs if d is not None]
    if not known:
        return {}
    constrained = any(d.get("constrained") for d in known)
    out: dict[str, Any] = {"constrained": constrained, "known": len(known)}
    if not constrained:
        out["forced_closes"] = sum(bool(d.get("cut")) for d in known)
        return out
    out["forced_closes"] = sum(bool(d.get("forced_close")) for d in known)
    out["grammar_changed"] = sum(bool(d.get("grammar_changed")) for d in known)
    out["repeat_stops"] = sum(bool(d.get("repeat_stop")) for d in known)
    if any("substituted" in d for d in known):
        swaps = [d.get("substituted") if d is not None and isinstance(d.get("substituted"), list) else None
                 for d in decs]
        out["substitutions"] = sum(sum(1 for s in row if isinstance(s, list) and len(s) == 3 and s[2] is not None)
                                   for row in swaps if row)
        out["substituted"] = swaps
    free_known = free_parsed = free_items = free_dropped = 0
    for s, d in zip(samples, decs):
        if d is None or d.get("free_pass") is False:  # no free answers asked for (`report_unconstrained: false`)
            continue
        # an answer the grammar did not change is its own free answer
        text = d.get("free_text") if d.get("grammar_changed") else s.text
        if not isinstance(text, str):
            continue
        free_known += 1
        try:
            answer = read_answer(text, kind, catalog, grid)
        except AnswerParseError:
            continue
        free_parsed += 1
        free_items += answer.n_read
        free_dropped += len(answer.item_errors)
    out.update(free_known=free_known, free_parsed=free_parsed, free_items=free_items,
               free_item_errors=free_dropped, free_responses=[d.get("free_text") if d else None for d in decs])
    return out


def failure_summary(predictions) -> str:
    """One line for the end of `degusta predict`: failed episodes, and where answers were parsed (zero-shot,
    fine-tuned models) failed samples and dropped items, each with its rate; for a local model, the answers
    the token budget closed early and, with the grammar, how many would parse without it.

    Example: "9 episodes, 1 failed (11.1%); samples: 3 of 45 failed (6.7%); items: 2 of 120 dropped (1.7%)"
    (with "; 2 of them named an object again" inside the parenthesis where they did: `on_repeat: skip`);
    constrained: "...; decoded inside the answer grammar: 2 of 45 answers closed early by the token budget
    (4.4%); without the grammar 31 of 45 would parse (68.9%; the grammar changed 20; 12 of their 150 items
    dropped, 8.0%)".
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
        repeats = sum(_count(d.get("n_item_repeats")) for d in diags)
        line += f"; items: {dropped} of {items} dropped ({_pct(dropped, items)}"
        line += f"; {repeats} of them named an object again)" if repeats else ")"
    decs = [d["decoding"] for d in diags if isinstance(d.get("decoding"), dict) and d["decoding"]]
    if decs:
        known = sum(_count(d.get("known")) for d in decs)
        closed = sum(_count(d.get("forced_closes")) for d in decs)
        if any(d.get("constrained") for d in decs):
            free_known = sum(_count(d.get("free_known")) for d in decs)
            free = sum(_count(d.get("free_parsed")) for d in decs)
            changed = sum(_count(d.get("grammar_changed")) for d in decs)
            items = sum(_count(d.get("free_items")) for d in decs)
            dropped = sum(_count(d.get("free_item_errors")) for d in decs)
            items_note = f"; {dropped} of their {items} items dropped, {_pct(dropped, items)}" if free else ""
            repeats = sum(_count(d.get("repeat_stops")) for d in decs)
            swapped = sum(_count(d.get("substitutions")) for d in decs)
            free_note = (f"; without the grammar {free} of {free_known} would parse "
                         f"({_pct(free, free_known)}; the grammar changed {changed}{items_note})" if free_known else
                         f"; the grammar changed {changed} (their free answers not decoded: "
                         "decoding.report_unconstrained is false)")
            line += (f"; decoded inside the answer grammar: {closed} of {known} answers closed early by the token "
                     f"budget ({_pct(closed, known)})"
                     + (f", {repeats} ended where the model named an object again" if repeats else "")
                     + (f", {swapped} items naming an object again given another id" if swapped else "")
                     + free_note)
        else:
            line += f"; {closed} of {known} answers cut off by the token budget ({_pct(closed, known)})"
    return line


def _count(v) -> int:
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else 0


def _pct(k: int, n: int) -> str:
    return f"{100.0 * k / n:.1f}%" if n else "n/a"
