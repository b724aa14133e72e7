"""Perception scores of a model's answers to `tasks.PerceptionExamples` (validation and the benchmark).

Per answer (`score_answer`) and over many (`summarize`):

- ``object_f1``: F1 of the predicted set of (type, id) pairs against the scene's, averaged over `list`
  answers (an unreadable answer predicts nothing: F1 0);
- ``cells_exact``: among ground-truth objects whose (type, id) the answer names (`list`, `describe`, `locate`),
  the fraction whose listed cells are exactly the footprint's cells; ``cells_exact_all`` counts the
  objects the answer missed as wrong too;
- ``cell_iou``: the mean intersection-over-union of those cell sets (how close the misses are);
- ``direction``: among the same named objects, the fraction with the right direction, plates left out
  (a round or square plate looks the same pointing N or S: its direction cannot be seen);
- ``transcribe_f1``: the same F1 on `transcribe` answers (copying a scene's list written in the prompt; not
  perception, so not in the headline);
- ``mark_id``: the fraction of `gomo` answers that are exactly the marked id;
- ``parse_rate``: the fraction of `list` / `describe` / `locate` answers `parse_answer` reads;
- ``perception``: the mean of object_f1, cells_exact, direction and mark_id (what picks best.ckpt).

Example:
    rows = [score_answer(ex, text, catalog, grid) for ex, text in zip(examples, texts)]
    summarize(rows)["perception"]
"""

from __future__ import annotations

import math
import re

HEADLINE = ("object_f1", "cells_exact", "direction", "mark_id")


def score_answer(example, text: str, catalog, grid) -> dict:
    """One answer's counts (see the module docstring); `example.meta` holds the task and its truth."""
    from degusta_learn.task.answers import AnswerParseError, parse_answer
    task = example.meta["task"]
    if task == "gomo":
        m = re.fullmatch(r"\s*(\d{1,4})\s*", text)
        return {"task": task, "mark_ok": bool(m) and int(m.group(1)) == example.meta["truth_id"]}
    truth = example.meta["truth"]
    try:
        items = parse_answer(text, "grid", catalog, grid)
        parsed = True
    except AnswerParseError:
        items, parsed = [], False
    pred = {(it.type, it.id): it for it in items}
    want = {(t["type"], t["id"]): t for t in truth}
    tp = len(set(pred) & set(want))
    row = {"task": task, "parsed": parsed, "tp": tp, "fp": len(pred) - tp, "fn": len(want) - tp,
           "n_truth": len(want), "cells_ok": 0, "cell_iou": 0.0, "named": 0, "dir_ok": 0, "dir_n": 0}
    for key, t in want.items():
        it = pred.get(key)
        if it is None:
            continue
        got, exp = set(it.cells or ()), set(t["cells"])
        row["named"] += 1
        row["cells_ok"] += got == exp
        row["cell_iou"] += len(got & exp) / max(1, len(got | exp))
        if t["type"] != "plate":
            row["dir_n"] += 1
            row["dir_ok"] += it.direction == t["direction"]
    return row


def summarize(rows: list[dict]) -> dict:
    """Aggregate `score_answer` rows into the scores of the module docstring (nan where nothing counts)."""
    lists = [r for r in rows if r["task"] == "list"]
    located = [r for r in rows if r["task"] in ("list", "describe", "locate")]
    marks = [r for r in rows if r["task"] == "gomo"]
    named = sum(r["named"] for r in located)

    def ratio(a: float, b: float) -> float:
        return a / b if b else math.nan

    def mean_f1(task_rows: list[dict]) -> float:
        f1s = [ratio(2 * r["tp"], 2 * r["tp"] + r["fp"] + r["fn"]) if (r["tp"] + r["fp"] + r["fn"]) else 1.0
               for r in task_rows]
        return ratio(sum(f1s), len(f1s))

    copies = [r for r in rows if r["task"] == "transcribe"]
    out = {
        "object_f1": mean_f1(lists),
        "transcribe_f1": mean_f1(copies),
        "cells_exact": ratio(sum(r["cells_ok"] for r in located), named),
        "cells_exact_all": ratio(sum(r["cells_ok"] for r in located), sum(r["n_truth"] for r in located)),
        "cell_iou": ratio(sum(r["cell_iou"] for r in located), named),
        "direction": ratio(sum(r["dir_ok"] for r in located), sum(r["dir_n"] for r in located)),
        "mark_id": ratio(sum(r["mark_ok"] for r in marks), len(marks)),
        "parse_rate": ratio(sum(r["parsed"] for r in located), len(located)),
        "n_list": len(lists), "n_describe": sum(r["task"] == "describe" for r in rows),
        "n_locate": sum(r["task"] == "locate" for r in rows), "n_gomo": len(marks),
        "n_transcribe": len(copies),
    }
    present = [out[k] for k in HEADLINE if not math.isnan(out[k])]
    out["perception"] = sum(present) / len(present) if present else math.nan
    return out
