"""The plan: ordered steps (which object, where, how rotated), the table they are on, what made them and what happened.

Positions are the table image's normalized frame (origin top-left, x right, y down, both in [0, 1], at the object's
centroid) and, when the request gave the table's size in metres, the same point in metres from that corner
(`x_m = x * width_m`, `y_m = y * height_m`). Rotations are degrees clockwise from image north, in [0, 360).
`Plan.to_json` writes the documented form (docs/planner.md, "The plan"); `Plan.from_json` reads it back and checks
it, naming the field path (``plan.steps[2].rotation: ...``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from degusta_learn.planner.request import At, shown
from degusta_learn.scene import Placement, Table
from degusta_learn.scene.types import normalized_rotation
from degusta_learn.scene.validate import MAX_ID, get

PLAN_FORMAT = "degusta plan"
PLAN_VERSION = 1



@dataclass(frozen=True)
class PlanStep:
    """One step: put `object` (of `type`) at (x, y), rotated `rotation` degrees clockwise from image north."""

    step: int
    object: int
    type: str
    x: float
    y: float
    rotation: float
    x_m: float | None = None
    y_m: float | None = None

    @property
    def placement(self) -> Placement:
        return Placement(self.object, self.x, self.y, self.rotation)

    def to_json(self) -> dict:
        return {"step": self.step, "object": self.object, "type": self.type, "x": self.x, "y": self.y,
                "rotation": self.rotation, "x_m": self.x_m, "y_m": self.y_m}


@dataclass(frozen=True)
class PlanTable:
    """The table the plan is for: id, image size in pixels, surface polygon (normalized) and size in metres."""

    id: int
    width: int
    height: int
    surface: tuple[tuple[float, float], ...]
    name: str = ""
    metres: tuple[float, float] | None = None

    @classmethod
    def of(cls, table: Table, metres: tuple[float, float] | None) -> PlanTable:
        return cls(table.id, table.width, table.height, tuple(table.surface), table.name, metres)

    @property
    def table(self) -> Table:
        return Table(self.id, self.width, self.height, self.surface, self.name)

    def to_json(self) -> dict:
        return {"id": self.id, "name": self.name, "width": self.width, "height": self.height,
                "surface": [list(p) for p in self.surface], "metres": list(self.metres) if self.metres else None}


@dataclass(frozen=True)
class Plan:
    """A plan for one request (docs/planner.md, "The plan")."""

    steps: tuple[PlanStep, ...]
    table: PlanTable
    method: str
    """The method that planned (the config's `method`)."""
    config_sha256: str
    """The fingerprint of the resolved config, as `degusta predict` records it (`choices.config_sha256`)."""
    failed: bool = False
    """The method reported a failure (e.g. no answer of a VLM parsed): the steps are what it could give, maybe none."""
    diagnostics: dict[str, Any] = field(default_factory=dict)
    """context, failures, cost_usd, replaced, dropped, clamped, cut, method (docs/planner.md)."""

    @property
    def placements(self) -> list[Placement]:
        return [s.placement for s in self.steps]

    def to_json(self) -> dict:
        return {"format": PLAN_FORMAT, "version": PLAN_VERSION, "method": self.method,
                "config_sha256": self.config_sha256, "table": self.table.to_json(),
                "steps": [s.to_json() for s in self.steps], "failed": self.failed, "diagnostics": self.diagnostics}

    @classmethod
    def from_json(cls, obj: Any) -> Plan:
        """The plan a JSON object holds; anything else raises DegustaError naming the field path."""
        at = At("plan")
        if not isinstance(obj, dict):
            raise at.fail(None, f"expected a JSON object, got {type(obj).__name__}")
        if obj.get("format") != PLAN_FORMAT:
            raise at.fail("format", f"expected {PLAN_FORMAT!r}, got {shown(obj.get('format'))}")
        if obj.get("version") != PLAN_VERSION:
            raise at.fail("version", f"this version reads plans of version {PLAN_VERSION}, got {shown(obj.get('version'))}")
        method = get(obj, "method", "str", at)
        sha = get(obj, "config_sha256", "str", at)
        t = obj.get("table")
        if not isinstance(t, dict):
            raise at.fail("table", f"expected a JSON object, got {shown(t)}")
        tat = at / "table"
        surface = get(t, "surface", "list", tat)
        for j, pt in enumerate(surface):
            if not (isinstance(pt, list) and len(pt) == 2 and all(_finite(v) and 0 <= v <= 1 for v in pt)):
                raise (tat / "surface").fail(j, f"expected [x, y] with both in [0, 1], got {shown(pt)}")
        metres = t.get("metres")
        if metres is not None and not (isinstance(metres, list) and len(metres) == 2
                                       and all(_finite(v) and v > 0 for v in metres)):
            raise tat.fail("metres", f"expected null or [width, height] in metres, got {shown(metres)}")
        table = PlanTable(get(t, "id", "int", tat, lo=0, hi=MAX_ID), get(t, "width", "int", tat, lo=1),
                          get(t, "height", "int", tat, lo=1), tuple((float(x), float(y)) for x, y in surface),
                          get(t, "name", "str", tat, optional=True, default="") if t.get("name") else "",
                          tuple(map(float, metres)) if metres else None)
        steps = []
        for i, s in enumerate(get(obj, "steps", "list", at)):
            sat = at / "steps" / i
            if not isinstance(s, dict):
                raise sat.fail(None, f"expected a JSON object, got {shown(s)}")
            if get(s, "step", "int", sat) != i + 1:
                raise sat.fail("step", f"expected {i + 1} (steps are numbered 1, 2, ... in order), got {s['step']}")
            rotation = get(s, "rotation", "number", sat)
            if not 0 <= rotation < 360:
                raise sat.fail("rotation", f"{rotation} is outside [0, 360)")
            metric = [get(s, k, "number", sat, optional=True) for k in ("x_m", "y_m")]
            steps.append(PlanStep(i + 1, get(s, "object", "int", sat, lo=0, hi=MAX_ID), get(s, "type", "str", sat),
                                  get(s, "x", "number", sat, lo=0.0, hi=1.0), get(s, "y", "number", sat, lo=0.0, hi=1.0),
                                  rotation, *metric))
        failed = get(obj, "failed", "bool", at, optional=True, default=False)
        diagnostics = obj.get("diagnostics") or {}
        if not isinstance(diagnostics, dict):
            raise at.fail("diagnostics", "expected a JSON object")
        return cls(tuple(steps), table, method, sha, failed, diagnostics)


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


__all__ = ["PLAN_FORMAT", "PLAN_VERSION", "Plan", "PlanStep", "PlanTable", "normalized_rotation"]
