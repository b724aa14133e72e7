"""A plan request as the one episode every method already answers: a dataset, an episode, a target that holds no answer.

The planner's dataset (its config's `dataset`) gives the catalog, the tables and the population (the other
participants' arrangements, which `population_mean`, the context-0 fallbacks and the neighbour methods read). The
request's person replaces whatever that dataset holds under their id: their past arrangements (inline, or the trials
of a dataset's participant) are the episode's context, and the target is a new trial on the table to set with no
placements. That target is reachable by `Dataset.arrangement` (every method reads its table there) but is none of
`Dataset.arrangements`, so no method can count it, learn from it or read an answer from it.

A request built from a dataset episode (its participant, its context trials, its target's table) is therefore the
episode `degusta predict` runs, less the answer: the same population, the same split of participants (the same ids),
the same context.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from degusta_learn.planner.request import DEFAULT_PERSON, MAX_CONTEXT, At, NewTable, PlanRequest, new_table, shown
from degusta_learn.scene import Arrangement, Catalog, Dataset, Episode, Table
from degusta_learn.scene.validate import check_picture


@dataclass
class PlanningDataset(Dataset):
    """A Dataset whose `target` arrangement (empty) is found by `arrangement()` but is not in `arrangements`; its
    person is one of `participants`."""

    target: Arrangement | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.target is not None:
            self._by_key[(self.target.participant, self.target.trial)] = self.target

    @property
    def participants(self) -> list[str]:
        """Every participant, the target's person included (with no past arrangement, as at context 0, they are
        still one of the ids the participant split is drawn over, as in the dataset `degusta predict` reads)."""
        ids = {a.participant for a in self.arrangements}
        return sorted(ids | {self.target.participant} if self.target is not None else ids)


@dataclass(frozen=True)
class Prepared:
    """What a method is given for one request, and what the plan is finished with."""

    ds: PlanningDataset
    episode: Episode
    table: Table
    on_hand: tuple[int, ...]
    """The objects on hand, in catalog order."""
    metres: tuple[float, float] | None
    n_objects: int | None


def _fmt_ids(ids) -> str:
    ids = sorted(ids)
    return ", ".join(map(str, ids[:8])) + (f" ... ({len(ids)} in all)" if len(ids) > 8 else "")


def check_catalog(entries: tuple[dict, ...], catalog: Catalog, where: str) -> None:
    """`request.catalog` must be the planner's catalog (the one its method was trained and evaluated with), entry
    by entry; the first difference is named. Pictures (`image`) are not compared."""
    at = At() / "catalog"
    mine = {o.id: o.to_json(with_image=False) for o in catalog}
    given = set()
    for i, entry in enumerate(entries):
        here = at / i
        oid = entry.get("id")
        if isinstance(oid, bool) or not isinstance(oid, int):
            raise here.fail("id", f"expected an object id, got {shown(oid)}")
        if oid not in mine:
            raise here.fail("id", f"object {oid} is not in the planner's catalog ({where}); the planner plans with "
                                  "the catalog its method was trained and evaluated on")
        if oid in given:
            raise here.fail("id", f"object {oid} is listed twice")
        given.add(oid)
        expected = mine[oid]
        for key, value in entry.items():
            if key == "image":
                continue
            if key not in expected:
                raise here.fail(str(key)[:60], f"unknown key (a catalog entry has {', '.join(expected)})")
            if value != expected[key]:
                raise here.fail(key, f"{shown(value)} differs from the planner's catalog ({where}: object {oid} has "
                                     f"{shown(expected[key])}); the planner plans with the catalog its method was "
                                     "trained and evaluated on")
    missing = set(mine) - given
    if missing:
        raise at.fail(None, f"objects {_fmt_ids(missing)} of the planner's catalog ({where}) are missing; send the "
                            "catalog whole or leave the key out")


def _same_table(a: Table, b: Table) -> bool:
    return (a.width, a.height, tuple(a.surface)) == (b.width, b.height, tuple(b.surface))


def _add_tables(tables: dict[int, Table], new: dict[int, Table], where: str, at: At) -> None:
    for tid, table in new.items():
        if tid in tables and not _same_table(tables[tid], table):
            known = tables[tid].name or "unnamed"
            raise at.fail(None, f"table {tid} ({where}) is not the planner's table {tid} ({known}): another size or "
                                "surface under the same id; give it another id")
        tables.setdefault(tid, table)


def _table(value: NewTable, tid: int, root, at: At) -> Table:
    image = None
    if value.image is not None:
        if root is None:
            raise at.fail("image", "the planner's dataset is not a folder, so a table picture cannot be read")
        image = check_picture(root, value.image, "image", at)
    return Table(tid, value.width, value.height, value.surface, name=value.name, image=image)


def prepare(req: PlanRequest, ref: Dataset, where: str,
            history_dataset: Callable[[str], Dataset] | None = None) -> Prepared:
    """The planning dataset and episode of `req` on the planner's dataset `ref` (named `where` in messages).

    `history_dataset(path)` loads the dataset a request's `dataset` names; None refuses such requests (a server
    reads no folder a client names)."""
    at = At()
    catalog = ref.catalog
    if req.catalog is not None:
        check_catalog(req.catalog, catalog, f"{where}/catalog.json")
    tables = dict(ref.tables)
    for i, entry in enumerate(req.tables):
        here = at / "tables" / i
        value = new_table(entry, here)
        if value.id is None:
            raise here.fail("id", "missing: a table the history refers to needs its id")
        _add_tables(tables, {value.id: _table(value, value.id, ref.root, here)}, "request.tables", here / "id")

    person = req.participant or DEFAULT_PERSON
    if req.arrangements is not None:
        context = list(req.arrangements)
        for i, arr in enumerate(context):
            here = at / "arrangements" / i
            if arr.table not in tables:
                raise here.fail("table", f"unknown table id {arr.table} (known: {_fmt_ids(tables)}; add it to "
                                         "`tables`)")
            for j, p in enumerate(arr.placements):
                if p.object not in catalog:
                    raise (here / "placements" / j).fail("object", f"unknown object id {p.object} (not in the "
                                                                   f"planner's catalog, {where}/catalog.json)")
    elif req.participant is not None:
        context = _from_dataset(req, ref, where, history_dataset, tables)
    else:
        context = []

    if isinstance(req.table, int):
        if req.table not in tables:
            raise at.fail("table", f"unknown table id {req.table} (known: {_fmt_ids(tables)}; or give a new table "
                                   "by width, height and surface)")
        table = tables[req.table]
    else:
        tid = req.table.id if req.table.id is not None else max(tables, default=-1) + 1
        if tid in tables:
            raise (at / "table").fail("id", f"table {tid} is a known table; leave `id` out for a new one, or give "
                                            "only the id to set the known one")
        table = _table(req.table, tid, ref.root, at / "table")
        tables[tid] = table

    on_hand = tuple(catalog.ids)
    if req.objects is not None:
        for i, oid in enumerate(req.objects):
            if oid not in catalog:
                raise (at / "objects").fail(i, f"unknown object id {oid} (not in the planner's catalog, "
                                               f"{where}/catalog.json)")
        chosen = set(req.objects)
        on_hand = tuple(o for o in catalog.ids if o in chosen)

    trial = max((a.trial for a in context), default=-1) + 1
    target = Arrangement(person, trial, table.id, ())
    rest = [a for a in ref.arrangements if a.participant != person]
    ds = PlanningDataset(catalog, tables, rest + context, None, dict(ref.meta), ref.root, target=target)
    task = "reconstruction" if any(a.table == table.id for a in context) else "generalization"
    episode = Episode(f"{person}/plan/k{len(context)}", person, tuple(a.trial for a in context), trial, task)
    return Prepared(ds, episode, table, on_hand, req.metres, req.n_objects)


def _from_dataset(req: PlanRequest, ref: Dataset, where: str, history_dataset, tables: dict[int, Table]) -> list:
    """The context of a request naming a participant: their trials (`trials`, default all) in a dataset."""
    at = At()
    source, name = ref, where
    if req.dataset is not None:
        if history_dataset is None:
            raise at.fail("dataset", "this planner reads arrangements only from its own dataset (a server opens no "
                                     "folder a request names); leave the key out, or send the arrangements inline")
        source, name = history_dataset(req.dataset), req.dataset
        if [o.to_json(with_image=False) for o in source.catalog] != [o.to_json(with_image=False) for o in ref.catalog]:
            raise at.fail("dataset", f"{name} has another catalog than the planner's ({where}); the planner plans with "
                                     "the catalog its method was trained and evaluated on")
        _add_tables(tables, dict(source.tables), f"{name}/tables.json", at / "dataset")
    by_trial = {a.trial: a for a in source.trials_of(req.participant)}
    if not by_trial:
        raise at.fail("participant", f"no participant {shown(req.participant)} in {name} (send their arrangements "
                                     "inline as `arrangements`)")
    if req.trials is None:
        if len(by_trial) > MAX_CONTEXT:
            raise at.fail("participant", f"{req.participant!r} has {len(by_trial)} arrangements in {name}, over the "
                                         f"limit of {MAX_CONTEXT}; choose some with `trials`")
        return [by_trial[t] for t in sorted(by_trial)]
    for i, t in enumerate(req.trials):
        if t not in by_trial:
            raise (at / "trials").fail(i, f"participant {req.participant!r} has no trial {t} in {name} (their "
                                          f"trials: {_fmt_ids(by_trial)})")
    return [by_trial[t] for t in req.trials]


__all__ = ["PlanningDataset", "Prepared", "check_catalog", "prepare"]
