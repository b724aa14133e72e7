"""The latent style of a synthetic participant (SYNTHETIC data), and its JSON file.

A style says everything that decides how one synthetic person sets a table:

- **where**: one or more place settings, each with an anchor `(u, v)` relative to the table surface's
  bounding box (0 = left/top edge, 1 = right/bottom edge) and a `facing` (degrees: 0 = the diner sits at
  the bottom edge of the image, 90 = at the left edge, 180 = at the top, 270 = at the right);
- **what and how**: `slots`, in the person's placement order, each an object type at an offset
  `(dx, dy)` from its setting's anchor in the setting's frame (normalized table units, the same physical
  units as `scene.object_size`, so a layout keeps its physical size on a bigger table), a rotation in the
  setting's frame, a probability `p_include` of being set in a given trial, and the person's favourite
  object for the slot;
- **object taste**: favourite `colors` and `materials`, how `strictly` they keep to them, and how `loyal`
  they are to their favourite objects (the probability a slot gets its favourite in a trial);
- **spacing**: `scale` multiplies every offset;
- **noise** (`Noise`): per-trial anchor shift, whole-layout turn, spacing change, per-object position and
  rotation noise, placement-order swaps;
- **rating** behaviour for the simulated jitter study (`rating_base`, `rating_sensitivity`).

The file `latent_styles.json` in a generated dataset folder is a JSON list of `Style.to_json()` dicts,
so the oracle works from the folder alone. See docs/data.md for every parameter's range.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_json, read_json

STYLES_FILE = "latent_styles.json"


@dataclass
class Setting:
    """One place setting: anchor relative to the surface bounds and the side the diner sits on."""

    u: float
    """Anchor x as a fraction of the surface's bounding-box width (0 = left edge)."""
    v: float
    """Anchor y as a fraction of the surface's bounding-box height (0 = top edge)."""
    facing: float = 0.0
    """Degrees clockwise: 0 = diner at the bottom edge (utensils point north), 180 = diner at the top."""


@dataclass
class Slot:
    """One object the person puts down: type, offset from its setting's anchor, rotation, favourite."""

    type: str
    dx: float
    """Offset right of the anchor in the setting frame (normalized table units, before `scale`)."""
    dy: float
    """Offset below the anchor in the setting frame (normalized table units, before `scale`)."""
    rotation: float
    """Object rotation in the setting frame (degrees clockwise; 0 = long axis to the far side)."""
    object: int
    """The person's favourite catalog object for this slot."""
    setting: int = 0
    p_include: float = 1.0
    """Probability the slot is set in a trial (1 = always; the oracle sets slots with p >= 0.5)."""


@dataclass
class Noise:
    """How one person's trials differ from their expected arrangement."""

    position: float = 0.01
    """Std of each object's position (normalized units)."""
    rotation: float = 5.0
    """Std of each object's rotation (degrees)."""
    anchor: float = 0.03
    """Std of the per-trial anchor shift, as a fraction of the surface bounds."""
    turn: float = 3.0
    """Std of the per-trial rotation of the whole layout about its anchor (degrees)."""
    scale: float = 0.04
    """Std of the per-trial log spacing factor."""
    order: float = 0.1
    """Probability of each adjacent swap in the placement order."""


@dataclass
class Style:
    """A synthetic participant's latent preferences (see the module docstring)."""

    participant: str
    template: str
    settings: list[Setting]
    slots: list[Slot]
    colors: list[str] = field(default_factory=list)
    materials: list[str] = field(default_factory=list)
    strictness: float = 2.0
    """How strongly non-favourite picks follow the favourite colours/materials (0 = not at all)."""
    loyalty: float = 0.8
    """Probability that a slot gets its favourite object in a trial."""
    scale: float = 1.0
    noise: Noise = field(default_factory=Noise)
    rating_base: float = 85.0
    """Mean rating (0..100) the person gives their own arrangement."""
    rating_sensitivity: float = 5.0
    """Rating drop (fraction of 100) per unit of jitter RMSD."""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> Style:
        d = dict(d)
        d["settings"] = [Setting(**s) for s in d["settings"]]
        d["slots"] = [Slot(**s) for s in d["slots"]]
        d["noise"] = Noise(**d.get("noise", {}))
        return cls(**d)


def write_styles(path: str | Path, styles: list[Style]) -> None:
    """Write styles as one JSON list (atomically)."""
    atomic_write_json(path, [s.to_json() for s in styles])


# Bounds a style's numbers must keep (docs/data.md draws them well inside): beyond them the oracle's layout
# leaves the table or overflows, so a hand-edited file is refused when read, naming the field.
_RANGES = {"u": (-1.0, 2.0), "v": (-1.0, 2.0), "facing": (-3600.0, 3600.0), "dx": (-2.0, 2.0), "dy": (-2.0, 2.0),
           "rotation": (-3600.0, 3600.0), "p_include": (0.0, 1.0), "loyalty": (0.0, 1.0), "strictness": (0.0, 100.0),
           "scale": (0.01, 10.0), "position": (0.0, 1.0), "anchor": (0.0, 1.0), "turn": (0.0, 360.0),
           "order": (0.0, 1.0), "rating_base": (0.0, 100.0), "rating_sensitivity": (0.0, 1000.0)}
_NOISE_RANGES = {"rotation": (0.0, 360.0), "scale": (0.0, 2.0)}


def _number(value, field: str, ranges: dict) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"field {field!r}: expected a finite number, got {value!r}")
    lo, hi = ranges.get(field.rsplit(".", 1)[-1], (-math.inf, math.inf))
    if not lo <= value <= hi:
        raise ValueError(f"field {field!r}: {value!r} is outside [{lo:g}, {hi:g}]")


def check_fields(cls, d, where: str, ranges: dict = _RANGES, min_int: int = 0) -> dict:
    """`d` checked against dataclass `cls`: an object, no unknown or missing keys, numbers finite and in `ranges`
    (by field name), integers >= `min_int` (ValueError naming the field, `where` its prefix). Both generators'
    latent styles are checked with it."""
    if not isinstance(d, dict):
        what = f"field {where.rstrip('.')!r}" if where else "the style"
        raise ValueError(f"{what}: expected an object, got {type(d).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ValueError(f"unknown field {where}{unknown[0]!r} (known: {', '.join(fields)})")
    for name, f in fields.items():
        if name not in d:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"missing field {where}{name!r}")
            continue
        value, kind = d[name], str(f.type)
        if kind == "float":
            _number(value, f"{where}{name}", ranges)
        elif kind == "int" and (isinstance(value, bool) or not isinstance(value, int) or value < min_int):
            raise ValueError(f"field {where}{name!r}: expected an integer >= {min_int}, got {value!r}")
        elif kind == "str" and not (isinstance(value, str) and value.strip()):
            raise ValueError(f"field {where}{name!r}: expected a non-empty string, got {value!r}")
        elif kind == "list[str]" and not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise ValueError(f"field {where}{name!r}: expected a list of strings")
    return d


def _check_style(d) -> None:
    check_fields(Style, d, "")
    for key in ("settings", "slots"):
        if not isinstance(d[key], list) or not d[key]:
            raise ValueError(f"field {key!r}: expected a non-empty list")
    for i, s in enumerate(d["settings"]):
        check_fields(Setting, s, f"settings[{i}].")
    for i, s in enumerate(d["slots"]):
        check_fields(Slot, s, f"slots[{i}].")
        if s.get("setting", 0) >= len(d["settings"]):
            raise ValueError(f"field 'slots[{i}].setting': {s['setting']} is not a setting index "
                             f"(the style has {len(d['settings'])})")
    if "noise" in d:
        check_fields(Noise, d["noise"], "noise.", {**_RANGES, **_NOISE_RANGES})


def read_styles(path: str | Path) -> dict[str, Style]:
    """Read a latent styles file -> {participant: Style}; a malformed entry names the file, entry and field."""
    data = read_json(path)
    if not isinstance(data, list):
        raise DegustaError(f"{path}: expected a JSON list of latent styles")
    out = {}
    for i, entry in enumerate(data):
        try:
            _check_style(entry)
            style = Style.from_json(entry)
        except (ValueError, TypeError, KeyError, AttributeError) as e:
            raise DegustaError(f"{path}: entry {i}: not a latent style: {e}") from None
        if style.participant in out:
            raise DegustaError(f"{path}: entry {i}: participant {style.participant!r} has a latent style already")
        out[style.participant] = style
    return out
