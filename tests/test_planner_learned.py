"""The planner with the learned model: a tiny checkpoint (3 training steps) plans what `degusta predict` predicts,
loads once for many plans, and never answers a rotation of 360."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import make_small_dataset

from degusta_learn.baselines import learned
from degusta_learn.baselines.learned import LearnedTrainConfig, train
from degusta_learn.baselines.learned.slot_model import SlotModel
from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict
from degusta_learn.planner import Planner
from degusta_learn.scene import load_dataset, make_episodes, read_predictions, save_dataset

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("planner_learned")
    ds = make_small_dataset()
    root = save_dataset(ds, tmp / "data")
    cfg = {"kind": "learned", "num_threads": 1, "dataset": str(root), "data": {"batch_size": 8, "repeats": 1},
           "model": {"d_model": 16, "n_layers": 1, "n_heads": 2, "d_ff": 32, "max_objects": 8},
           "trainer": {"run_dir": str(tmp), "run_name": "tiny", "max_epochs": -1, "max_steps": 3,
                       "accelerator": "cpu", "devices": 1, "progress_bar": False, "log_every_n_steps": 1}}
    torch.set_num_threads(1)
    return train(from_dict(LearnedTrainConfig, cfg), ds), root


def _sets(run, root):
    # batch_size 1: predict decodes each episode alone, as the planner does (a batch of 10 sums attention over other
    # padding and can move a rotation's 4th decimal)
    return ["method=learned", f"dataset={root}", f"checkpoint={run / 'last.ckpt'}", "num_threads=1", "context=2",
            "batch_size=1"]


def test_learned_plans_equal_predictions_and_the_model_loads_once(trained, tmp_path, monkeypatch):
    run, root = trained
    out = run_predict(None, [*_sets(run, root), f"out={tmp_path / 'p.jsonl'}"])
    ds = load_dataset(root)
    predictions = {p.episode: p for p in read_predictions(out, ds.catalog)}
    loads = []
    real = learned.load_model
    monkeypatch.setattr(learned, "load_model", lambda *a, **k: loads.append(a) or real(*a, **k))
    planner = Planner.from_config(None, _sets(run, root))
    episodes = make_episodes(ds, 2, "test")
    for ep in episodes:
        plan = planner.plan({"participant": ep.participant, "trials": list(ep.context),
                             "table": ds.arrangement(ep.participant, ep.target).table})
        expected = [q.to_json() for q in predictions[ep.id].placements]
        assert [{"object": s.object, "x": s.x, "y": s.y, "rotation": s.rotation} for s in plan.steps] == expected
        assert plan.config_sha256 == predictions[ep.id].diagnostics["choices"]["config_sha256"]
    assert len(loads) == 1, "the checkpoint must be loaded once for all plans"
    # a new table, an empty history (the checkpoint's population rows), a new person: it plans
    plan = planner.plan({"table": {"width": 800, "height": 600, "surface": [[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]]}})
    assert plan.steps and all(plan.table.table.contains(s.x, s.y) for s in plan.steps)
    assert len(loads) == 1


def test_a_rotation_of_360_from_the_model_is_planned_as_0(trained, monkeypatch):
    run, root = trained
    decode = SlotModel.decode

    def at_360(self, batch, min_objects=1):
        objs, xy, rot = decode(self, batch, min_objects)
        return objs, xy, [np.full(len(r), 360.0, dtype=np.float32) for r in rot]  # float32 % 360 can give 360

    monkeypatch.setattr(SlotModel, "decode", at_360)
    person = make_episodes(load_dataset(root), 2, "test")[0].participant  # one the model never saw
    plan = Planner.from_config(None, _sets(run, root)).plan({"participant": person, "trials": [0, 1], "table": 2})
    assert plan.steps and {s.rotation for s in plan.steps} == {0.0}
    model, hp = learned.load_model(run / "last.ckpt")  # the learned method itself answers 0, not 360
    ds = load_dataset(root)
    pred = learned.predict_episodes(model, ds, make_episodes(ds, 2, "test")[:1], hp["population"])[0]
    assert {p.rotation for p in pred.placements} == {0.0}


def test_a_participant_the_model_trained_on_is_refused_as_predict_refuses(trained):
    run, root = trained
    from degusta_learn.scene import split_participants

    train_id = split_participants(load_dataset(root).participants, 0)["train"][0]
    with pytest.raises(DegustaError, match="training participants of this model|in this model's training split"):
        Planner.from_config(None, _sets(run, root)).plan({"participant": train_id, "trials": [0, 1], "table": 2})
