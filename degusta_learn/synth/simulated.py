"""The `simulated` generator: the paper's controlled benchmark made concrete (SYNTHETIC data).

The paper: "three positional preferences, three object preferences, and a single order preference ...
positional and rotational noise ... 18 preferences on two table tops for a total of 36 preferences ...
reconstruction ... and generalization ... for 72 total experiments". Our reading:

- **18 preferences** = 3 positional (`western`: plate, fork left, knife and spoon right, cup above right;
  `mirrored`: the same mirrored left-right; `abstract`: utensils fanned around the plate at 60-degree
  steps, cup on the left) x 3 object preferences (all `red`, all `blue`, all `yellow`: per type the first
  catalog object whose colours are that colour, the same objects in every trial) x 2 noise levels
  (`low`, `high`; see `NOISE`). One order preference: plate, fork, knife, spoon, cup. Each preference
  is one participant, `sim_<position>_<colour>_<noise>`.
- **two tables**: default tables 0 (`oak`, rectangular) and 1 (`marble`, round); each participant sets
  6 noisy arrangements on each (trials 0-5 on oak, 6-11 on marble), anchored near the near edge.
- **36 preferences** = 18 preferences x 2 tables: the 36 (participant, context table) pairs. The context
  of each is the first 4 trials on that table.
- **72 experiments** = 36 x {reconstruction (target: the 5th trial on the same table), generalization
  (target: the 6th trial on the other table)}; written to `episodes.jsonl` (context length 4), ids
  `<participant>/<context table>/<task>`.

Noise per trial (the paper's "positional and rotational noise" and "random transformations and
rotations"): per-object position and rotation noise, plus a whole-layout shift, turn and spacing change.

Usage:
    from degusta_learn.synth import simulated
    ds = simulated(seed=0)
    degusta data generate simulated --out data/simulated
"""

from __future__ import annotations

import numpy as np

from degusta_learn.config import check_seed
from degusta_learn.scene import Arrangement, Catalog, Dataset, Episode, default_catalog, default_tables
from degusta_learn.scene.dataset import validate_dataset
from degusta_learn.synth.realize import MIN_OBJECTS, sample_arrangement
from degusta_learn.synth.style import Noise, Setting, Slot, Style

POSITIONS = {  # (type, dx, dy, rotation) in placement order: plate, fork, knife, spoon, cup
    "western": [("plate", 0.0, 0.0, 0.0), ("fork", -0.13, 0.0, 0.0), ("knife", 0.13, 0.0, 0.0),
                ("spoon", 0.178, 0.0, 0.0), ("cup", 0.17, -0.16, 0.0)],
    "mirrored": [("plate", 0.0, 0.0, 0.0), ("fork", 0.13, 0.0, 0.0), ("knife", -0.13, 0.0, 0.0),
                 ("spoon", -0.178, 0.0, 0.0), ("cup", -0.17, -0.16, 0.0)],
    "abstract": [("plate", 0.0, 0.0, 0.0), ("fork", -0.02, -0.165, 300.0), ("knife", 0.165, -0.11, 60.0),
                 ("spoon", 0.16, 0.085, 120.0), ("cup", -0.17, 0.06, 0.0)],
}
COLORS = ("red", "blue", "yellow")
NOISE = {
    "low": Noise(position=0.01, rotation=5.0, anchor=0.03, turn=5.0, scale=0.03, order=0.0),
    "high": Noise(position=0.025, rotation=15.0, anchor=0.06, turn=12.0, scale=0.06, order=0.0),
}
TABLES = (0, 1)
TRIALS_PER_TABLE = 6
CONTEXT = 4
DESCRIPTION = ("SYNTHETIC controlled benchmark after the DegustaBot paper: 18 preferences (3 positional x 3 "
               "colour x 2 noise levels) x 2 tables, 6 noisy arrangements each; 72 experiments "
               "(36 preference-table contexts x reconstruction/generalization) in episodes.jsonl.")


def colour_objects(catalog: Catalog, colour: str) -> dict[str, int]:
    """Per type, the first object all in `colour` (else the first with `colour` as its main colour)."""
    out = {}
    for type_ in catalog.types:
        objs = catalog.of_type(type_)
        pure = [o for o in objs if o.colors == (colour,)] or [o for o in objs if o.color1 == colour]
        if pure:
            out[type_] = pure[0].id
    return out


def simulated_styles(catalog: Catalog) -> list[Style]:
    """The 18 preference styles (participants), in a fixed order."""
    styles = []
    for position, slots in POSITIONS.items():
        for colour in COLORS:
            objects = colour_objects(catalog, colour)
            for level, noise in NOISE.items():
                styles.append(Style(
                    participant=f"sim_{position}_{colour}_{level}", template=position,
                    settings=[Setting(0.5, 0.7, 0.0)],
                    slots=[Slot(t, dx, dy, rot, objects[t]) for t, dx, dy, rot in slots],
                    colors=[colour], materials=[], strictness=5.0, loyalty=1.0, scale=1.0, noise=noise))
    return styles


def simulated_episodes(styles: list[Style]) -> list[Episode]:
    """The 72 experiments: per participant and context table, reconstruction and generalization."""
    episodes = []
    names = {t.id: t.name for t in default_tables()}
    for style in styles:
        for a, table in enumerate(TABLES):
            other = 1 - a
            context = tuple(range(a * TRIALS_PER_TABLE, a * TRIALS_PER_TABLE + CONTEXT))
            targets = {"reconstruction": a * TRIALS_PER_TABLE + CONTEXT,
                       "generalization": other * TRIALS_PER_TABLE + CONTEXT + 1}
            for task, target in targets.items():
                episodes.append(Episode(f"{style.participant}/{names[table]}/{task}", style.participant,
                                        context, target, task))
    return episodes


def simulated_with_styles(seed: int = 0) -> tuple[Dataset, list[Style], list[Episode]]:
    """The simulated dataset, its 18 styles and its 72 episodes."""
    seed = check_seed(seed)  # 0..2**32-1: meta.json then holds a seed `data validate` accepts
    catalog = default_catalog()
    tables = {t.id: t for t in default_tables() if t.id in TABLES}
    styles = simulated_styles(catalog)
    arrangements = []
    for i, style in enumerate(styles):
        rng = np.random.default_rng(np.random.SeedSequence([seed, i]))
        for a, table_id in enumerate(TABLES):
            for k in range(TRIALS_PER_TABLE):
                placements = sample_arrangement(style, tables[table_id], catalog, rng)
                arrangements.append(Arrangement(style.participant, a * TRIALS_PER_TABLE + k, table_id,
                                                tuple(placements)))
    meta = {"name": "simulated", "synthetic": True, "generator": "degusta_learn.synth.simulated", "seed": seed,
            "description": DESCRIPTION, "min_objects": MIN_OBJECTS, "latent_styles": "latent_styles.json",
            "episodes": "episodes.jsonl"}
    # The generator keeps the validator's rules: what it returns always loads (never written otherwise).
    ds = validate_dataset(Dataset(catalog, tables, arrangements, None, meta))
    return ds, styles, simulated_episodes(styles)


def simulated(seed: int = 0) -> Dataset:
    """The simulated dataset (SYNTHETIC) in memory; its 72 episodes: `simulated_episodes`."""
    return simulated_with_styles(seed)[0]
