"""The set-prediction transformer: its Hungarian matching loss by hand, a tiny Lightning run, predict, bad input."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from degusta_learn.baselines.learned import load_model as load_learned
from degusta_learn.baselines.set_transformer import SetTransformerTrainConfig, load_model, predict_episodes, train
from degusta_learn.baselines.set_transformer.encoding import SetEncoder, collate_sets
from degusta_learn.baselines.set_transformer.matching import assign, set_loss
from degusta_learn.baselines.set_transformer.model import ModelConfig, SetTransformer
from degusta_learn.baselines.learned.features import Vocab
from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict, run_train
from degusta_learn.metrics import score_many
from degusta_learn.scene import load_dataset, make_episodes, read_predictions, save_dataset

sys.path.insert(0, str(Path(__file__).parent))
from conftest import make_small_dataset  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py
LN2 = math.log(2.0)


def _two_by_two():
    """Two queries, two target objects (catalog of 3), built so that the greedy choice (query 0 takes its cheapest
    object first) is wrong: the optimal assignment is query 0 -> target 1, query 1 -> target 0."""
    out = {"present": torch.zeros(1, 2),  # sigmoid 0.5: -log = ln 2 in every cost entry
           "obj": torch.log(torch.tensor([[[0.5, 0.4, 0.1], [0.8, 0.1, 0.1]]])),
           "xy": torch.tensor([[[0.45, 0.5], [0.5, 0.5]]]),
           "rot": torch.tensor([[[1.0, 0.0], [0.0, 1.0]]]),  # (sin, cos): 90 and 0 degrees
           "step": torch.tensor([[0.1, 0.0]])}
    batch = {"y_obj": torch.tensor([[0, 1]]), "y_xy": torch.tensor([[[0.5, 0.5], [0.3, 0.5]]]),
             "y_rot": torch.tensor([[math.pi, math.pi / 2]]), "y_step": torch.tensor([[0.0, 0.05]]),
             "y_mask": torch.tensor([[True, True]])}
    return out, batch


def test_matching_loss_on_a_hand_computed_two_by_two_case():
    out, batch = _two_by_two()
    cfg = ModelConfig()  # w_present 1, w_object 1, w_position 1, w_rotation 0.2, w_step 0.2
    # cost C[i, j] = -log sigmoid(0) - log p_i(obj_j) + 100 * |xy_i - xy_j|^2:
    #   C00 = ln2 - ln0.5 + 100 * 0.0025 = 1.636   C01 = ln2 - ln0.4 + 100 * 0.0225 = 3.859
    #   C10 = ln2 - ln0.8 + 0              = 0.916   C11 = ln2 - ln0.1 + 100 * 0.04   = 6.996
    # identity 8.632, swapped 4.776: the swap wins although query 0 is nearer target 0
    (queries, targets), = assign(out, batch, cfg)
    assert dict(zip(queries.tolist(), targets.tolist())) == {0: 1, 1: 0}
    losses = set_loss(out, batch, cfg)
    expected = {"present": LN2,  # both queries matched: -log sigmoid(0) each
                "object": (-math.log(0.4) - math.log(0.8)) / 2,
                "position": (100 * 0.15 ** 2 + 0.0) / 2,  # query 0 at 0.45 vs target 1 at 0.3; query 1 exact
                "rotation": (0.0 + 2.0) / 2,  # 90 vs 90 degrees; 0 vs 180 degrees: 1 - cos(pi) = 2
                "step": (0.05 ** 2 + 0.0) / 2}
    expected["loss"] = (expected["present"] + expected["object"] + expected["position"] + 0.2 * expected["rotation"]
                        + 0.2 * expected["step"])
    for key, value in expected.items():
        assert float(losses[key]) == pytest.approx(value, rel=1e-6), key
    assert float(losses["loss"]) == pytest.approx(0.6931 + 0.5697 + 1.125 + 0.2 + 0.0005 * 0.5, abs=1e-3)


def test_unmatched_queries_are_pushed_to_absent():
    """Three queries, one target object: two queries stay unmatched and their present loss pulls them to absent,
    each weighted by absent_weight."""
    cfg = ModelConfig(absent_weight=0.5)
    out = {"present": torch.tensor([[0.0, 1.0, -1.0]], requires_grad=True),
           "obj": torch.log(torch.full((1, 3, 2), 0.5)), "xy": torch.tensor([[[0.5, 0.5], [0.9, 0.9], [0.1, 0.1]]]),
           "rot": torch.tensor([[[0.0, 1.0]] * 3]), "step": torch.zeros(1, 3)}
    batch = {"y_obj": torch.tensor([[1]]), "y_xy": torch.tensor([[[0.5, 0.5]]]), "y_rot": torch.zeros(1, 1),
             "y_step": torch.zeros(1, 1), "y_mask": torch.tensor([[True]])}
    (queries, targets), = assign(out, batch, cfg)
    assert queries.tolist() == [0] and targets.tolist() == [0]  # the query on the spot, not the most present one
    losses = set_loss(out, batch, cfg)
    # BCE(0 -> 1) = ln 2; BCE(1 -> 0) = ln(1 + e); BCE(-1 -> 0) = ln(1 + e^-1); weights 1, 0.5, 0.5
    present = (LN2 + 0.5 * math.log(1 + math.e) + 0.5 * math.log(1 + math.exp(-1))) / 2.0
    assert float(losses["present"].detach()) == pytest.approx(present, rel=1e-6)
    losses["loss"].backward()
    grad = out["present"].grad[0]
    assert grad[0] < 0 and grad[1] > 0 and grad[2] > 0  # descent raises the matched logit, lowers the others


def test_the_loss_does_not_depend_on_the_order_of_the_target():
    torch.manual_seed(0)
    B, Q, n_obj, M = 2, 6, 10, 4
    out = {"present": torch.randn(B, Q), "obj": torch.randn(B, Q, n_obj).log_softmax(-1), "xy": torch.rand(B, Q, 2),
           "rot": torch.nn.functional.normalize(torch.randn(B, Q, 2), dim=-1), "step": torch.rand(B, Q)}
    batch = {"y_obj": torch.tensor([[3, 1, 7, 0], [2, 5, 9, -1]]), "y_xy": torch.rand(B, M, 2),
             "y_rot": torch.rand(B, M) * 6.28, "y_step": torch.tensor([[0.0, 0.05, 0.1, 0.15], [0.0, 0.05, 0.1, 0.0]]),
             "y_mask": torch.tensor([[True] * 4, [True, True, True, False]])}
    before = set_loss(out, batch, ModelConfig())
    perm = [torch.tensor([2, 0, 3, 1]), torch.tensor([1, 2, 0, 3])]  # episode 1 keeps its padding last
    shuffled = {k: torch.stack([v[b][perm[b]] for b in range(B)]) if k.startswith("y_") else v for k, v in batch.items()}
    after = set_loss(out, shuffled, ModelConfig())
    for key in before:
        assert float(after[key]) == pytest.approx(float(before[key]), rel=1e-6), key
    # and the matched (query -> object) pairs are the same pairs
    for b, ((q0, t0), (q1, t1)) in enumerate(zip(assign(out, batch, ModelConfig()), assign(out, shuffled, ModelConfig()))):
        objs = batch["y_obj"][b]
        assert dict(zip(q0.tolist(), objs[t0].tolist())) == dict(zip(q1.tolist(), objs[perm[b][t1]].tolist()))


def test_a_few_steps_on_one_batch_lower_the_loss():
    ds = make_small_dataset()
    vocab = Vocab.from_dataset(ds)
    model = SetTransformer(ModelConfig(d_model=16, n_heads=2, n_encoder_layers=1, n_decoder_layers=1, d_ff=32,
                                       n_queries=8), vocab)
    encode = SetEncoder(vocab, ds.tables, 8)
    by_p = ds.by_participant()
    batch = collate_sets([encode(trials[:2], trials[4].table, trials[4]) for trials in list(by_p.values())[:4]])
    torch.manual_seed(0)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    first = set_loss(model(batch), batch, model.cfg)["loss"].item()
    for _ in range(30):
        loss = set_loss(model(batch), batch, model.cfg)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert set_loss(model(batch), batch, model.cfg)["loss"].item() < 0.5 * first


def test_rotation_and_order_start_from_the_placed_objects_context_tokens():
    """With the heads' corrections at zero, a query placing an object the context shows once takes that token's
    position, rotation and step exactly, whatever else it attends to; an object the context lacks gets what the
    whole pointer shows."""
    from degusta_learn.baselines.set_transformer.encoding import CARRIED, ROTATION, STEP

    ds = make_small_dataset()
    vocab = Vocab.from_dataset(ds)
    torch.manual_seed(0)
    model = SetTransformer(ModelConfig(d_model=16, n_heads=2, n_encoder_layers=1, n_decoder_layers=1, d_ff=32,
                                       n_queries=8), vocab)
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.zero_()
    encode = SetEncoder(vocab, ds.tables, 8)
    trials = next(iter(ds.by_participant().values()))
    batch = collate_sets([encode(trials[:1], trials[4].table, trials[4])])  # context 1: each object once
    out = model(batch)
    feat, tok_obj = batch["tok_feat"][0], batch["tok_obj"][0]
    n_tok = int(batch["tok_mask"][0].sum())
    assert len(set(tok_obj[:n_tok].tolist())) == n_tok
    for t in range(n_tok):
        for q in range(8):
            placed = out["placing"](torch.tensor(0), torch.tensor(q), tok_obj[t])
            torch.testing.assert_close(placed["xy"], feat[t, CARRIED])
            torch.testing.assert_close(placed["rot"], torch.nn.functional.normalize(feat[t, ROTATION], dim=-1))
            torch.testing.assert_close(placed["step"], feat[t, STEP])
    absent = next(o for o in range(vocab.n_objects) if o not in tok_obj[:n_tok].tolist())
    placed = out["placing"](torch.tensor(0), torch.tensor(2), torch.tensor(absent))
    for key in ("xy", "rot", "step"):
        torch.testing.assert_close(placed[key], out[key][0, 2])
    objs, _, rots = model.decode(batch, min_objects=3)
    shown = {int(tok_obj[t]): math.degrees(math.atan2(*feat[t, ROTATION].tolist())) % 360.0 for t in range(n_tok)}
    for row, angle in zip(objs[0], rots[0]):
        if row in shown:
            assert angle == pytest.approx(shown[row], abs=1e-3)


def _metrics(run: Path) -> list[dict]:
    with open(run / "csv/version_0/metrics.csv") as f:
        return list(csv.DictReader(f))


def tiny_config(tmp_path, dataset, **trainer) -> dict:
    return {"kind": "set_transformer", "num_threads": 1, "dataset": str(dataset),
            "data": {"batch_size": 8, "repeats": 1},
            "model": {"d_model": 16, "n_heads": 2, "n_encoder_layers": 1, "n_decoder_layers": 1, "d_ff": 32,
                      "n_queries": 8},
            "optim": {"lr": 1e-2, "warmup_steps": 2},
            "trainer": {"run_dir": str(tmp_path), "run_name": "tiny", "max_epochs": -1, "max_steps": 24,
                        "accelerator": "cpu", "devices": 1, "progress_bar": False, "log_every_n_steps": 1,
                        "loggers": ["csv"], **trainer}}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One tiny Lightning run (24 steps, validated at steps 12 and 24), shared by the checkpoint tests."""
    tmp = tmp_path_factory.mktemp("set_transformer")
    root = save_dataset(make_small_dataset(), tmp / "data")
    ds = load_dataset(root)  # as `degusta train` reads it (its fingerprint is what predict checks)
    torch.set_num_threads(1)
    run = train(from_dict(SetTransformerTrainConfig, tiny_config(tmp, root, val_check_interval=12)), ds)
    return run, root, ds


def test_a_tiny_run_lowers_the_loss_and_logs_the_set_score(trained):
    run, _, _ = trained
    for name in ("config.yaml", "last.ckpt", "best.ckpt"):
        assert (run / name).is_file(), name
    rows = _metrics(run)
    train_loss = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    val = [r for r in rows if r.get("val/set_rmsd")]
    # the batches differ (episodes drawn afresh), so compare means, and the fixed validation episodes' loss
    assert len(train_loss) == 24 and np.mean(train_loss[-8:]) < 0.95 * np.mean(train_loss[:8])
    assert float(val[1]["val/loss"]) < float(val[0]["val/loss"])
    assert len(val) == 2 and {"val/set_rmsd_k0", "val/set_rmsd_k2", "val/set_rmsd_k4", "val/object_accuracy"} <= set(val[0])
    ckpt = torch.load(run / "best.ckpt", weights_only=True)
    assert ckpt["hyper_parameters"]["kind"] == "set_transformer"
    monitor = next(v for k, v in ckpt["callbacks"].items() if k.startswith("ModelCheckpoint") and v["monitor"])
    assert monitor["monitor"] == "val/set_rmsd" and float(monitor["best_model_score"]) == pytest.approx(
        min(float(r["val/set_rmsd"]) for r in val), rel=1e-6)


def test_validation_set_rmsd_is_what_evaluate_scores(trained):
    """val/set_rmsd of the last validation (at the last step: last.ckpt's weights) equals the mean set RMSD that
    degusta_learn.metrics gives the same weights' predictions of the validation episodes."""
    run, _, ds = trained
    model, hp = load_model(run / "last.ckpt")
    rows = _metrics(run)
    logged = [float(r["val/set_rmsd"]) for r in rows if r.get("val/set_rmsd")][-1]
    episodes = [e for k in (0, 2, 4) for e in make_episodes(ds, k, "val", 0)]
    preds = predict_episodes(model, ds, episodes, hp["min_objects"])
    scores = score_many(ds.catalog, [ds.arrangement(e.participant, e.target) for e in episodes], preds)
    assert logged == pytest.approx(np.mean([s.set_rmsd for s in scores]), abs=1e-5)


def test_the_checkpoint_predicts_through_the_registry(trained, tmp_path):
    run, root, _ = trained
    ds = load_dataset(root)
    out = run_predict(None, ["method=set_transformer", f"dataset={root}", f"out={tmp_path / 'p.jsonl'}",
                             "context=4", f"checkpoint={run}"])
    preds = read_predictions(out, ds.catalog)
    assert len(preds) == len(make_episodes(ds, 4, "test", 0))
    for p in preds:
        objects = [q.object for q in p.placements]
        assert 3 <= len(objects) <= 8 and len(set(objects)) == len(objects)  # min_objects .. n_queries, no repeats
        table = ds.tables[ds.arrangement(p.participant, p.target).table]
        xy = np.array([[q.x, q.y] for q in p.placements])
        assert table.contains(xy[:, 0], xy[:, 1]).all()
    with pytest.raises(DegustaError, match=r"^seed: \d+ of the \d+ participants predicted here are"):
        run_predict(None, ["method=set_transformer", f"dataset={root}", f"out={tmp_path / 'v.jsonl'}",
                           "split=val", f"checkpoint={run}"])


def test_a_checkpoint_of_the_other_kind_or_an_older_format_is_refused(trained, tmp_path):
    run, _, _ = trained
    with pytest.raises(DegustaError, match="kind 'set_transformer', not a 'learned'"):
        load_learned(run / "best.ckpt")
    ckpt = torch.load(run / "best.ckpt", weights_only=True)
    ckpt["hyper_parameters"]["kind"] = "learned"
    torch.save(ckpt, tmp_path / "learned.ckpt")
    with pytest.raises(DegustaError, match="kind 'learned', not a 'set_transformer' model"):
        load_model(tmp_path / "learned.ckpt")
    (tmp_path / "junk.ckpt").write_text("not a checkpoint")
    with pytest.raises(DegustaError, match="junk.ckpt: not a loadable"):
        load_model(tmp_path / "junk.ckpt")
    ckpt["hyper_parameters"].update(kind="set_transformer", format=1)  # rotation and step heads from scratch
    torch.save(ckpt, tmp_path / "format1.ckpt")
    with pytest.raises(DegustaError, match="format 1; this version reads format 2.*retrain"):
        load_model(tmp_path / "format1.ckpt")


@pytest.mark.parametrize("overrides, message", [
    (["model.d_modle=8"], "unknown key 'model.d_modle'"),
    (["model.n_heads=3"], "model.n_heads: 3 does not divide model.d_model=64"),
    (["model.n_queries=0"], "model.n_queries: expected a value from 1"),
    (["model.dropout=1.0"], r"model.dropout: expected in \[0, 1\)"),
    (["model.absent_weight=-1"], "model.absent_weight: expected at least 0"),
    (["model.w_object=0", "model.w_position=0"], "model.w_object / model.w_position: both 0"),
    (["trainer.monitor=test/set_rmsd"], "trainer.monitor: 'test/set_rmsd' refused"),
    (["data.contexts=[3]"], "data.contexts"),
    (["kind=set_transformr"], "unknown trainer kind 'set_transformr'"),
])
def test_bad_config_names_the_key(tmp_path, overrides, message):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("# degusta train --config c.yaml\nkind: set_transformer\nmodel: {d_model: 64}\n")
    with pytest.raises(DegustaError, match=message):
        run_train(cfg, overrides)


def test_too_few_queries_or_an_unlogged_monitor_is_refused_before_training(tmp_path):
    root = save_dataset(make_small_dataset(), tmp_path / "data")  # up to 5 objects per arrangement
    base = [f"trainer.run_dir={tmp_path}", "trainer.run_name=tiny"]
    with pytest.raises(DegustaError, match=r"model.n_queries: 4, but participant 'p\d+' trial \d+ .* has 5 objects"):
        run_train(None, ["kind=set_transformer", f"dataset={root}", "model.n_queries=4", *base])
    with pytest.raises(DegustaError, match="trainer.monitor"):
        run_train(None, ["kind=set_transformer", f"dataset={root}", "trainer.monitor=val/rmsd_k3", *base])
    assert not (tmp_path / "tiny").exists()
