"""Episodes and participant splits.

Splits are by participant: the sorted participant ids are shuffled with a seeded RNG and cut into
train / val / test by `SPLIT_FRACTIONS` (70 / 10 / 20), so no participant appears in two splits and the
split of a participant depends only on the seed and the set of participants.

An episode takes one of a participant's trials as the target and `k` (0, 2 or 4) of their other trials
as context, chosen deterministically from (seed, participant, target). Every trial of every participant
in the split becomes a target once, so a split of P participants with 5 trials each gives 5P episodes.
`task` is "reconstruction" when some context trial was set on the target's table, else "generalization".
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from degusta_learn.config import check_seed
from degusta_learn.errors import DegustaError
from degusta_learn.files.guard import check_output_file
from degusta_learn.files.jsonio import atomic_write_jsonl, read_jsonl
from degusta_learn.names import SPLITS
from degusta_learn.scene.dataset import Dataset
from degusta_learn.scene.types import TASKS, Episode
from degusta_learn.scene.validate import MAX_TRIAL, Where, get, require_mapping

SPLIT_FRACTIONS = {"train": 0.7, "val": 0.1, "test": 0.2}


def split_participants(participants: list[str], seed: int = 0) -> dict[str, list[str]]:
    """Deterministic train/val/test split of participant ids (each split sorted)."""
    seed = check_seed(seed)
    ids = sorted(set(participants))
    if len(ids) < 3:
        raise DegustaError(f"need at least 3 participants to split into train/val/test, got {len(ids)}")
    order = np.random.default_rng(seed).permutation(len(ids))
    n_test = max(1, round(SPLIT_FRACTIONS["test"] * len(ids)))
    n_val = max(1, round(SPLIT_FRACTIONS["val"] * len(ids)))
    test = sorted(ids[i] for i in order[:n_test])
    val = sorted(ids[i] for i in order[n_test:n_test + n_val])
    train = sorted(ids[i] for i in order[n_test + n_val:])
    return {"train": train, "val": val, "test": test}


def participants_in(ds: Dataset, split: str, seed: int = 0) -> list[str]:
    if split not in SPLITS:
        raise DegustaError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    if split == "all":
        return ds.participants
    return split_participants(ds.participants, seed)[split]


def _stable_seed(*parts) -> int:
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little")


def make_episodes(ds: Dataset, context: int, split: str = "test", seed: int = 0) -> list[Episode]:
    """Episodes of context length `context` for every target trial of every participant in `split`."""
    seed = check_seed(seed)
    if isinstance(context, bool) or not isinstance(context, int) or context < 0:
        raise DegustaError(f"context length must be an integer >= 0, got {context!r}")
    episodes = []
    by_p = ds.by_participant()
    for participant in participants_in(ds, split, seed):
        trials = by_p[participant]
        if len(trials) <= context:
            raise DegustaError(f"participant {participant!r} has {len(trials)} trials: too few for "
                               f"context length {context} plus a target")
        for target in trials:
            others = [a for a in trials if a.trial != target.trial]
            rng = np.random.default_rng(_stable_seed(seed, participant, target.trial, context))
            chosen = sorted(rng.choice(len(others), size=context, replace=False).tolist()) if context else []
            ctx = [others[i] for i in chosen]
            task = "reconstruction" if any(a.table == target.table for a in ctx) else "generalization"
            episodes.append(Episode(id=f"{participant}/t{target.trial}/k{context}", participant=participant,
                                    context=tuple(a.trial for a in ctx), target=target.trial, task=task))
    return episodes


def write_episodes(path: str | Path, episodes: list[Episode], inputs=(), datasets=()) -> None:
    """Write episodes.jsonl atomically; never over one of `inputs` ((what, path) pairs) or a dataset's files
    (a dataset folder enclosing `path` counts even when not named in `datasets`)."""
    check_output_file(path, inputs, key="--out", datasets=datasets)
    atomic_write_jsonl(path, (e.to_json() for e in episodes))


def read_episodes(path: str | Path, ds: Dataset | None = None) -> list[Episode]:
    """Read episodes.jsonl; with `ds`, check that every participant and trial exists."""
    out, seen = [], set()
    for lineno, entry in read_jsonl(path):
        w = Where(path, line=lineno)
        require_mapping(entry, w)
        eid = get(entry, "id", "str", w)
        if eid in seen:
            raise w.fail("id", f"duplicate episode id {eid!r}")
        seen.add(eid)
        participant = get(entry, "participant", "id", w)
        context = get(entry, "context", "list", w)
        for c in context:
            if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c <= MAX_TRIAL:
                raise w.fail("context", f"expected a list of trial numbers (0..{MAX_TRIAL}), got {context!r}"[:300])
        if len(set(context)) != len(context):
            raise w.fail("context", f"a trial appears twice in {context!r}"[:300])
        named = re.search(r"/k(\d+)$", eid)  # the ids make_episodes writes end in the context length
        if named and int(named.group(1)) != len(context):
            raise w.fail("context", f"{len(context)} trials, but the id {eid!r} says context length {named.group(1)}")
        target = get(entry, "target", "int", w, lo=0, hi=MAX_TRIAL)
        if target in context:
            raise w.fail("context", f"the target trial {target} is also in the context")
        task = get(entry, "task", "str", w, optional=True, default="generalization")
        if task not in TASKS:
            raise w.fail("task", f"expected one of {list(TASKS)}, got {task!r}")
        if ds is not None:
            for trial in [*context, target]:
                if (participant, trial) not in ds._by_key:
                    raise w.fail("target" if trial == target else "context",
                                 f"participant {participant!r} has no trial {trial} in the dataset")
        out.append(Episode(eid, participant, tuple(context), target, task))
    if not out:
        raise DegustaError(f"{path}: no episodes")
    return out
