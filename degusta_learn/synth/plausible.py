"""Plausible tables: the rules a set table keeps, checks for arrangements and styles, and plausible type draws.

A table is judged from its object types alone. With D = max(1, number of plates), the diners it is set for:

- `plates`: at most `MAX_PLATES` (4) plates, the most place settings any style sets;
- `cups`, `knives`: at most D of each (one per diner);
- `forks`, `spoons`: at most 2 D of each (a salad fork or a dessert spoon beside each diner's own);
- `utensils`: at least one utensil (fork, knife or spoon) per plate.

So "five plates and a knife" breaks `plates` and `utensils`, and three cups beside one plate breaks `cups`.
The naturalistic generator's legacy tables (`degusta data generate naturalistic --legacy`) draw the types of its
`row` and `freeform` templates independently from `templates.TYPE_PRIOR`, which breaks these rules on about a
fifth of them; its default tables draw those types from the same prior *conditioned on the rules* (rejection
sampling), plates and one utensil per plate are always set, and every other template is
unchanged (its place settings already keep the rules). `style_violations` is the guarantee that makes every
trial of a style plausible: the rules hold for all of its slots, its plates are always set (so D cannot
change between trials) and its always-set slots hold a utensil per plate. See docs/data.md, "Plausible tables".

Usage:
    from degusta_learn.synth.plausible import violations, dataset_violations
    violations(["plate"] * 5 + ["knife"])        # ('plates', 'utensils')
    dataset_violations(load_dataset("data/naturalistic"))   # {rule: (tables, participants)}
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np

from degusta_learn.scene import Dataset

MAX_PLATES = 4
UTENSILS = ("fork", "knife", "spoon")
RULES = ("plates", "cups", "knives", "forks", "spoons", "utensils")
"""Every rule's name, in the order `violations` reports them."""
MAX_DRAWS = 1000
"""Rejection-sampling draws of `plausible_types` before it settles for one object fewer."""


def violations(types: Sequence[str]) -> tuple[str, ...]:
    """The rules (names from `RULES`) that a table with objects of these `types` breaks; () when plausible."""
    n = Counter(types)
    plates = n["plate"]
    diners = max(1, plates)
    caps = {"plates": (plates, MAX_PLATES), "cups": (n["cup"], diners), "knives": (n["knife"], diners),
            "forks": (n["fork"], 2 * diners), "spoons": (n["spoon"], 2 * diners)}
    broken = [rule for rule, (count, cap) in caps.items() if count > cap]
    if sum(n[u] for u in UTENSILS) < plates:
        broken.append("utensils")
    return tuple(broken)


def core_mask(types: Sequence[str], n_core: int = 3) -> list[bool]:
    """Which slots a plausible style always sets: the first `n_core`, every plate, and the first utensils up to
    one per plate (so the always-set slots keep the `utensils` rule whenever all the slots do)."""
    core = [i < n_core or t == "plate" for i, t in enumerate(types)]
    need = sum(t == "plate" for t in types) - sum(c and t in UTENSILS for c, t in zip(core, types))
    for i, t in enumerate(types):
        if need <= 0:
            break
        if t in UTENSILS and not core[i]:
            core[i], need = True, need - 1
    return core


def plausible_types(rng: np.random.Generator, n: int, draw: Callable[[np.random.Generator], str]) -> list[str]:
    """`n` types, each from `draw(rng)`, conditioned on `violations(...) == ()` (rejection sampling; after
    `MAX_DRAWS` failed draws of `n`, draws of `n - 1`, down to one plate, fork and cup)."""
    for size in range(n, 2, -1):
        for _ in range(MAX_DRAWS):
            types = [draw(rng) for _ in range(size)]
            if not violations(types):
                return types
    return ["plate", "fork", "cup"]


def style_violations(style) -> tuple[str, ...]:
    """Why some trial of `style` (a `synth.Style`) could be implausible; () when every trial is plausible.

    Reported: the rules its full slot set breaks, `plates` when a plate is not always set (`p_include` < 1, so
    the number of diners could change between trials) and `utensils` when the always-set slots hold fewer
    utensils than plates. Trials always hold the always-set slots and never more than all of them.
    """
    types = [s.type for s in style.slots]
    broken = list(violations(types))
    if any(s.type == "plate" and s.p_include < 1.0 for s in style.slots) and "plates" not in broken:
        broken.append("plates")
    core = [s.type for s in style.slots if s.p_include >= 1.0]
    if "utensils" in violations(core) and "utensils" not in broken:
        broken.append("utensils")
    return tuple(r for r in RULES if r in broken)


def dataset_violations(ds: Dataset) -> dict[str, tuple[int, int]]:
    """Per rule of `RULES`: (tables that break it, participants with at least one such table); and under "any",
    the tables and participants that break at least one rule."""
    tables: Counter = Counter()
    people: dict[str, set] = {rule: set() for rule in (*RULES, "any")}
    for a in ds.arrangements:
        broken = violations([ds.catalog[o].type for o in a.objects])
        for rule in (*broken, "any") if broken else ():
            tables[rule] += 1
            people[rule].add(a.participant)
    return {rule: (tables[rule], len(people[rule])) for rule in (*RULES, "any")}
