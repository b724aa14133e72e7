"""The planner (degusta_learn/planner): a request as one episode with no answer, plans equal to `degusta predict`'s
predictions for the same episode, objects on hand, rotations, the surface, request validation, the plan's JSON and
`degusta plan`."""

from __future__ import annotations

import json
import subprocess
import sys

import jsonschema
import pytest
from conftest import make_small_dataset
from PIL import Image

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict
from degusta_learn.planner import Plan, Planner, PlanRequest, loads_request
from degusta_learn.planner.episode import PlanningDataset, Prepared, prepare
from degusta_learn.planner.plan import normalized_rotation
from degusta_learn.planner.schema import PLAN_SCHEMA, REQUEST_SCHEMA
from degusta_learn.planner.steps import INSIDE, finish, on_hand
from degusta_learn.scene import (
    Catalog,
    CatalogObject,
    Episode,
    Placement,
    Prediction,
    Table,
    load_dataset,
    make_episodes,
    read_predictions,
    save_dataset,
)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return save_dataset(make_small_dataset(), tmp_path_factory.mktemp("planner") / "data")


def planner(root, method="copy_nearest", *extra, **kw):
    return Planner.from_config(None, [f"method={method}", f"dataset={root}", *extra], **kw)


def episode_request(ds, ep) -> dict:
    """The request of a dataset episode: its participant, its context trials, its target's table (not the answer)."""
    return {"participant": ep.participant, "trials": list(ep.context),
            "table": ds.arrangement(ep.participant, ep.target).table}


@pytest.mark.parametrize("method,context", [("copy_nearest", 2), ("consensus", 4), ("population_mean", 2),
                                            ("copy_nearest", 0)])
def test_a_plan_for_a_test_episode_is_that_episodes_prediction(root, tmp_path, method, context):
    out = run_predict(None, [f"method={method}", f"dataset={root}", f"out={tmp_path / 'p.jsonl'}",
                             f"context={context}", "split=test"])
    ds = load_dataset(root)
    predictions = {p.episode: p for p in read_predictions(out, ds.catalog)}
    p = planner(root, method, f"context={context}", "split=test")  # the same config: the same fingerprint
    episodes = make_episodes(ds, context, "test")
    assert len(episodes) == 10
    for ep in episodes:
        plan = p.plan(episode_request(ds, ep))
        expected = [q.to_json() for q in predictions[ep.id].placements]
        assert [{"object": s.object, "x": s.x, "y": s.y, "rotation": s.rotation} for s in plan.steps] == expected
        assert [s.step for s in plan.steps] == list(range(1, len(expected) + 1))
        assert plan.config_sha256 == predictions[ep.id].diagnostics["choices"]["config_sha256"]
        assert plan.diagnostics["context"] == context and plan.diagnostics["replaced"] == []


def test_the_target_trial_holds_no_answer(root):
    ref = load_dataset(root)
    ep = make_episodes(ref, 2, "test")[0]
    prep = prepare(PlanRequest.from_json(episode_request(ref, ep)), ref, "data")
    ds = prep.ds
    target = ds.arrangement(prep.episode.participant, prep.episode.target)
    assert target.placements == () and target.table == ref.arrangement(ep.participant, ep.target).table
    assert target not in ds.arrangements  # no method counts it among anyone's arrangements
    mine = [a for a in ds.arrangements if a.participant == ep.participant]
    assert [a.trial for a in mine] == list(ep.context)  # the answer (and the unused trials) are gone
    assert prep.episode.context == ep.context and prep.episode.target not in ep.context
    assert len(ds.arrangements) == len(ref.arrangements) - 3  # 5 trials of the person, 2 kept as context
    assert ds.participants == ref.participants  # the same ids: the same split, the same population


def test_an_inline_history_plans_as_the_participant_form(root):
    ds = load_dataset(root)
    ep = make_episodes(ds, 4, "test")[3]
    p = planner(root, "consensus")
    by_id = p.plan(episode_request(ds, ep))
    inline = {"participant": ep.participant, "table": ds.arrangement(ep.participant, ep.target).table,
              "arrangements": [ds.arrangement(ep.participant, t).to_json() for t in ep.context]}
    assert p.plan(inline).to_json() == by_id.to_json()
    typed = PlanRequest(table=inline["table"], participant=ep.participant, trials=ep.context)
    assert p.plan(typed).to_json() == by_id.to_json()


def test_an_empty_history_gets_the_methods_population_default(root):
    plan = planner(root, "copy_nearest").plan({"table": 1})
    assert plan.diagnostics["context"] == 0 and plan.diagnostics["method"]["fallback"] == "population_mean"
    assert len(plan.steps) >= 3


def _tiny() -> tuple[Catalog, Table]:
    """Three plates whose features differ from plate 0 by 1 (plate 1: shape), 2 (plate 2: shape, pattern) and 1
    (plate 3: pattern), a fork, a cup."""
    objs = [CatalogObject(0, "plate", "red", "red", "ceramic", "ceramic", "round", "solid"),
            CatalogObject(1, "plate", "red", "red", "ceramic", "ceramic", "square", "solid"),
            CatalogObject(2, "plate", "red", "red", "ceramic", "ceramic", "square", "dotted"),
            CatalogObject(3, "plate", "red", "red", "ceramic", "ceramic", "round", "dotted"),
            CatalogObject(4, "fork", "gray", "gray", "metal", "metal", "straight", "solid"),
            CatalogObject(5, "cup", "blue", "blue", "glass", "glass", "round", "solid")]
    return Catalog(tuple(objs)), Table(0, 100, 100, ((0.2, 0.2), (0.8, 0.2), (0.8, 0.8), (0.2, 0.8)))


def _prepared(hand, n_objects=None, metres=None) -> Prepared:
    catalog, table = _tiny()
    ds = PlanningDataset(catalog, {0: table}, [])
    return Prepared(ds, Episode("x/plan/k0", "x", (), 0, "generalization"), table, tuple(hand), metres, n_objects)


def _at(*objects):
    return [Placement(o, 0.3 + 0.1 * i, 0.5, 90.0) for i, o in enumerate(objects)]


def test_objects_not_on_hand_are_replaced_by_the_nearest_of_their_type_or_dropped():
    # plate 0 missing: plates 1 and 3 are both 1 feature away -> the lower id, 1; plate 2 (2 away) never
    placed, replaced, dropped = on_hand(_at(0, 4, 5), _prepared([1, 2, 3, 4]))
    assert [p.object for p in placed] == [1, 4]
    assert placed[0] == Placement(1, 0.3, 0.5, 90.0)  # the same place and rotation
    assert replaced == [{"step": 1, "proposed": 0, "object": 1, "type": "plate", "feature_distance": 1}]
    assert dropped == [{"object": 5, "type": "cup", "reason": "no cup on hand"}]
    # plate 3 is placed by the method itself: the replacement of plate 0 may not take it, so it gets plate 2
    placed, replaced, _ = on_hand(_at(0, 3), _prepared([2, 3]))
    assert [p.object for p in placed] == [2, 3] and replaced[0]["feature_distance"] == 2
    # every plate on hand already placed: dropped, and said why
    placed, _, dropped = on_hand(_at(0, 1), _prepared([1]))
    assert [p.object for p in placed] == [1]
    assert dropped == [{"object": 0, "type": "plate", "reason": "every plate on hand is placed already"}]


def test_a_plan_uses_only_the_objects_on_hand(root):
    ds = load_dataset(root)
    ep = make_episodes(ds, 2, "test")[0]
    p = planner(root)
    full = p.plan(episode_request(ds, ep))
    first = full.steps[0]
    hand = [o for o in ds.catalog.ids if o != first.object]
    plan = p.plan({**episode_request(ds, ep), "objects": hand})
    assert {s.object for s in plan.steps} <= set(hand)
    assert (plan.steps[0].type, plan.steps[0].x, plan.steps[0].y) == (first.type, first.x, first.y)
    assert plan.diagnostics["replaced"][0]["proposed"] == first.object
    assert [s.object for s in plan.steps[1:]] == [s.object for s in full.steps[1:]]
    # no object of the first step's type on hand: that step is dropped, the others move up
    others = [o for o in ds.catalog.ids if ds.catalog[o].type != first.type]
    plan = p.plan({**episode_request(ds, ep), "objects": others})
    kept = [s for s in full.steps if s.type != first.type]
    assert [s.object for s in plan.steps] == [s.object for s in kept]
    assert {d["type"] for d in plan.diagnostics["dropped"]} == {first.type}


@pytest.mark.parametrize("given,expected", [(360.0, 0.0), (359.99999, 0.0), (-90.0, 270.0), (720.5, 0.5),
                                            (-0.0, 0.0), (359.9999, 359.9999)])
def test_rotations_are_normalized_to_0_360(given, expected):
    value = normalized_rotation(given)
    assert value == expected and 0 <= value < 360 and str(value) != "-0.0"


def test_finish_normalizes_rotation_clamps_onto_the_surface_and_cuts():
    prep = _prepared([0, 1, 4, 5], n_objects=2, metres=(2.0, 1.0))
    pred = Prediction("x/plan/k0", "x", 0, "m", [Placement(0, 0.9, 0.5, 360.0), Placement(4, 0.5, 0.5, 359.99999),
                                                 Placement(5, 0.4, 0.4, 10.0)])
    steps, made = finish(pred, prep)
    assert [(s.object, s.rotation) for s in steps] == [(0, 0.0), (4, 0.0)]
    assert (steps[0].x, steps[0].y) == (round(0.8 - INSIDE, 6), 0.5)  # the nearest point of the surface
    assert (steps[1].x, steps[1].y) == (0.5, 0.5)
    assert (steps[0].x_m, steps[0].y_m) == (round(2 * (0.8 - INSIDE), 4), 0.5)  # x * 2 m, y * 1 m
    assert made["clamped"] == [1] and made["cut"] == 1


def test_a_new_table_with_its_size_in_metres(root):
    surface = [[0.1, 0.1], [0.9, 0.1], [0.9, 0.6], [0.1, 0.6]]
    plan = planner(root).plan({"participant": "p000", "trials": [0, 1],
                               "table": {"width": 1600, "height": 1000, "surface": surface, "name": "kitchen",
                                         "metres": [1.6, 1.0]}})
    assert plan.table.id == 5 and plan.table.metres == (1.6, 1.0) and plan.table.name == "kitchen"
    table = plan.table.table
    for s in plan.steps:
        assert table.contains(s.x, s.y)
        assert (s.x_m, s.y_m) == (round(s.x * 1.6, 4), round(s.y * 1.0, 4))


BAD = [
    ({"table": {"width": 100, "height": 100, "surface": [[0, 0], [1, 0], [1, 1], [2, 0]]}},
     "request.table.surface[3]: expected [x, y] with both in [0, 1]"),
    ({"table": {"width": 100, "height": 100, "surface": [[0, 0], [0.5, 0.5], [1, 1]]}},
     "request.table.surface: a degenerate polygon"),
    ({"table": 99}, "request.table: unknown table id 99"),
    ({"table": {"id": 0, "width": 9, "height": 9, "surface": [[0, 0], [1, 0], [1, 1]]}},
     "request.table.id: table 0 is a known table"),
    ({}, "request.table: missing"),
    ({"table": 0, "colour": "red"}, "request.colour: unknown key"),
    ({"table": 0, "objects": [3, 999]}, "request.objects[1]: unknown object id 999"),
    ({"table": 0, "objects": [3, 3]}, "request.objects[1]: object 3 is listed twice"),
    ({"table": 0, "objects": list(range(1001))}, "request.objects: 1001 objects, over the limit of 1000"),
    ({"table": 0, "n_objects": 0}, "request.n_objects: 0 is out of range"),
    ({"table": 0, "arrangements": [{"table": 0, "placements": [{"object": 1, "x": 1.5, "y": 0.5}]}]},
     "request.arrangements[0].placements[0].x: 1.5 is out of range"),
    ({"table": 0, "arrangements": [{"table": 7, "placements": [{"object": 1, "x": 0.5, "y": 0.5}]}]},
     "request.arrangements[0].table: unknown table id 7"),
    ({"table": 0, "arrangements": [{"table": 0, "placements": [{"object": 900, "x": 0.5, "y": 0.5}]}]},
     "request.arrangements[0].placements[0].object: unknown object id 900"),
    ({"table": 0, "arrangements": [{"table": 0, "placements": [{"object": 1, "x": 0.5, "y": 0.5}]}] * 9},
     "request.arrangements: 9 arrangements, over the limit of 8"),
    ({"table": 0, "participant": "nobody"}, "request.participant: no participant 'nobody'"),
    ({"table": 0, "participant": "p000", "trials": [7]}, "request.trials[0]: participant 'p000' has no trial 7"),
    ({"table": 0, "trials": [1]}, "request.trials: only with `participant`"),
    ({"table": {"id": 0, "metres": [1.0, -2]}}, "request.table.metres: expected [width, height]"),
    ({"table": 0, "catalog": [{"id": 0, "class": "cup"}]}, "request.catalog: objects 1, 2, 3"),
]


@pytest.mark.parametrize("request_json,message", BAD, ids=[m.split(":")[0] + str(i) for i, (_, m) in enumerate(BAD)])
def test_a_bad_request_is_one_line_naming_the_field(root, request_json, message):
    with pytest.raises(DegustaError) as e:
        planner(root).plan(request_json)
    assert str(e.value).startswith(message), str(e.value)
    assert "\n" not in str(e.value)


def test_another_catalog_is_refused_naming_the_difference(root):
    ds = load_dataset(root)
    catalog = ds.catalog.to_json()
    planner(root).plan({"table": 0, "catalog": catalog})  # the planner's own catalog, repeated: fine
    catalog[17] = {**catalog[17], "color1": "purple" if catalog[17]["color1"] != "purple" else "red"}
    with pytest.raises(DegustaError, match=r"^request\.catalog\[17\]\.color1: '(purple|red)' differs from the "
                                           r"planner's catalog .*object 17 has"):
        planner(root).plan({"table": 0, "catalog": catalog})


@pytest.mark.parametrize("data,message", [
    (b'{"table": 0, "n_objects": NaN}', "request: invalid JSON (NaN is not a number JSON allows"),
    (b'{"table": 0, "table": 1}', "request: invalid JSON (the key 'table' is given twice"),
    (b'{"table": 0', "request: invalid JSON at line 1 column 12"),
    (b'{"table": 1e999}', "request: invalid JSON ('1e999' overflows to infinity"),
    (b'\xff{}', "request: not UTF-8 text"),
    (b'[' * 100_000, "request: invalid JSON (nested too deeply)"),
    (b" " * (2**20 + 1), "request: 1,048,577 bytes, over the limit of 1,048,576 bytes"),
])
def test_request_bytes_are_read_strictly(data, message):
    with pytest.raises(DegustaError) as e:
        loads_request(data)
    assert str(e.value).startswith(message), str(e.value)


def test_the_oracle_cannot_plan(root):
    with pytest.raises(DegustaError, match="method 'oracle' cannot plan: the oracle reads the generator's latent"):
        planner(root, "oracle")


def test_a_plan_round_trips_through_its_json_and_schema(root):
    plan = planner(root, "random").plan({"participant": "p001", "table": {"id": 2, "metres": [0.9, 0.9]}})
    data = json.loads(json.dumps(plan.to_json()))
    jsonschema.validate(data, PLAN_SCHEMA)
    assert Plan.from_json(data) == plan
    assert all(0 <= s["rotation"] < 360 for s in data["steps"])
    data["steps"][0]["rotation"] = 360.0
    with pytest.raises(DegustaError, match=r"^plan\.steps\[0\]\.rotation: 360\.0 is outside \[0, 360\)"):
        Plan.from_json(data)
    for request_json, _ in BAD[2:3]:  # the schema describes the form; ids are checked against the planner's data
        jsonschema.validate(request_json, REQUEST_SCHEMA)
    jsonschema.validate({"participant": "p001", "trials": [0, 2], "table": {"id": 2}, "objects": [1, 2]},
                        REQUEST_SCHEMA)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"table": 0, "colour": 1}, REQUEST_SCHEMA)


def test_cli_plan_writes_plan_json_and_png(root, tmp_path, capsys):
    request = tmp_path / "request.json"
    request.write_text(json.dumps({"participant": "p002", "trials": [0, 1, 2], "table": 3, "n_objects": 3}))
    out = tmp_path / "plan"
    assert main(["plan", "--config", "baseline_copy_nearest", "--set", f"dataset={root}", "--request", str(request),
                 "--out", str(out)]) == 0
    assert "copy_nearest: 3 steps; wrote plan.json and plan.png" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["plan.json", "plan.png"]
    plan = Plan.from_json(json.loads((out / "plan.json").read_text()))
    assert len(plan.steps) == 3 and plan.method == "copy_nearest"
    with Image.open(out / "plan.png") as img:
        assert img.format == "PNG" and img.width == 512 and img.height > 512
    # a bad request: one line, exit 2, nothing written
    request.write_text(json.dumps({"table": 3, "objects": [9999]}))
    again = tmp_path / "again"
    assert main(["plan", "--config", "baseline_copy_nearest", "--set", f"dataset={root}", "--request", str(request),
                 "--out", str(again)]) == 2
    err = capsys.readouterr().err
    assert err == f"degusta: error: {request}: request.objects[0]: unknown object id 9999 (not in the planner's " \
                  f"catalog, {root}/catalog.json)\n"
    assert not again.exists()
    request.write_bytes(b" " * (2**20 + 5))
    assert main(["plan", "--config", "baseline_copy_nearest", "--set", f"dataset={root}", "--request", str(request),
                 "--out", str(again)]) == 2
    assert "file too large" in capsys.readouterr().err and not again.exists()


def test_a_request_may_name_a_dataset_folder_but_a_server_planner_refuses(root, tmp_path):
    other = save_dataset(make_small_dataset(n_participants=4, seed=3), tmp_path / "other")
    plan = planner(root).plan({"participant": "p003", "dataset": str(other), "trials": [0, 1], "table": 2})
    assert plan.diagnostics["context"] == 2
    with pytest.raises(DegustaError, match="^request.dataset: this planner reads arrangements only from its own"):
        planner(root, read_paths=False).plan({"participant": "p003", "dataset": str(other), "table": 2})


def test_import_degusta_learn_stays_light_and_exports_planner():
    code = ("import sys, degusta_learn\n"
            "assert 'degusta_learn.planner' not in sys.modules and 'torch' not in sys.modules\n"
            "from degusta_learn import Planner\n"
            "from degusta_learn.planner import Planner as P\n"
            "assert Planner is P\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
