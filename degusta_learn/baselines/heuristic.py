"""Heuristic baselines: `random`, `population_mean`, `copy_nearest`, `consensus` (the bar every method meets).

- **random**: `min_objects`..`max_objects` distinct random objects at uniform random spots on the target
  surface, with uniform random rotations (seeded by the config seed and the episode id).
- **population_mean**: the population's "average table" over TRAINING participants only
  (`split_participants(..., seed)["train"]`, whatever split is predicted): the most common arrangement
  length; per placement step, the most common object type at that step, the most common object id of
  that type at that step (not used yet), the mean position relative to the surface bounds and the
  circular-mean rotation. With `per_table`, only training arrangements on the target table are used
  (all of them if there are none).
- **copy_nearest**: the participant's context arrangement on the target table if there is one, else the
  one whose table is nearest in shape and size (`transfer.table_distance`; ties -> the latest trial),
  carried onto the target table with positions mapped relative to the surface bounds.
- **consensus**: the nearest context arrangement is the reference; every other context arrangement is
  matched to it (Hungarian; same type required, same id preferred, then nearer relative positions).
  A reference object is kept if its type is matched in at least `min_support` of the context
  arrangements; the kept objects are cut to the median context length (least supported first); each
  gets the most common matched id, the median relative position and the circular-mean rotation.

With context length 0 the context-based baselines (`copy_nearest`, `consensus`) fall back to
population_mean; their predictions say so in `diagnostics["fallback"]`.

Usage:
    degusta predict --config configs/baseline_copy_nearest.yaml
    degusta predict --config configs/baseline_random.yaml --set context=0 --set out=runs/random/k0.jsonl
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from degusta_learn.baselines.transfer import (
    circular_mean,
    place_on,
    relative_positions,
    stable_seed,
    table_distance,
)
from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.scene import Arrangement, Dataset, Episode, Prediction, Table, split_participants
from degusta_learn.synth.geometry import bounds, inside, to_relative

Rows = tuple[list[int], np.ndarray, np.ndarray]  # objects, relative positions (N, 2), rotations (N,)


@dataclass
class RandomConfig(PredictConfig):
    """Predict config of `random`."""

    min_objects: int = 3
    """Fewest objects per prediction."""
    max_objects: int = 8
    """Most objects per prediction (inclusive)."""

    def __post_init__(self):
        super().__post_init__()
        if not 1 <= self.min_objects <= self.max_objects:
            raise DegustaError(f"min_objects/max_objects: expected 1 <= min_objects <= max_objects, "
                               f"got {self.min_objects} and {self.max_objects}")


@dataclass
class PopulationMeanConfig(PredictConfig):
    """Predict config of `population_mean`."""

    per_table: bool = True
    """Use only training arrangements on the target table (True) or on every table (False)."""


@dataclass
class CopyNearestConfig(PredictConfig):
    """Predict config of `copy_nearest` (no keys of its own)."""


@dataclass
class ConsensusConfig(PredictConfig):
    """Predict config of `consensus`."""

    min_support: float = 0.5
    """Keep a reference object if its type is matched in at least this share of the context arrangements."""

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.min_support <= 1.0:
            raise DegustaError(f"min_support: expected a share in [0, 1], got {self.min_support}")


def target_table(ds: Dataset, ep: Episode) -> Table:
    """The table of the episode's target trial (the empty table every method is shown)."""
    return ds.tables[ds.arrangement(ep.participant, ep.target).table]


def _prediction(cfg, ep: Episode, placements, **diagnostics) -> Prediction:
    return Prediction(ep.id, ep.participant, ep.target, cfg.method, placements, diagnostics=diagnostics)


# --- random -------------------------------------------------------------------------------------------

def run_random(cfg: RandomConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    out = []
    ids = np.array(ds.catalog.ids)
    for ep in episodes:
        rng = np.random.default_rng(stable_seed(cfg.seed, ep.id))
        table = target_table(ds, ep)
        hi = min(cfg.max_objects, len(ids))
        n = int(rng.integers(min(cfg.min_objects, hi), hi + 1))
        objects = rng.choice(ids, size=n, replace=False).tolist()
        x0, y0, x1, y1 = bounds(table)
        cand = rng.uniform([x0, y0], [x1, y1], size=(n, 64, 2))  # 64 tries per object
        ok = inside(table, cand)
        first = np.where(ok.any(1), ok.argmax(1), 0)
        xy = cand[np.arange(n), first]
        uv = to_relative(table, xy)
        out.append(_prediction(cfg, ep, place_on(table, ds.catalog, objects, uv, rng.uniform(0, 360, n))))
    return out


# --- population mean ------------------------------------------------------------------------------------

def _mode(counter: Counter):
    """Most common key; ties -> the smallest key (deterministic)."""
    return min(counter.items(), key=lambda kv: (-kv[1], kv[0]))[0]


def mean_arrangement(ds: Dataset, arrangements: list[Arrangement]) -> Rows:
    """The step-wise population mean of `arrangements` (see the module docstring)."""
    cat = ds.catalog
    n = _mode(Counter(len(a.placements) for a in arrangements))
    overall = Counter(p.object for a in arrangements for p in a.placements)
    rel = [relative_positions(a, ds.tables[a.table]) for a in arrangements]
    objects, uv, rot, used = [], [], [], set()
    for i in range(n):
        at = [(a.placements[i], r[i]) for a, r in zip(arrangements, rel) if len(a.placements) > i]
        type_ = _mode(Counter(cat[p.object].type for p, _ in at))
        same = [(p, r) for p, r in at if cat[p.object].type == type_]
        step = Counter(p.object for p, _ in same)
        ranked = sorted(step, key=lambda o: (-step[o], o))
        ranked += sorted((o for o in overall if cat[o].type == type_ and o not in step), key=lambda o: (-overall[o], o))
        pick = next((o for o in ranked if o not in used), None)
        if pick is None:
            continue
        used.add(pick)
        objects.append(pick)
        uv.append(np.mean([r for _, r in same], axis=0))
        rot.append(circular_mean([p.rotation for p, _ in same]))
    return objects, np.array(uv).reshape(-1, 2), np.array(rot)


class PopulationModel:
    """Population means of the training participants, per target table (computed on first use)."""

    def __init__(self, ds: Dataset, seed: int = 0, per_table: bool = True):
        self.ds, self.per_table = ds, per_table
        self.train = split_participants(ds.participants, seed)["train"]
        keep = set(self.train)
        self.arrangements = [a for a in ds.arrangements if a.participant in keep]
        self._cache: dict = {}

    def rows(self, table_id: int) -> tuple[Rows, int]:
        """(the mean arrangement, how many training arrangements it averages) for a target table."""
        key = table_id if self.per_table else None
        if key not in self._cache:
            pool = [a for a in self.arrangements if key is None or a.table == key] or self.arrangements
            self._cache[key] = (mean_arrangement(self.ds, pool), len(pool))
        return self._cache[key]

    def predict(self, cfg, ep: Episode, **diagnostics) -> Prediction:
        table = target_table(self.ds, ep)
        (objects, uv, rot), n = self.rows(table.id)
        return _prediction(cfg, ep, place_on(table, self.ds.catalog, objects, uv, rot),
                           population_arrangements=n, **diagnostics)


def run_population_mean(cfg: PopulationMeanConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    model = PopulationModel(ds, cfg.seed, cfg.per_table)
    return [model.predict(cfg, ep) for ep in episodes]


# --- context-based: copy_nearest and consensus -------------------------------------------------------------

def nearest_context(ds: Dataset, context: list[Arrangement], table: Table) -> Arrangement:
    """The context arrangement on `table`, else on the most similar table; ties -> the latest trial."""
    return min(context, key=lambda a: (table_distance(ds.tables[a.table], table) if a.table != table.id else -1.0,
                                       -a.trial))


def copy_rows(ds: Dataset, context: list[Arrangement], table: Table) -> tuple[Rows, dict]:
    src = nearest_context(ds, context, table)
    rows = (src.objects, relative_positions(src, ds.tables[src.table]), src.rotations)
    return rows, {"source_trial": src.trial, "source_table": src.table}


def consensus_rows(ds: Dataset, context: list[Arrangement], table: Table, min_support: float = 0.5,
                   reference: Arrangement | None = None) -> tuple[Rows, dict]:
    """`consensus`'s rows (module docstring) of `context` for `table`; `reference`: the arrangement the others are
    matched to (default: the nearest context arrangement; `collaborative` passes its nearest neighbour's)."""
    cat = ds.catalog
    ref = reference if reference is not None else nearest_context(ds, context, table)
    ref_uv = relative_positions(ref, ds.tables[ref.table])
    groups = [[(p.object, ref_uv[i], p.rotation)] for i, p in enumerate(ref.placements)]
    for a in context:
        if a is ref:
            continue
        uv = relative_positions(a, ds.tables[a.table])
        cost = np.linalg.norm(ref_uv[:, None] - uv[None], axis=-1)  # (n_ref, n_a)
        cost += np.array([[0.0 if p.object == q.object else 1.0 if cat[p.object].type == cat[q.object].type else 1e3
                           for q in a.placements] for p in ref.placements])
        for r, c in zip(*linear_sum_assignment(cost)):
            if cost[r, c] < 1e3:
                groups[r].append((a.placements[c].object, uv[c], a.placements[c].rotation))
    support = [len(g) / len(context) for g in groups]
    keep = [i for i, s in enumerate(support) if s >= min_support]
    n_target = int(round(float(np.median([len(a.placements) for a in context]))))
    if len(keep) > n_target:
        keep = sorted(sorted(keep, key=lambda i: (-support[i], i))[:n_target])
    objects, uv, rot, used = [], [], [], set()
    for i in keep:
        votes = Counter(o for o, _, _ in groups[i] if o not in used)
        if not votes:
            continue
        pick = min(votes, key=lambda o: (-votes[o], o != ref.placements[i].object, o))
        used.add(pick)
        objects.append(pick)
        uv.append(np.median([u for _, u, _ in groups[i]], axis=0))
        rot.append(circular_mean([r for _, _, r in groups[i]]))
    rows = (objects, np.array(uv).reshape(-1, 2), np.array(rot))
    return rows, {"reference_trial": ref.trial, "support": [round(support[i], 3) for i in keep]}


def with_population_fallback(cfg, ds: Dataset, episodes: list[Episode], predict_one,
                             reason: str = "no context arrangements (context length 0)") -> list[Prediction]:
    """`predict_one(ep)` for every episode with context; an episode without context gets population_mean's
    prediction, marked as that fallback with `reason` (the population is built once, on first need)."""
    population = None
    out = []
    for ep in episodes:
        if not ep.context:
            population = population or PopulationModel(ds, cfg.seed)
            out.append(population.predict(cfg, ep, fallback="population_mean", reason=reason))
        else:
            out.append(predict_one(ep))
    return out


def run_context(cfg, ds: Dataset, episodes: list[Episode], rows_fn) -> list[Prediction]:
    """Predictions of a context-based method: `rows_fn(ds, context arrangements, target table)` -> (rows,
    diagnostics) per episode, placed on the target table; episodes without context fall back to population_mean
    (shared by `copy_nearest`, `consensus`, `slot_heuristic` and `collaborative`)."""
    def predict_one(ep: Episode) -> Prediction:
        table = target_table(ds, ep)
        context = [ds.arrangement(ep.participant, t) for t in ep.context]
        (objects, uv, rot), diagnostics = rows_fn(ds, context, table)
        return _prediction(cfg, ep, place_on(table, ds.catalog, objects, uv, rot), **diagnostics)

    return with_population_fallback(cfg, ds, episodes, predict_one)


def run_copy_nearest(cfg: CopyNearestConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    return run_context(cfg, ds, episodes, copy_rows)


def run_consensus(cfg: ConsensusConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    return run_context(cfg, ds, episodes, lambda d, c, t: consensus_rows(d, c, t, cfg.min_support))


RANDOM = MethodSpec(RandomConfig, run_random, "random objects at random spots and rotations on the target table")
POPULATION_MEAN = MethodSpec(PopulationMeanConfig, run_population_mean,
                             "the training participants' step-wise mean arrangement on the target table")
COPY_NEAREST = MethodSpec(CopyNearestConfig, run_copy_nearest,
                          "the context arrangement on the most similar table, carried onto the target table")
CONSENSUS = MethodSpec(ConsensusConfig, run_consensus,
                       "objects and median positions agreed across the context arrangements")
