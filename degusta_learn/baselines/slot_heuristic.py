"""`slot_heuristic`: the learned slot model's deterministic starting point, with nothing learned.

The context arrangements are aligned into slots and carried onto the target table with the learned model's
own code (`learned.align.align_context`, `learned.slots.carry`; docs/learned.md, "Architecture"): a slot is one
part the person keeps setting, its carried position the registered mean of its members with the layout's centre
placed where the context centres sit relative to their surface bounds. Then, instead of a model:

- a slot is set when its *support* (the share of the context arrangements that filled it) is at least
  `min_support`; when none is, the best-supported slot is set (an empty answer scores the worst);
- each set slot gets its *voted* object, the one that filled it most often. Slots choose in order of support
  (then the top vote's share), each taking its most voted object not taken yet (an object fills one slot);
  ties go to the object that more context arrangements hold anywhere, then to the smaller id. A slot whose
  objects are all taken stays empty;
- the object sits at the slot's carried position, turned by the circular mean of its members' rotations;
- the objects are listed in the order of their slots' mean placement step.

Context length 0 falls back to the population prior, as the learned model's does: the training participants'
step-wise mean arrangement on the target table (`population_mean`); predictions say so in
`diagnostics["fallback"]`.

It imports torch (through `learned.slots`, whose carrying it reuses), unlike the other heuristic baselines.

Usage:
    degusta predict --config configs/baseline_slot_heuristic.yaml
    degusta predict --config configs/baseline_slot_heuristic.yaml --set min_support=0.75 --set split=val
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from degusta_learn.baselines.heuristic import Rows, run_context
from degusta_learn.baselines.learned.align import align_context
from degusta_learn.baselines.learned.slots import carry
from degusta_learn.baselines.transfer import circular_mean
from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.scene import Arrangement, Dataset, Episode, Prediction, Table
from degusta_learn.synth.geometry import to_relative


@dataclass
class SlotHeuristicConfig(PredictConfig):
    """Predict config of `slot_heuristic`."""

    min_support: float = 0.5
    """Set a slot filled in at least this share of the context arrangements (higher = fewer objects)."""

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.min_support <= 1.0:
            raise DegustaError(f"min_support: expected a share in [0, 1], got {self.min_support}")


def slot_rows(ds: Dataset, context: list[Arrangement], table: Table, min_support: float = 0.5) -> tuple[Rows, dict]:
    """The slot heuristic's rows (objects, positions relative to `table`'s bounds, rotations) and diagnostics."""
    k = len(context)
    ctx = [a for a in context if a.placements]
    if not ctx:
        return ([], np.zeros((0, 2)), np.zeros(0)), {"slots": 0, "support": []}
    type_index = {t: i for i, t in enumerate(ds.catalog.types)}
    types = {o.id: type_index[o.type] for o in ds.catalog}
    group, _ = align_context(ctx, ds.tables, types)  # (M,) slot of every context placement, concatenated
    groups = np.split(group, np.cumsum([len(a.placements) for a in ctx])[:-1])
    n_slots = int(group.max()) + 1
    slot_xy, *_ = carry(ctx, groups, n_slots, ds.tables, table)  # (S, 2) on the target table
    members = np.bincount(group, minlength=n_slots)
    support = members / k
    objects = np.concatenate([a.objects for a in ctx])
    steps = np.concatenate([np.arange(len(a.placements)) for a in ctx]).astype(float)
    rotations = np.concatenate([a.rotations for a in ctx])
    mean_step = np.bincount(group, weights=steps, minlength=n_slots) / members
    votes = [Counter(objects[group == s].tolist()) for s in range(n_slots)]
    held = Counter(o for a in ctx for o in set(a.objects))  # context arrangements holding each object

    keep = [s for s in range(n_slots) if support[s] >= min_support - 1e-9] or [int(np.argmax(support))]
    keep.sort(key=lambda s: (-support[s], -max(votes[s].values()) / members[s], s))
    chosen: dict[int, int] = {}
    for s in keep:
        free = [o for o in votes[s] if o not in chosen.values()]
        if free:
            chosen[s] = min(free, key=lambda o: (-votes[s][o], -held[o], o))
    order = sorted(chosen, key=lambda s: (mean_step[s], s))
    uv = to_relative(table, slot_xy[order]) if order else np.zeros((0, 2))
    rot = np.array([circular_mean(rotations[group == s]) for s in order])
    rows = ([chosen[s] for s in order], uv.reshape(-1, 2), rot)
    return rows, {"slots": n_slots, "support": [round(float(support[s]), 3) for s in order]}


def run_slot_heuristic(cfg: SlotHeuristicConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    return run_context(cfg, ds, episodes, lambda d, c, t: slot_rows(d, c, t, cfg.min_support))


SLOT_HEURISTIC = MethodSpec(SlotHeuristicConfig, run_slot_heuristic,
                            "the learned model's aligned slots without learning: supported slots, voted objects, "
                            "registered mean positions")
