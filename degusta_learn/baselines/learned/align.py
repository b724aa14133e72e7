"""Which context objects play the same part: a deterministic alignment of the context arrangements.

Context arrangements are visited in order; each one's objects are matched one-to-one (Hungarian) to the
groups found so far, by position relative to the surface bounds, requiring the same type and preferring
the same object id (as the `consensus` baseline matches arrangements to its reference); objects left
unmatched, or farther than `MAX_DIST` from every group of their type, start new groups. A group's position
is the running mean of its members. The groups are the slots of the slot model (slots.py); appending the
target arrangement as one more arrangement tells which slots it sets (the training labels).

The alignment is an input, not a decision: the model learns which slots to set, with which objects, where
and in which order; the alignment spares it from discovering correspondences across arrangements by
attention alone, which a CPU-sized token model did not manage (see docs/learned.md).

Usage:
    group, support = align_context(context, tables, vocab)   # (N,), (N,) over the concatenated context
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from degusta_learn.scene import Arrangement, Table

MAX_DIST = 0.3  # bounds-relative units (1 = the whole surface width / height)
FAR = 1e3


def _relative(arr: Arrangement, table: Table) -> np.ndarray:
    x0, y0, x1, y1 = table.bounds
    return (arr.positions - [x0, y0]) / np.maximum([x1 - x0, y1 - y0], 1e-6)


def align_context(context: list[Arrangement], tables: dict[int, Table], types: dict[int, int]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Group index and group support for every placement of `context` (in concatenated order).

    Args:
        context: the context arrangements.
        tables: table id -> Table (for the bounds).
        types: object id -> type index.
    """
    g_uv: list[np.ndarray] = []  # running mean position per group
    g_type: list[int] = []
    g_ids: list[set] = []
    g_n: list[int] = []
    assigned = []
    for arr in context:
        uv = _relative(arr, tables[arr.table])
        kinds = [types[o] for o in arr.objects]
        assign = np.full(len(uv), -1)
        if g_uv:
            dist = np.linalg.norm(uv[:, None] - np.array(g_uv)[None], axis=-1)  # (n, G)
            same = np.array(kinds)[:, None] == np.array(g_type)[None]
            known = np.array([[o in ids for ids in g_ids] for o in arr.objects])
            cost = np.where(same & (dist <= MAX_DIST), dist + 0.1 * ~known, FAR)
            for i, g in zip(*linear_sum_assignment(cost)):
                if cost[i, g] < FAR:
                    assign[i] = g
        for i, o in enumerate(arr.objects):
            g = assign[i]
            if g < 0:
                g_uv.append(uv[i].copy())
                g_type.append(kinds[i])
                g_ids.append(set())
                g_n.append(0)
                g = assign[i] = len(g_uv) - 1
            else:
                g_uv[g] = (g_uv[g] * g_n[g] + uv[i]) / (g_n[g] + 1)
            g_ids[g].add(o)
            g_n[g] += 1
        assigned.append(assign)
    if not assigned:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32)
    group = np.concatenate(assigned).astype(np.int64)
    support = (np.array(g_n, dtype=np.float32) / len(context))[group]
    return group, support
