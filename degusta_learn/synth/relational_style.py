"""The latent style of a `relational` participant (SYNTHETIC data): placement rules, not slots, and its JSON file.

The naturalistic generator's person is a list of *slots*: each object at a fixed offset from an anchor that sits at
a fraction of the surface's bounding box. A relational person is a small graph of *rules*, each placing one object
relative to something already on the table:

- **seats** (`Seat`): where each diner sits: which table edge (`side`: `near` = the bottom edge of the image,
  `left`, `far`, `right`), how far along it (`along`, a fraction of the surface's half extent along that edge,
  + = the diner's right) and how far in their plate is set (`inset`: from the edge to the plate's near rim,
  normalized units). The edge is the surface polygon's own boundary, so a round table's edge curves away;
- **rules** (`Rule`), listed in the person's placement order, each placing a type with the person's favourite
  object of that type by one `relation`:
  - `edge`: the seat's plate, `inset` in from the edge (the anchor; `ref` is -1),
  - `centre`: a shared serving plate at the surface's centre (`ref` -1),
  - `beside`: next to object `ref`, their footprints `gap` apart along `direction`,
  - `tip`: beyond the far end of utensil `ref` (a cup above-right of the knife's tip),
  - `on`: on top of `ref`, its centre `gap` from ref's centre along `direction` (utensils laid on the plate),
  - `stack`: against `ref` like `beside` but overlapping (`gap` < 0): a clustered bundle of utensils;
  `direction` and `rotation` are degrees clockwise in the seat's frame (0 = away from the diner, 90 = to their
  right), `shift` moves the object sideways (perpendicular to `direction`, + = clockwise of it). So where an object
  lands depends on its neighbour's realized position, size and rotation, not on a fixed offset: the person's noise
  travels along the rule chain, and an angled fork sits further out than an upright one;
- **what** (`p_include`: the chance a rule is set in a trial; plates are always set), **taste** (favourite
  colours and materials, `strictness`, `loyalty`: as in the naturalistic generator, synth/taste.py), **noise**
  (`RelNoise`) and **rating** traits for the simulated jitter study (synth/ratings.py).

`latent_styles.json` of a relational dataset is a JSON list of `RelationalStyle.to_json()` dicts;
`read_relational_styles` checks every field when it reads one, so a hand-edited file is refused naming the entry
and field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_json, read_json
from degusta_learn.synth.style import check_fields

SIDES = {"near": 0.0, "left": 90.0, "far": 180.0, "right": 270.0}
"""A seat's edge -> the diner's facing (degrees clockwise; 0: sits at the bottom edge, utensils point north)."""
RELATIONS = ("edge", "centre", "beside", "tip", "on", "stack")
ROOTS = ("edge", "centre")
"""Relations to the table, not to another object: their rule has `ref` -1 and is a plate, always set."""
TYPES = ("plate", "cup", "fork", "knife", "spoon")


@dataclass
class Seat:
    """Where one diner sits: an edge of the table, a place along it, how far in their plate is set."""

    side: str
    """`near` (the bottom edge of the image), `left`, `far` or `right`."""
    along: float = 0.0
    """Place along the edge as a fraction of the surface's half extent along it (+ = the diner's right)."""
    inset: float = 0.05
    """From the edge to the plate's near rim, normalized units."""


@dataclass
class Rule:
    """One object the person puts down, relative to the seat's edge, the table centre or an earlier rule's object."""

    type: str
    object: int
    """The person's favourite catalog object for this rule."""
    relation: str
    """One of RELATIONS (module docstring)."""
    ref: int = -1
    """Index of the earlier rule whose object this one is placed against; -1 for `edge` and `centre`."""
    seat: int = 0
    """Whose frame the direction and rotation are in (a shared object uses seat 0's)."""
    direction: float = 0.0
    """Degrees clockwise in the seat's frame: 0 = away from the diner, 90 = their right, 270 = their left."""
    gap: float = 0.0
    """`beside`/`stack`/`tip`: clearance between footprints along `direction` (< 0 overlaps); `on`/`centre`: distance
    of the centre from ref's centre (the table's centre); `edge`: unused (the seat's inset)."""
    shift: float = 0.0
    """Sideways offset, perpendicular to `direction` (+ = clockwise of it), normalized units."""
    rotation: float = 0.0
    """Object rotation in the seat's frame (degrees clockwise; 0 = long axis away from the diner)."""
    p_include: float = 1.0
    """Probability the rule is set in a trial (the oracle sets rules with p >= 0.5)."""


@dataclass
class RelNoise:
    """How one person's trials differ from their expected arrangement."""

    position: float = 0.006
    """Std of each object's own position jitter, after its rule (normalized units)."""
    rotation: float = 4.0
    """Std of each object's rotation (degrees)."""
    direction: float = 4.0
    """Std of each rule's direction (degrees): moves the object around its reference."""
    gap: float = 0.008
    """Std of each rule's gap (normalized units)."""
    seat: float = 0.04
    """Std of a seat's place along its edge (fraction of the half extent) and of its inset (x 0.5, units)."""
    turn: float = 3.0
    """Std of a diner's facing (degrees): their whole setting turns with it."""
    order: float = 0.1
    """Probability of each adjacent swap in the placement order (never before an object's reference)."""


@dataclass
class RelationalStyle:
    """A relational participant's latent preferences (see the module docstring)."""

    participant: str
    habit: str
    """How their place setting is built (relational_habits.HABITS), for reports."""
    layout: str
    """How many diners and where (relational_habits.LAYOUTS), for reports."""
    seats: list[Seat]
    rules: list[Rule]
    colors: list[str] = field(default_factory=list)
    materials: list[str] = field(default_factory=list)
    strictness: float = 2.0
    """How strongly non-favourite picks follow the favourite colours/materials (0 = not at all)."""
    loyalty: float = 0.8
    """Probability that a rule gets its favourite object in a trial."""
    noise: RelNoise = field(default_factory=RelNoise)
    rating_base: float = 85.0
    rating_sensitivity: float = 5.0

    @property
    def template(self) -> str:
        """The oracle's diagnostics name a style by this (as the naturalistic Style's template)."""
        return f"{self.habit}/{self.layout}"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> RelationalStyle:
        d = dict(d)
        d["seats"] = [Seat(**s) for s in d["seats"]]
        d["rules"] = [Rule(**r) for r in d["rules"]]
        d["noise"] = RelNoise(**d.get("noise", {}))
        return cls(**d)


def write_relational_styles(path: str | Path, styles: list[RelationalStyle]) -> None:
    """Write styles as one JSON list (atomically)."""
    atomic_write_json(path, [s.to_json() for s in styles])


# Bounds a style's numbers keep (the sampler draws well inside them): beyond them the layout leaves the table.
_RANGES = {"along": (-1.0, 1.0), "inset": (-0.2, 0.5), "direction": (-3600.0, 3600.0), "gap": (-0.3, 0.5),
           "shift": (-0.3, 0.3), "rotation": (-3600.0, 3600.0), "p_include": (0.0, 1.0), "strictness": (0.0, 100.0),
           "loyalty": (0.0, 1.0), "rating_base": (0.0, 100.0), "rating_sensitivity": (0.0, 1000.0)}
_NOISE_RANGES = {"position": (0.0, 0.2), "rotation": (0.0, 360.0), "direction": (0.0, 180.0), "gap": (0.0, 0.2),
                 "seat": (0.0, 1.0), "turn": (0.0, 180.0), "order": (0.0, 1.0)}


def _check_fields(cls, d, where: str, ranges: dict = _RANGES) -> None:
    """`d` against dataclass `cls` (style.check_fields with this generator's bounds; a rule's `ref` may be -1)."""
    check_fields(cls, d, where, ranges, min_int=-1)


def check_relational_style(d) -> None:
    """Refuse (ValueError naming the field) a dict that is not a relational style whose rules can be laid out."""
    _check_fields(RelationalStyle, d, "")
    for key in ("seats", "rules"):
        if not isinstance(d[key], list) or not d[key]:
            raise ValueError(f"field {key!r}: expected a non-empty list")
    for i, s in enumerate(d["seats"]):
        _check_fields(Seat, s, f"seats[{i}].")
        if s["side"] not in SIDES:
            raise ValueError(f"field 'seats[{i}].side': {s['side']!r} is not one of {', '.join(SIDES)}")
    for i, r in enumerate(d["rules"]):
        where = f"rules[{i}]"
        _check_fields(Rule, r, f"{where}.")
        if r["type"] not in TYPES:
            raise ValueError(f"field '{where}.type': {r['type']!r} is not one of {', '.join(TYPES)}")
        if r["relation"] not in RELATIONS:
            raise ValueError(f"field '{where}.relation': {r['relation']!r} is not one of {', '.join(RELATIONS)}")
        ref, root = r.get("ref", -1), r["relation"] in ROOTS
        if root and (ref != -1 or r["type"] != "plate" or r.get("p_include", 1.0) < 1.0):
            raise ValueError(f"field '{where}.relation': {r['relation']!r} places an always-set plate with ref -1")
        if not root and not 0 <= ref < i:
            raise ValueError(f"field '{where}.ref': {ref} is not an earlier rule (rules are in placement order)")
        if not 0 <= r.get("seat", 0) < len(d["seats"]):
            raise ValueError(f"field '{where}.seat': {r['seat']} is not a seat index (the style has "
                             f"{len(d['seats'])})")
    if "noise" in d:
        _check_fields(RelNoise, d["noise"], "noise.", _NOISE_RANGES)


def read_relational_styles(path: str | Path) -> dict[str, RelationalStyle]:
    """Read a relational latent styles file -> {participant: style}; a malformed entry names file, entry and field."""
    data = read_json(path)
    if not isinstance(data, list):
        raise DegustaError(f"{path}: expected a JSON list of latent styles")
    out = {}
    for i, entry in enumerate(data):
        try:
            check_relational_style(entry)
            style = RelationalStyle.from_json(entry)
        except (ValueError, TypeError, KeyError, AttributeError) as e:
            raise DegustaError(f"{path}: entry {i}: not a relational latent style: {e}") from None
        if style.participant in out:
            raise DegustaError(f"{path}: entry {i}: participant {style.participant!r} has a latent style already")
        out[style.participant] = style
    return out
