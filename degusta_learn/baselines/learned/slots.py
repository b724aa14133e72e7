"""Slots: the recurring objects of a participant's context arrangements, as inputs for the slot model.

A *slot* is one part the person keeps setting ("the plate of the near setting", "the fork left of it").
The context arrangements are aligned into slots deterministically (align.py: Hungarian matching by
bounds-relative position, same type required, same object preferred); each slot gathers its members:
which objects filled it, where, how rotated, at which placement step. The slot model (slot_model.py)
then decides, per slot, whether the target gets it, with which object, exactly where and in which order.

Carrying a slot onto the target table. The context arrangements are first *registered* to each other by
translation (each is shifted so its members sit as close as possible to their slots' means, a few
rounds), which removes the per-trial shift of a whole layout. A slot's carried position is its registered
mean, moved so that the layout's centre lands where the context layouts' centres sit relative to their
surface bounds (as `data.swap_table` carries a layout: physical offsets kept, the centre follows the
table). Averaging over the context removes each trial's own noise; the model adds a learned residual.

Context length 0: there is no context to align, so the slots come from the population prior: the
training participants' step-wise mean arrangement on the target table (`heuristic.mean_arrangement`,
stored in the checkpoint), flagged as such. One model serves context 0, 2 and 4.

Targets (training): the target arrangement is aligned to the slots the same way, as one more
arrangement; a slot a target object joins is "set" with that object, position, rotation and step. A
target object that joins no slot (a part the context never showed) cannot be predicted by this model and
is counted as missed.

Usage:
    s = encode_slots(vocab, tables, context, target_table, population, target=None)   # dict of arrays
    batch = collate_slots([s, ...])
"""

from __future__ import annotations

import numpy as np
import torch

from degusta_learn.baselines.heuristic import PopulationModel
from degusta_learn.baselines.learned.align import align_context
from degusta_learn.baselines.learned.features import Vocab, table_geometry
from degusta_learn.errors import DegustaError
from degusta_learn.scene import Arrangement, Dataset, Placement, Table
from degusta_learn.synth.geometry import to_relative, to_table

SLOT_FEATURES = ("support", "population", "members / 4", "mean step / max_objects", "u", "v", "dx", "dy",
                 "spread", "top vote share", "distinct objects / members", "k / 4", "median count / max_objects",
                 "well-supported slots of its type / 4")
SLOT_DIM = len(SLOT_FEATURES)
REGISTER_ROUNDS = 3


def register(xy: list[np.ndarray], groups: list[np.ndarray], n_groups: int) -> list[np.ndarray]:
    """Translations (one (2,) per arrangement) that bring each arrangement's members onto their slot means."""
    shift = [np.zeros(2) for _ in xy]
    for _ in range(REGISTER_ROUNDS):
        pts = np.concatenate([p + s for p, s in zip(xy, shift)])
        g = np.concatenate(groups)
        sums = np.zeros((n_groups, 2))
        np.add.at(sums, g, pts)
        means = sums / np.bincount(g, minlength=n_groups)[:, None]
        shift = [(means[gi] - p).mean(0) for p, gi in zip(xy, groups)]
        mean_shift = np.mean(shift, axis=0)
        shift = [s - mean_shift for s in shift]
    return shift


def population_context(population: dict, table: Table) -> Arrangement:
    """The population's mean arrangement on `table` as a pseudo context arrangement (trial -1)."""
    rows = population.get(table.id) or population.get(-1) or []
    xy = to_table(table, np.array([[u, v] for _, u, v, _ in rows]).reshape(-1, 2))
    return Arrangement("population", -1, table.id, tuple(
        Placement(int(row[0]), float(x), float(y), float(row[3])) for row, (x, y) in zip(rows, xy)))


def population_rows(ds: Dataset, seed: int = 0) -> dict[int, list[list[float]]]:
    """The training participants' mean arrangement per table (key -1: over every table) as plain lists
    [object id, u, v, rotation] (stored in checkpoints; `population_context` reads them)."""
    def rows(model: PopulationModel, key) -> list[list[float]]:
        (objects, uv, rot), _ = model.rows(key)
        return [[int(o), float(u), float(v), float(r)] for o, (u, v), r in zip(objects, uv, rot)]

    per_table = PopulationModel(ds, seed, per_table=True)
    out = {int(t): rows(per_table, t) for t in ds.tables}
    out[-1] = rows(PopulationModel(ds, seed, per_table=False), -1)
    return out


class SlotEncoder:
    """`encode(context, target_table_id, target=None)` -> `encode_slots(...)` with fixed vocabulary, tables,
    population rows and max_objects (a plain object, so DataLoader workers can pickle it)."""

    def __init__(self, vocab: Vocab, tables: dict[int, Table], population: dict, max_objects: int):
        self.vocab, self.tables, self.population, self.max_objects = vocab, tables, population, max_objects

    def __call__(self, context: list[Arrangement], target_table: int, target: Arrangement | None = None) -> dict:
        return encode_slots(self.vocab, self.tables, context, target_table, self.population, target, self.max_objects)


def carry(ctx: list[Arrangement], groups: list[np.ndarray], n_slots: int, tables: dict[int, Table], table: Table
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Slot positions carried onto `table` (module docstring): (slot_xy (S, 2), the layout anchor (2,) on
    `table`, every member's registered position (M, 2), the slot means in the registered frame (S, 2))."""
    ctx_xy = [a.positions for a in ctx]
    shift = register(ctx_xy, groups, n_slots)
    g = np.concatenate(groups)
    pts = np.concatenate([p + s for p, s in zip(ctx_xy, shift)])
    mean = np.zeros((n_slots, 2))
    np.add.at(mean, g, pts)
    mean /= np.bincount(g, minlength=n_slots)[:, None]
    # the layout's centre goes where the context centres sit relative to their surface bounds
    rel_centre = np.mean([to_relative(tables[a.table], a.positions.mean(0)) for a in ctx], axis=0)
    anchor = to_table(table, rel_centre)
    centre = np.mean([(p + s).mean(0) for p, s in zip(ctx_xy, shift)], axis=0)
    return mean - centre + anchor, anchor, pts, mean


def encode_slots(vocab: Vocab, tables: dict[int, Table], context: list[Arrangement], target_table: int,
                 population: dict, target: Arrangement | None = None, max_objects: int = 20) -> dict[str, np.ndarray]:
    """Slot arrays for one episode (`target` None at prediction time).

    Args:
        population: table id -> [(object id, u, v, rotation), ...] population rows (key -1: any table).

    Returns (S = slots): slot_feat (S, SLOT_DIM) (SLOT_FEATURES; u, v relative to the target surface's
    bounds in [-1, 1], dx, dy offset from the layout's centre), slot_type (S,), slot_votes (S, n_obj) member counts per
    object, slot_xy (S, 2) carried position on the target table, slot_rot (S, 2) member mean (sin, cos),
    share (n_obj,) fraction of context arrangements holding each object, taste (n_obj, 2) how common each
    object's colours and materials are among the context objects (`_taste`), tgt_table (), tgt_geom (GEOM_DIM,);
    with a target: y_set (S,) 0/1, y_obj (S,) catalog row (-1 unset), y_xy (S, 2), y_rot (S,) radians,
    y_step (S,), y_missed () target objects in no slot.
    """
    table = tables[target_table]
    is_population = not context
    ctx = context or [population_context(population, table)]
    ctx = [a for a in ctx if a.placements] or ctx
    k = len(context)
    everything = ctx + ([target] if target is not None and target.placements else [])
    group, _ = align_context(everything, tables, vocab.type_of_id)
    sizes = [len(a.placements) for a in everything]
    groups = np.split(group, np.cumsum(sizes)[:-1]) if everything else []
    ctx_groups = groups[:len(ctx)]
    n_slots = int(max((g.max() + 1 for g in ctx_groups if len(g)), default=0))
    if n_slots == 0:
        raise DegustaError(f"no objects to build slots from for table {target_table} (empty context and no "
                           "population rows for this table)")
    slot_xy, anchor, pts, mean = carry(ctx, ctx_groups, n_slots, tables, table)
    g = np.concatenate(ctx_groups)
    members = np.bincount(g, minlength=n_slots).astype(float)
    uv = to_relative(table, slot_xy) * 2 - 1
    spread = np.sqrt(np.bincount(g, weights=((pts - mean[g]) ** 2).sum(1), minlength=n_slots) / members)
    rows = np.concatenate([vocab.rows(a.objects) for a in ctx])
    votes = np.zeros((n_slots, vocab.n_objects), dtype=np.float32)
    np.add.at(votes, (g, rows), 1.0)
    steps = np.concatenate([np.arange(len(a.placements)) for a in ctx]).astype(float)
    mean_step = np.bincount(g, weights=steps, minlength=n_slots) / members
    rad = np.deg2rad(np.concatenate([a.rotations for a in ctx]))
    rot = np.stack([np.bincount(g, weights=np.sin(rad), minlength=n_slots),
                    np.bincount(g, weights=np.cos(rad), minlength=n_slots)], 1) / members[:, None]
    slot_type = np.zeros(n_slots, dtype=np.int64)
    slot_type[g] = vocab.type_of_row[rows]
    median_count = float(np.median([len(a.placements) for a in ctx]))
    n_ctx = max(k, 1)
    strong = members / n_ctx >= 0.5
    same_type = np.bincount(slot_type, weights=strong.astype(float), minlength=len(vocab.types))[slot_type]
    feat = np.stack([
        members / n_ctx if not is_population else np.zeros(n_slots),
        np.full(n_slots, float(is_population)),
        members / 4.0,
        mean_step / max_objects,
        uv[:, 0],
        uv[:, 1],
        slot_xy[:, 0] - anchor[0],
        slot_xy[:, 1] - anchor[1],
        spread,
        votes.max(1) / members,
        (votes > 0).sum(1) / members,
        np.full(n_slots, k / 4.0),
        np.full(n_slots, median_count / max_objects),
        same_type / 4.0,
    ], axis=1).astype(np.float32)
    share = np.zeros(vocab.n_objects, dtype=np.float32)
    for a in ctx:
        share[np.unique(vocab.rows(a.objects))] += 1.0 / len(ctx)
    taste = _taste(vocab, rows)
    out = {"slot_feat": feat, "slot_type": slot_type, "slot_votes": votes, "slot_xy": slot_xy.astype(np.float32),
           "slot_rot": rot.astype(np.float32), "share": share, "taste": taste,
           "tgt_table": np.int64(vocab.table_index.get(target_table, len(vocab.tables))),
           "tgt_geom": table_geometry(table)}
    if target is not None:
        out.update(labels(vocab, target, groups[len(ctx)] if target.placements else np.zeros(0, dtype=np.int64),
                          slot_xy, max_objects))
    return out


def labels(vocab: Vocab, target: Arrangement, target_slots: np.ndarray, slot_xy: np.ndarray, max_objects: int
           ) -> dict[str, np.ndarray]:
    """Training labels per slot from the target's alignment (`target_slots`: slot of each target object;
    a number >= len(slot_xy) is a slot the context never showed): y_set, y_obj (-1 unset), y_xy (unset
    slots keep their carried position), y_rot (radians), y_step, and y_missed (objects in no slot)."""
    if len(target.placements) > max_objects:
        raise DegustaError(f"participant {target.participant!r} trial {target.trial}: {len(target.placements)} "
                           f"objects, more than model.max_objects={max_objects}")
    n_slots = len(slot_xy)
    y_set = np.zeros(n_slots, dtype=np.float32)
    y_obj = np.full(n_slots, -1, dtype=np.int64)
    y_xy = slot_xy.astype(np.float32).copy()
    y_rot = np.zeros(n_slots, dtype=np.float32)
    y_step = np.zeros(n_slots, dtype=np.float32)
    idx = np.nonzero(target_slots < n_slots)[0]
    at = target_slots[idx]
    y_set[at] = 1.0
    y_obj[at] = vocab.rows([target.objects[i] for i in idx])
    y_xy[at] = target.positions[idx]
    y_rot[at] = np.deg2rad(target.rotations[idx])
    y_step[at] = idx / max_objects
    return {"y_set": y_set, "y_obj": y_obj, "y_xy": y_xy, "y_rot": y_rot, "y_step": y_step,
            "y_missed": np.int64(len(target_slots) - len(idx))}


def _taste(vocab: Vocab, rows: np.ndarray) -> np.ndarray:
    """(n_obj, 2): per catalog object, the mean share of the context objects' colour slots (color1, color2)
    that its two colours take, and the same for materials: how well it fits the colours and materials the
    person chose (of any type)."""
    colors = np.concatenate([vocab.codes[rows, 1], vocab.second[rows, 0]])
    materials = np.concatenate([vocab.codes[rows, 2], vocab.second[rows, 1]])
    out = np.zeros((vocab.n_objects, 2), dtype=np.float32)
    for j, (mine, first, second) in enumerate(((colors, vocab.codes[:, 1], vocab.second[:, 0]),
                                               (materials, vocab.codes[:, 2], vocab.second[:, 1]))):
        hist = np.bincount(mine, minlength=vocab.sizes[1 + j]) / max(len(mine), 1)
        out[:, j] = (hist[first] + hist[second]) / 2
    return out


def _pad(arrays: list[np.ndarray], value=0) -> tuple[torch.Tensor, torch.Tensor]:
    n = max((len(a) for a in arrays), default=0)
    first = arrays[0]
    out = np.full((len(arrays), n, *first.shape[1:]), value, dtype=first.dtype)
    mask = np.zeros((len(arrays), n), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
        mask[i, : len(a)] = True
    return torch.from_numpy(out), torch.from_numpy(mask)


def collate_slots(samples: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    """Pad samples into a batch: per-slot arrays become (B, S, ...) with slot_mask (B, S) (True = real slot);
    share (B, n_obj), taste (B, n_obj, 2), tgt_table (B,), tgt_geom (B, GEOM_DIM); index (B,) and y_missed (B,) when present."""
    batch: dict[str, torch.Tensor] = {}
    keys = ["slot_feat", "slot_type", "slot_votes", "slot_xy", "slot_rot"]
    keys += [k for k in ("y_set", "y_obj", "y_xy", "y_rot", "y_step") if k in samples[0]]
    for key in keys:
        batch[key], batch["slot_mask"] = _pad([s[key] for s in samples], -1 if key == "y_obj" else 0)
    for key in ("share", "taste", "tgt_geom"):
        batch[key] = torch.from_numpy(np.stack([s[key] for s in samples]))
    for key in ("tgt_table", "index", "y_missed"):
        if key in samples[0]:
            batch[key] = torch.tensor([int(s[key]) for s in samples])
    return batch
