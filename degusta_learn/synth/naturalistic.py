"""The `naturalistic` generator: a SYNTHETIC stand-in for the paper's 199 x 5 online-study arrangements.

Every participant `p000` ... `p198` gets a latent style (templates.py), sets the five default tables once
each in a personal random order (trials 0-4), and rates one jittered copy of each arrangement
(ratings.py). Participants are drawn independently from their own seed stream, so participant `i` is the
same whatever the number of participants.

Usage:
    from degusta_learn.synth import naturalistic
    ds = naturalistic(seed=0)                    # in memory
    degusta data generate naturalistic --out data/naturalistic   # on disk, with latent_styles.json
"""

from __future__ import annotations

import numpy as np

from degusta_learn.config import check_seed
from degusta_learn.scene import Arrangement, Dataset, default_catalog, default_tables
from degusta_learn.scene.dataset import validate_dataset
from degusta_learn.synth.ratings import simulate_rating
from degusta_learn.synth.realize import MIN_OBJECTS, sample_arrangement, taste_weights
from degusta_learn.synth.style import Style
from degusta_learn.synth.templates import sample_style

N_PARTICIPANTS = 199
DESCRIPTION = ("SYNTHETIC stand-in for the DegustaBot naturalistic study: 199 simulated participants x 5 "
               "arrangements on 5 tables, each participant drawn from a latent style (layout template, "
               "anchor, spacing, utensil angle, object taste, count, order, noise), plus simulated "
               "jitter-study ratings. Not human data.")


def naturalistic_with_styles(seed: int = 0, n_participants: int = N_PARTICIPANTS,
                             plausible: bool = True) -> tuple[Dataset, list[Style]]:
    """The naturalistic dataset and the latent style of every participant.

    `plausible` (the default): every table keeps the rules of plausible.py (meta.json says `"plausible": true`).
    Off: the legacy tables, exactly the files this generator wrote before it kept those rules, byte for byte
    (about a fifth of them break one; meta.json has no `plausible` key).
    """
    seed = check_seed(seed)  # 0..2**32-1: meta.json then holds a seed `data validate` accepts
    catalog = default_catalog()
    tables = {t.id: t for t in default_tables()}
    table_ids = sorted(tables)
    arrangements, ratings, styles = [], [], []
    for i in range(n_participants):
        style_rng, trial_rng, rating_rng = (np.random.default_rng(s)
                                            for s in np.random.SeedSequence([seed, i]).spawn(3))
        pid = f"p{i:03d}"
        style = sample_style(style_rng, pid, catalog, plausible=plausible)
        styles.append(style)
        weights = taste_weights(style, catalog)
        for trial, t_index in enumerate(trial_rng.permutation(len(table_ids))):
            table = tables[table_ids[int(t_index)]]
            placements = sample_arrangement(style, table, catalog, trial_rng, weights)
            arrangement = Arrangement(pid, trial, table.id, tuple(placements))
            arrangements.append(arrangement)
            ratings.append(simulate_rating(arrangement, style.rating_base, style.rating_sensitivity, rating_rng))
    meta = {"name": "naturalistic", "synthetic": True, "generator": "degusta_learn.synth.naturalistic",
            "seed": seed, "description": DESCRIPTION, "min_objects": MIN_OBJECTS,
            "latent_styles": "latent_styles.json"}
    if plausible:  # only when on: the legacy meta.json stays as it was
        meta["plausible"] = True
        meta["description"] = DESCRIPTION + " Every table keeps the plausibility rules (docs/data.md)."
    # The generator keeps the validator's rules: what it returns always loads (never written otherwise).
    return validate_dataset(Dataset(catalog, tables, arrangements, ratings, meta)), styles


def naturalistic(seed: int = 0, plausible: bool = True) -> Dataset:
    """The naturalistic dataset (SYNTHETIC) in memory; see the module docstring."""
    return naturalistic_with_styles(seed, plausible=plausible)[0]
