"""`collaborative`: collaborative filtering across participants: what the people whose tables resemble this
person's context set on the target table.

Neighbours are TRAINING participants only (`split_participants(..., seed)["train"]`, whatever split is predicted;
never the episode's own participant), so no validation or test arrangement is ever read as an answer.

Similarity (`similarity`), one of two:

`tables`: how well a training participant's arrangements would have predicted this person's context: the mean,
over the context arrangements, of the set-aware score (`metrics.score_many`'s `set_rmsd`, the score that ranks
methods) of the participant's arrangement on the same table taken as a prediction of the person's (collaborative
filtering's "co-rated items", with tables as the items). A participant who set none of the context tables is at
the worst distance, `SET_PENALTY`.

`features`: every participant gets a profile of table-independent features, averaged over arrangements (the
person: their context arrangements; a training participant: all of theirs):

- `objects`: the share of arrangements holding each catalog object (their favourite objects);
- `types`: the mean count of each object type per arrangement (what and how much they set);
- `taste`: the distribution of the colours and of the materials of the objects they set (color1/color2,
  material1/material2);
- `layout`: per object type, the mean position relative to the surface bounds (where they put it).

The distance of two profiles is `w_objects * d_objects + w_types * d_types + w_taste * d_taste + w_layout *
d_layout`, each term in [0, 1]: weighted Jaccard distances (1 - sum(min) / sum(max)) for objects and types, the
mean total-variation distance of the colour and material distributions, and for layout the mean, over the types
either profile sets, of the distance of the two mean positions (capped at 1; 1 for a type only one sets). The
`k` nearest training participants are the neighbours (ties, under either similarity: the smaller participant
id).

Prediction. Each neighbour contributes its own arrangement on the target table, or, when it never set that
table, its arrangement on the most similar table carried onto it relative to the surface bounds (`copy_nearest`'s
rule). These are combined as `consensus` combines context arrangements (`heuristic.consensus_rows`, with the
nearest neighbour's arrangement as the reference and `min_support`). With `own_objects`, each predicted object is
then replaced by an object of the same type from the person's own context (their most held first, each once),
while there is one: the neighbours give the layout, the person their objects.

Context length 0 falls back to population_mean (no context, no neighbours to find).

Usage:
    degusta predict --config configs/baseline_collaborative.yaml
    degusta predict --config configs/baseline_collaborative.yaml --set k=5 --set split=val
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Literal

import numpy as np

from degusta_learn.baselines.heuristic import Rows, consensus_rows, nearest_context, run_context
from degusta_learn.baselines.transfer import relative_positions
from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.metrics import SET_PENALTY, score_many
from degusta_learn.scene import Arrangement, Catalog, Dataset, Episode, Prediction, Table, split_participants

WEIGHTS = ("w_objects", "w_types", "w_taste", "w_layout")


@dataclass
class CollaborativeConfig(PredictConfig):
    """Predict config of `collaborative`."""

    k: int = 1
    """Neighbours (training participants) whose arrangements are combined."""
    similarity: Literal["tables", "features"] = "tables"
    """How neighbours are found: set RMSD on the tables both set ("tables") or table-independent profiles
    ("features", weighted by the w_ keys)."""
    min_support: float = 0.5
    """Keep a reference object if its type is matched in at least this share of the neighbours' arrangements."""
    own_objects: bool = False
    """Replace each predicted object by one of the same type from the person's own context, while there is one."""
    w_objects: float = 1.0
    """Weight of the favourite-objects term of the "features" distance."""
    w_types: float = 1.0
    """Weight of the object-types-and-counts term."""
    w_taste: float = 1.0
    """Weight of the colours-and-materials term."""
    w_layout: float = 1.0
    """Weight of the per-type-position term (relative to the surface bounds)."""

    def __post_init__(self):
        super().__post_init__()
        if isinstance(self.k, bool) or self.k < 1:
            raise DegustaError(f"k: expected a number of neighbours >= 1, got {self.k}")
        if not 0.0 <= self.min_support <= 1.0:
            raise DegustaError(f"min_support: expected a share in [0, 1], got {self.min_support}")
        for key in WEIGHTS:
            if not getattr(self, key) >= 0.0:
                raise DegustaError(f"{key}: expected a weight >= 0, got {getattr(self, key)}")
        if not sum(getattr(self, key) for key in WEIGHTS) > 0.0:
            raise DegustaError(f"{', '.join(WEIGHTS)}: at least one weight must be > 0")


@dataclass
class Profiles:
    """Profiles of P participants (module docstring), as arrays for one vectorized distance."""

    objects: np.ndarray  # (P, n_objects) share of arrangements holding each object
    types: np.ndarray  # (P, n_types) mean count per arrangement
    colors: np.ndarray  # (P, n_colors) distribution
    materials: np.ndarray  # (P, n_materials) distribution
    layout: np.ndarray  # (P, n_types, 2) mean bounds-relative position (0 where the type is never set)


class Featurizer:
    """Builds `Profiles` from arrangements with the dataset's catalog and tables."""

    def __init__(self, catalog: Catalog, tables: dict[int, Table]):
        self.tables = tables
        self.row = {o.id: i for i, o in enumerate(catalog)}
        types = catalog.types
        colors = sorted({c for o in catalog for c in (o.color1, o.color2)})
        materials = sorted({m for o in catalog for m in (o.material1, o.material2)})
        self.type_of = np.array([types.index(o.type) for o in catalog])
        self.color_of = np.array([[colors.index(o.color1), colors.index(o.color2)] for o in catalog])
        self.material_of = np.array([[materials.index(o.material1), materials.index(o.material2)] for o in catalog])
        self.sizes = (len(catalog), len(types), len(colors), len(materials))

    def profiles(self, people: list[list[Arrangement]]) -> Profiles:
        n_obj, n_types, n_col, n_mat = self.sizes
        out = Profiles(np.zeros((len(people), n_obj)), np.zeros((len(people), n_types)),
                       np.zeros((len(people), n_col)), np.zeros((len(people), n_mat)),
                       np.zeros((len(people), n_types, 2)))
        for i, arrangements in enumerate(people):
            rows = [np.array([self.row[o] for o in a.objects], dtype=int) for a in arrangements]
            n = max(len(arrangements), 1)
            for r in rows:
                out.objects[i, np.unique(r)] += 1.0 / n
            every = np.concatenate(rows) if rows else np.zeros(0, dtype=int)
            out.types[i] = np.bincount(self.type_of[every], minlength=n_types) / n
            out.colors[i] = _distribution(self.color_of[every].ravel(), n_col)
            out.materials[i] = _distribution(self.material_of[every].ravel(), n_mat)
            if len(every):
                uv = np.concatenate([relative_positions(a, self.tables[a.table]) for a in arrangements])
                count = np.bincount(self.type_of[every], minlength=n_types)
                for axis in range(2):
                    out.layout[i, :, axis] = np.bincount(self.type_of[every], weights=uv[:, axis],
                                                         minlength=n_types) / np.maximum(count, 1)
        return out


def _distribution(codes: np.ndarray, size: int) -> np.ndarray:
    counts = np.bincount(codes, minlength=size).astype(float)
    return counts / counts.sum() if counts.sum() else counts


def _jaccard_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """1 - sum(min) / sum(max) of a (D,) against each row of b (P, D); 0 when both are all zero."""
    top = np.maximum(a, b).sum(1)
    return np.where(top > 0, 1.0 - np.minimum(a, b).sum(1) / np.where(top > 0, top, 1.0), 0.0)


def distances(query: Profiles, pool: Profiles, weights: tuple[float, float, float, float]) -> np.ndarray:
    """(P,) distance of the one-person profile `query` to each of `pool`'s P profiles (module docstring)."""
    w_objects, w_types, w_taste, w_layout = weights
    d_objects = _jaccard_distance(query.objects[0], pool.objects)
    d_types = _jaccard_distance(query.types[0], pool.types)
    d_taste = 0.25 * (np.abs(query.colors[0] - pool.colors).sum(1) + np.abs(query.materials[0] - pool.materials).sum(1))
    mine, theirs = query.types[0] > 0, pool.types > 0  # (T,), (P, T)
    gap = np.minimum(np.linalg.norm(query.layout[0] - pool.layout, axis=-1), 1.0)  # (P, T)
    gap = np.where(mine & theirs, gap, 1.0)
    either = mine | theirs
    d_layout = np.where(either, gap, 0.0).sum(1) / np.maximum(either.sum(1), 1)
    return w_objects * d_objects + w_types * d_types + w_taste * d_taste + w_layout * d_layout


class NeighbourModel:
    """The training participants (their arrangements and profiles), and the k nearest of them to a context."""

    def __init__(self, ds: Dataset, seed: int = 0):
        self.catalog = ds.catalog
        self.featurize = Featurizer(ds.catalog, ds.tables)
        by_p = ds.by_participant()
        self.train = split_participants(ds.participants, seed)["train"]
        self.arrangements = [by_p[p] for p in self.train]
        self.pool = self.featurize.profiles(self.arrangements)
        self._table_scores: dict[tuple[str, int], np.ndarray] = {}

    def table_scores(self, arrangement: Arrangement) -> np.ndarray:
        """(P,) set RMSD of each training participant's arrangement on `arrangement`'s table as a prediction of
        it (nan for a participant who never set that table); cached per (participant, trial)."""
        key = (arrangement.participant, arrangement.trial)
        if key not in self._table_scores:
            theirs = [[a for a in mine if a.table == arrangement.table] for mine in self.arrangements]
            have = [i for i, same in enumerate(theirs) if same]
            scores = score_many(self.catalog, [arrangement] * len(have),
                                [max(theirs[i], key=lambda a: a.trial) for i in have])
            out = np.full(len(self.train), np.nan)
            out[have] = [s.set_rmsd for s in scores]
            self._table_scores[key] = out
        return self._table_scores[key]

    def distances(self, context: list[Arrangement], cfg: CollaborativeConfig) -> np.ndarray:
        """(P,) distance of the person behind `context` to each training participant (module docstring)."""
        if cfg.similarity == "features":
            return distances(self.featurize.profiles([context]), self.pool, tuple(getattr(cfg, k) for k in WEIGHTS))
        scores = np.array([self.table_scores(a) for a in context])  # (k, P)
        seen = ~np.isnan(scores)
        total = np.where(seen, scores, 0.0).sum(0)
        return np.where(seen.any(0), total / np.maximum(seen.sum(0), 1), SET_PENALTY)

    def nearest(self, context: list[Arrangement], cfg: CollaborativeConfig) -> list[int]:
        """Indices into `self.train` of the `cfg.k` nearest training participants (never the context's own)."""
        d = self.distances(context, cfg)
        own = {a.participant for a in context}
        order = [int(i) for i in np.lexsort((np.arange(len(d)), d)) if self.train[i] not in own]
        return order[:cfg.k]


def own_objects(catalog: Catalog, objects: list[int], context: list[Arrangement]) -> list[int]:
    """`objects` with each replaced by a not-yet-used context object of its type (most held first, then the
    smaller id), while the context has one; an object neither replaced nor free is dropped (no object twice)."""
    held = Counter(o for a in context for o in set(a.objects))
    mine: dict[str, list[int]] = {}
    for o in sorted(held, key=lambda o: (-held[o], o)):
        mine.setdefault(catalog[o].type, []).append(o)
    out: list[int | None] = []
    for o in objects:
        pool = mine.get(catalog[o].type)
        out.append(pool.pop(0) if pool else None)
    used = {o for o in out if o is not None}
    for i, o in enumerate(objects):
        if out[i] is None and o not in used:
            out[i] = o
            used.add(o)
    return [o if o is not None else -1 for o in out]


def collaborative_rows(model: NeighbourModel, cfg: CollaborativeConfig, ds: Dataset, context: list[Arrangement],
                       table: Table) -> tuple[Rows, dict]:
    """The neighbours' combined rows for `table` (module docstring) and diagnostics naming the neighbours."""
    near = model.nearest(context, cfg)
    picked = [nearest_context(ds, model.arrangements[i], table) for i in near]
    (objects, uv, rot), info = consensus_rows(ds, picked, table, cfg.min_support, reference=picked[0])
    if cfg.own_objects:
        objects = own_objects(ds.catalog, objects, context)
        keep = [i for i, o in enumerate(objects) if o >= 0]
        objects, uv, rot = [objects[i] for i in keep], uv[keep], rot[keep]
    return (objects, uv, rot), {"neighbours": [model.train[i] for i in near], "support": info["support"]}


def run_collaborative(cfg: CollaborativeConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    model = NeighbourModel(ds, cfg.seed)
    if not model.train:
        raise DegustaError(f"{cfg.dataset}: no training participants to take neighbours from")
    return run_context(cfg, ds, episodes, lambda d, c, t: collaborative_rows(model, cfg, d, c, t))


COLLABORATIVE = MethodSpec(CollaborativeConfig, run_collaborative,
                           "the arrangements of the training participants whose contexts resemble this person's, "
                           "combined as consensus combines")
