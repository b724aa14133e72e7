"""A method's prediction made into plan steps a robot can carry out: objects on hand only, on the surface, rotations
in [0, 360), at most `n_objects` steps.

In this order:

1. **Objects on hand.** A placed object that is on hand stays. One that is not is replaced by the free object on
   hand of the same type nearest to it in features (`metrics.matching.hamming`, the distance the scores match
   objects by; ties -> the lower id), at the same place and rotation; with no free object of that type on hand it is
   dropped. Objects the method placed itself are never taken by a replacement. `diagnostics.replaced` and
   `diagnostics.dropped` say what happened.
2. **At most `n_objects` steps**: the first ones are kept (`diagnostics.cut`: how many were left out).
3. **On the surface.** A centroid outside the table's surface polygon is moved to the nearest point of the surface
   (1e-4 inside its edge); `diagnostics.clamped` lists those steps. Every method already places on the surface; this
   is for a method that does not, and for a new table's polygon.
4. **Rounded as every JSON file of the toolkit is**: x, y to 6 decimals, rotation to 4 decimals in [0, 360) (a
   rotation that rounds to 360 is 0), metres to 4 decimals (0.1 mm).
"""

from __future__ import annotations

import numpy as np

from degusta_learn.metrics.matching import hamming
from degusta_learn.planner.episode import Prepared
from degusta_learn.planner.plan import PlanStep, normalized_rotation
from degusta_learn.scene import Placement, Prediction, Table

INSIDE = 1e-4
"""How far inside the surface's edge a clamped position lands (normalized units)."""


def on_hand(placements: list[Placement], prep: Prepared) -> tuple[list[Placement], list[dict], list[dict]]:
    """Step 1 (module docstring): (placements, replaced, dropped); `replaced[i]["step"]` is 1-based in the result."""
    catalog = prep.ds.catalog
    available = sorted(prep.on_hand)
    have = set(available)
    used = {p.object for p in placements if p.object in have}
    out, replaced, dropped = [], [], []
    for p in placements:
        if p.object in have:
            out.append(p)
            continue
        kind = catalog[p.object].type
        free = [o for o in available if o not in used and catalog[o].type == kind]
        if not free:
            some = any(catalog[o].type == kind for o in available)
            dropped.append({"object": p.object, "type": kind, "reason": f"every {kind} on hand is placed already"
                            if some else f"no {kind} on hand"})
            continue
        distance = hamming(catalog.features([p.object]), catalog.features(free))[0]  # (len(free),)
        pick = free[int(np.argmin(distance))]  # first minimum: the lower id
        used.add(pick)
        replaced.append({"step": len(out) + 1, "proposed": p.object, "object": pick, "type": kind,
                         "feature_distance": int(distance.min())})
        out.append(Placement(pick, p.x, p.y, p.rotation))
    return out, replaced, dropped


def nearest_on_surface(table: Table, x: float, y: float) -> tuple[float, float]:
    """The point of `table`'s surface nearest to (x, y): the point itself if inside, else the nearest point of the
    polygon's edges moved INSIDE toward the surface."""
    if bool(table.contains(x, y)):
        return x, y
    poly = np.asarray(table.surface, dtype=float)
    a, b = poly, np.roll(poly, -1, axis=0)  # edges a -> b, (P, 2)
    ab = b - a
    t = np.clip(((np.array([x, y]) - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-18), 0.0, 1.0)
    foot = a + t[:, None] * ab  # (P, 2) nearest point of each edge
    i = int(np.argmin(((foot - [x, y]) ** 2).sum(1)))
    q = foot[i]
    normal = np.array([-ab[i, 1], ab[i, 0]]) / max(float(np.hypot(*ab[i])), 1e-18)
    for step in (INSIDE, -INSIDE, 10 * INSIDE, -10 * INSIDE):
        cand = np.clip(q + step * normal, 0.0, 1.0)
        if bool(table.contains(cand[0], cand[1])):
            return float(cand[0]), float(cand[1])
    return float(np.clip(q[0], 0, 1)), float(np.clip(q[1], 0, 1))  # a sliver thinner than 1e-3: its edge


def finish(prediction: Prediction, prep: Prepared) -> tuple[list[PlanStep], dict]:
    """Steps 1-4 of the module docstring: (the plan steps, the planner's diagnostics)."""
    placements, replaced, dropped = on_hand(list(prediction.placements), prep)
    n = prep.n_objects if prep.n_objects is not None else len(placements)
    cut = max(0, len(placements) - n)
    placements = placements[:n]
    replaced = [r for r in replaced if r["step"] <= n]
    catalog, table, metres = prep.ds.catalog, prep.table, prep.metres
    steps, clamped = [], []
    for i, p in enumerate(placements, start=1):
        x, y = nearest_on_surface(table, float(p.x), float(p.y))
        if (x, y) != (p.x, p.y):
            clamped.append(i)
        x, y = round(x, 6), round(y, 6)
        x_m, y_m = (round(x * metres[0], 4), round(y * metres[1], 4)) if metres else (None, None)
        steps.append(PlanStep(i, int(p.object), catalog[p.object].type, x, y, normalized_rotation(p.rotation),
                              x_m, y_m))
    return steps, {"replaced": replaced, "dropped": dropped, "clamped": clamped, "cut": cut}


__all__ = ["INSIDE", "finish", "nearest_on_surface", "on_hand"]
