"""Training the learned model from config (Lightning), its checkpoints, `degusta predict`, and bad input."""

import numpy as np
import pytest
import torch

from degusta_learn.baselines.learned import LearnedTrainConfig, load_model, predict_episodes, train
from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict, run_train
from degusta_learn.scene import (
    CatalogObject,
    Dataset,
    load_dataset,
    make_episodes,
    read_predictions,
    save_dataset,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


def tiny_config(tmp_path, dataset="unused", **trainer) -> dict:
    return {"kind": "learned", "num_threads": 1,
            "dataset": str(dataset), "data": {"batch_size": 8, "repeats": 1},
            "model": {"d_model": 16, "n_layers": 1, "n_heads": 2, "d_ff": 32, "max_objects": 8},
            "trainer": {"run_dir": str(tmp_path), "run_name": "tiny", "max_epochs": -1, "max_steps": 3,
                        "accelerator": "cpu", "devices": 1, "progress_bar": False, "log_every_n_steps": 1,
                        **trainer}}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One tiny run (3 steps, validated twice) shared by the checkpoint tests."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import make_small_dataset

    tmp = tmp_path_factory.mktemp("learned")
    ds = make_small_dataset()
    root = save_dataset(ds, tmp / "data")
    torch.set_num_threads(1)
    run = train(from_dict(LearnedTrainConfig, tiny_config(tmp, root, val_check_interval=2)), ds)
    return run, root, ds


def test_run_folder_has_config_checkpoints_and_metric_logs(trained):
    run, _, _ = trained
    for name in ("config.yaml", "last.ckpt", "best.ckpt"):
        assert (run / name).is_file(), name
    header = (run / "csv/version_0/metrics.csv").read_text().splitlines()[0].split(",")
    assert {"val/rmsd", "val/object_accuracy", "val/rmsd_unregistered", "val/rmsd_k4", "train/loss"} <= set(header)
    ckpt = torch.load(run / "last.ckpt", weights_only=True)  # weights-only loading works
    assert ckpt["hyper_parameters"]["kind"] == "learned" and ckpt["global_step"] == 3


def test_checkpoint_round_trip_gives_identical_predictions(trained, tmp_path):
    run, root, _ = trained
    ds = load_dataset(root)  # the file rounds positions: predict from what `degusta predict` reads
    model, hp = load_model(run / "last.ckpt")
    again, _ = load_model(run)  # a run folder -> best.ckpt
    episodes = make_episodes(ds, 2, "test")
    a = predict_episodes(model, ds, episodes, hp["population"], hp["min_objects"])
    b = predict_episodes(load_model(run / "last.ckpt")[0], ds, episodes, hp["population"], hp["min_objects"])
    assert [p.to_json() for p in a] == [p.to_json() for p in b]
    assert all(len(p.placements) >= 3 for p in a) and again.cfg == model.cfg
    # through the registry, as `degusta predict` runs it (same thread count: float sums depend on it)
    out = run_predict(None, ["method=learned", f"dataset={root}", f"out={tmp_path / 'p.jsonl'}", "context=2",
                             f"checkpoint={run / 'last.ckpt'}", "num_threads=1"])
    preds = read_predictions(out, ds.catalog)
    assert [p.to_json()["placements"] for p in preds] == [p.to_json()["placements"] for p in a]
    for p in preds:  # on the target table's surface
        table = ds.tables[ds.arrangement(p.participant, p.target).table]
        xy = np.array([[q.x, q.y] for q in p.placements])
        assert table.contains(xy[:, 0], xy[:, 1]).all()


def test_resume_continues_the_step_count(trained, tmp_path):
    run, root, ds = trained
    import shutil

    copy = shutil.copytree(run, tmp_path / "tiny")
    cfg = from_dict(LearnedTrainConfig, tiny_config(tmp_path, root, max_steps=5, val_check_interval=2))
    assert train(cfg, ds) == copy
    assert torch.load(copy / "last.ckpt", weights_only=True)["global_step"] == 5
    assert (copy / "csv/version_1").is_dir()  # the resumed part logs beside the first, nothing lost


def test_checkpoint_of_another_kind_or_no_checkpoint_is_refused(trained, tmp_path):
    run, _, _ = trained
    ckpt = torch.load(run / "last.ckpt", weights_only=True)
    ckpt["hyper_parameters"]["kind"] = "finetune"
    torch.save(ckpt, tmp_path / "other.ckpt")
    with pytest.raises(DegustaError, match="kind 'finetune', not a 'learned'"):
        load_model(tmp_path / "other.ckpt")
    ckpt["hyper_parameters"].update(kind="learned", format=1)  # the autoregressive model of an older version
    torch.save(ckpt, tmp_path / "old.ckpt")
    with pytest.raises(DegustaError, match="format 1; this version reads format 3.*retrain"):
        load_model(tmp_path / "old.ckpt")
    (tmp_path / "junk.ckpt").write_text("not a checkpoint")
    with pytest.raises(DegustaError, match="junk.ckpt: not a loadable"):
        load_model(tmp_path / "junk.ckpt")
    with pytest.raises(DegustaError, match="no best.ckpt or last.ckpt"):
        load_model(tmp_path)


@pytest.mark.parametrize("sets", [["split=train"], ["split=val"], ["seed=1", "split=all"]])
def test_predicting_participants_it_trained_on_is_refused(trained, tmp_path, sets):
    """A predict seed other than the training seed ran silently on test participants it had trained on."""
    run, root, _ = trained
    with pytest.raises(DegustaError, match=r"^(seed|dataset): \d+ of the \d+ participant"):
        run_predict(None, ["method=learned", f"dataset={root}", f"out={tmp_path / 'p.jsonl'}", "context=2",
                           f"checkpoint={run}", *sets])
    assert not (tmp_path / "p.jsonl").exists()


def test_other_catalog_is_refused(trained, tmp_path):
    run, root, ds = trained
    objects = list(ds.catalog)
    objects[0] = CatalogObject(**{**objects[0].__dict__, "color1": "green"})
    other = Dataset(type(ds.catalog)(tuple(objects)), ds.tables, ds.arrangements, meta=ds.meta)
    other_root = save_dataset(other, tmp_path / "other")
    with pytest.raises(DegustaError, match="another catalog"):
        run_predict(None, ["method=learned", f"dataset={other_root}", f"out={tmp_path / 'p.jsonl'}",
                           f"checkpoint={run}"])
    assert not (tmp_path / "p.jsonl").exists()


@pytest.mark.parametrize("override, message", [
    ("model.d_modle=8", "unknown key 'model.d_modle'"),
    ("model.d_model=big", "model.d_model: expected int"),
    ("data.contexts=[3]", "data.contexts"),
    ("model.n_heads=3", "model.n_heads: 3 does not divide"),
    ("kind=finetune_typo", "unknown trainer kind"),
    # old spellings (one spelling per concept across config kinds) name the key that replaced them
    ("data.dataset=x", "'data.dataset' is now 'dataset'"),
    ("data.split_seed=1", "'data.split_seed' is now 'seed'"),
    ("data.context_lengths=[2]", "'data.context_lengths' is now 'data.contexts'"),
    ("data.val_context_lengths=[2]", "'data.val_context_lengths' is now 'data.val_contexts'"),
])
def test_bad_config_names_the_key(tmp_path, override, message):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("# degusta train --config c.yaml\nkind: learned\n")
    with pytest.raises(DegustaError, match=message):
        run_train(cfg, [override])


def test_too_few_participants_is_a_clear_error(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import make_small_dataset

    root = save_dataset(make_small_dataset(n_participants=2), tmp_path / "two")
    with pytest.raises(DegustaError, match="2 participant.*too few for a train/val/test split"):
        run_train(None, [f"{k}={v}" for k, v in {"kind": "learned", "dataset": root,
                                                  "trainer.run_dir": tmp_path}.items()])
    assert not (tmp_path / "learned").exists()
