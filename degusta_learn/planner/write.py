"""`degusta plan`'s output folder: plan.json and plan.png, written whole or not at all (files.folders.write_folder)."""

from __future__ import annotations

import io
import json
from pathlib import Path

from degusta_learn.files.folders import OutputKind, write_folder
from degusta_learn.planner.plan import Plan
from degusta_learn.planner.planner import Planner

PLAN_FOLDER = OutputKind("plan", ("plan.json", "plan.png"))
"""What `degusta plan --out DIR` writes; a folder holding other files keeps them (the two are renamed in beside)."""


def write_plan(planner: Planner, plan: Plan, out: str | Path) -> Path:
    """Write plan.json (`Plan.to_json`) and plan.png (`Planner.image`) into the folder `out`; returns it."""
    image = planner.image(plan)  # drawn before the folder is touched: a drawing error leaves it as it was
    png = io.BytesIO()
    image.save(png, format="PNG", optimize=True)
    text = json.dumps(plan.to_json(), indent=2) + "\n"
    with write_folder(out, PLAN_FOLDER) as stage:
        (stage / "plan.json").write_text(text, encoding="utf-8")
        (stage / "plan.png").write_bytes(png.getvalue())
    return Path(out)


__all__ = ["PLAN_FOLDER", "write_plan"]
