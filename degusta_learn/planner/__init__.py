"""The planner: a plan for a new table from a person's past arrangements, by any registered method.

Usage:
    degusta plan --config baseline_consensus --request request.json --out plan/     # plan.json + plan.png
    degusta serve --config learned_predict --set checkpoint=runs/learned_cpu         # POST /plan on 127.0.0.1:8000

    from degusta_learn import Planner
    planner = Planner.from_config("baseline_consensus")
    plan = planner.plan({"participant": "p004", "table": 2})
    for step in plan.steps: print(step.step, step.type, step.object, step.x, step.y, step.rotation)

The request and plan formats are in docs/planner.md. Modules: request.py (`PlanRequest`, its JSON and bounds),
episode.py (a request as one episode with no answer), steps.py (objects on hand, the surface, rotations),
plan.py (`Plan`), planner.py (`Planner`), draw.py (plan.png), server.py (FastAPI app), schema.py (JSON Schemas).
"""

from degusta_learn.planner.plan import Plan, PlanStep, PlanTable
from degusta_learn.planner.planner import Planner
from degusta_learn.planner.request import LIMITS, MAX_REQUEST_BYTES, NewTable, PlanRequest, loads_request, read_request

__all__ = ["LIMITS", "MAX_REQUEST_BYTES", "NewTable", "Plan", "PlanRequest", "PlanStep", "PlanTable", "Planner",
           "loads_request", "read_request"]
