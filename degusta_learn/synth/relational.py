"""The `relational` generator: SYNTHETIC participants whose tables come from placement rules, not slots.

The naturalistic generator and the learned slot model share one idea: a person is a list of slots at fixed
offsets from an anchor. A method ranking measured only on that data could be an artefact of the shared idea.
Here a person is a graph of rules relative to the table edge they sit at and to objects already placed
(relational_style.py; the draws: relational_habits.py; trials: relational_realize.py), so where an object lands
depends on its neighbours' sizes, rotations and realized positions, and noise travels along the rule chain.
Tables are plausible by construction (plausible.py's rules; every footprint on the surface).

Every participant `p000` ... sets the five default tables once each in a personal random order (trials 0-4) and
rates one jittered copy of each arrangement (ratings.py), like the naturalistic default and at its size. Each
participant is drawn from its own seed stream, so participant `i` is the same whatever the number of participants.

Options (`RelationalOptions`; `degusta data generate relational --set KEY=VALUE`): `participants`, `noise`,
`multi`. One that cannot make valid data is refused naming the key.

Usage:
    degusta data generate relational --out data/relational
    degusta data generate relational --out data/relational_noisy --set noise=2 --set participants=400

    from degusta_learn.synth.relational import relational_with_styles
    ds, styles = relational_with_styles(seed=0)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from degusta_learn.config import check_seed
from degusta_learn.config.fields import bounded
from degusta_learn.config.loading import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.scene import Arrangement, Dataset, default_catalog, default_tables
from degusta_learn.scene.dataset import validate_dataset
from degusta_learn.synth.ratings import simulate_rating
from degusta_learn.synth.relational_habits import sample_relational_style
from degusta_learn.synth.relational_realize import MIN_OBJECTS, sample_relational, taste_weights
from degusta_learn.synth.relational_style import RelationalStyle

GENERATOR = "degusta_learn.synth.relational"
"""meta.json "generator" of a relational dataset (the oracle dispatches on it)."""
SALT = 0x72656C61  # "rela": the relational streams differ from the naturalistic ones for the same seed
DESCRIPTION = ("SYNTHETIC second generator family: {n} simulated participants x 5 arrangements on 5 tables, each "
               "participant a graph of placement rules relative to the table edge they sit at and to objects "
               "already placed (no slots), with colour/material taste, person-specific noise along the rule "
               "chain and simulated jitter-study ratings. Not human data.")


@dataclass
class RelationalOptions:
    """Options of the relational generator (`--set KEY=VALUE`)."""

    participants: int = bounded(199, 3, 20000)
    """Synthetic participants (at least 3: the train/val/test split needs one in each; 199 take ~3 s)."""
    noise: float = bounded(1.0, 0.0, 5.0)
    """Multiplies every noise of every person (0: each person repeats their expected table). At most 5: beyond it a
    growing share of trials cannot stay on the surface with their noise and fall back to their noiseless layout (3%
    at 6, 6% at 10, against under 1% up to 3), so the option would no longer add the noise it says."""
    multi: float = bounded(0.2, 0.0, 1.0)
    """Share of participants who set the table for several diners."""


def relational_options(options: dict | RelationalOptions | None) -> RelationalOptions:
    """`options` checked (unknown keys, types, bounds: DegustaError naming the key)."""
    if isinstance(options, RelationalOptions):
        options = asdict(options)
    return from_dict(RelationalOptions, dict(options or {}), where="relational generator")


def relational_with_styles(seed: int = 0, options: dict | RelationalOptions | None = None
                           ) -> tuple[Dataset, list[RelationalStyle]]:
    """The relational dataset and the latent style of every participant (see the module docstring)."""
    seed = check_seed(seed)
    opts = relational_options(options)
    catalog = default_catalog()
    tables = {t.id: t for t in default_tables()}
    table_ids = sorted(tables)
    arrangements, ratings, styles = [], [], []
    for i in range(opts.participants):
        style_rng, trial_rng, rating_rng = (np.random.default_rng(s)
                                            for s in np.random.SeedSequence([seed, i, SALT]).spawn(3))
        pid = f"p{i:03d}"
        style = sample_relational_style(style_rng, pid, catalog, [tables[t] for t in table_ids], opts.multi,
                                        opts.noise)
        styles.append(style)
        weights = taste_weights(style, catalog)
        for trial, t_index in enumerate(trial_rng.permutation(len(table_ids))):
            table = tables[table_ids[int(t_index)]]
            placements = sample_relational(style, table, catalog, trial_rng, weights)
            arrangement = Arrangement(pid, trial, table.id, tuple(placements))
            arrangements.append(arrangement)
            ratings.append(simulate_rating(arrangement, style.rating_base, style.rating_sensitivity, rating_rng))
    meta = {"name": "relational", "synthetic": True, "generator": GENERATOR, "seed": seed,
            "description": DESCRIPTION.format(n=opts.participants), "min_objects": MIN_OBJECTS,
            "latent_styles": "latent_styles.json", "options": asdict(opts), "plausible": True}
    try:
        return validate_dataset(Dataset(catalog, tables, arrangements, ratings, meta)), styles
    except DegustaError as e:  # never expected: the generator keeps the validator's rules
        raise DegustaError(f"relational generator made invalid data (a bug): {e}") from None
