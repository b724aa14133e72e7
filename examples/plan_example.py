"""Plan a new table for a person from Python: load a method once, ask it for plans, read the steps.

Usage (CPU, seconds; generates the embedded SYNTHETIC default into data/naturalistic if it is missing):
    python examples/plan_example.py
    python examples/plan_example.py --config learned_predict --set checkpoint=runs/learned_cpu   # a trained model

The same requests work from the command line (`degusta plan --request request.json`) and over HTTP
(`degusta serve`, POST /plan); docs/planner.md documents the request and the plan.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from degusta_learn import Planner
from degusta_learn.synth import generate_dataset

DATA = Path("data/naturalistic")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="baseline_consensus", help="a predict config (name or path)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    parser.add_argument("--out", type=Path, default=Path("runs/plan_example"), help="where plan.png goes")
    args = parser.parse_args()
    if not (DATA / "catalog.json").is_file():
        generate_dataset("naturalistic", DATA, seed=0)
    planner = Planner.from_config(args.config, [f"dataset={DATA}", *args.set])  # loads the method once
    person = planner.dataset.participants[0]

    # 1. A person of the dataset, their first four tables as the history, a new 1.2 m x 0.8 m table to set,
    #    with only some objects on hand: the first three of each type (ids: cups 0-24, forks 25-49, knives 50-74,
    #    plates 75-99, spoons 100-124 in the default catalog).
    table = {"width": 1200, "height": 800, "surface": [[0.05, 0.08], [0.95, 0.08], [0.95, 0.92], [0.05, 0.92]],
             "name": "oak", "metres": [1.2, 0.8]}
    plan = planner.plan({"participant": person, "trials": [0, 1, 2, 3], "table": table,
                         "objects": [o for o in planner.dataset.catalog.ids if o % 25 < 3]})
    print(f"{plan.method} planned {len(plan.steps)} steps for {person} (config {plan.config_sha256[:12]}):")
    for s in plan.steps:
        print(f"  {s.step}. {s.type:<5} #{s.object:<3} at ({s.x_m:.3f} m, {s.y_m:.3f} m), rotated {s.rotation:.0f} deg")
    for r in plan.diagnostics["replaced"]:
        print(f"  step {r['step']}: {r['proposed']} is not on hand, {r['object']} (the nearest {r['type']}) instead")
    for d in plan.diagnostics["dropped"]:
        print(f"  left out: object {d['object']} ({d['reason']})")

    # 2. Someone new: no history at all (the method's population default), a known table, at most 4 objects.
    plan = planner.plan({"table": 2, "n_objects": 4})
    print(f"a new person on table 2: {[(s.type, s.object) for s in plan.steps]}")

    args.out.mkdir(parents=True, exist_ok=True)
    planner.image(plan).save(args.out / "plan.png")
    print(f"drew the last plan in {args.out / 'plan.png'}")


if __name__ == "__main__":
    main()
