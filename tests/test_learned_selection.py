"""The learned model picks best.ckpt by the set-aware score: the shipped configs monitor `val/set_rmsd`, the module
logs it (and per context length), and the logged value is the mean of `metrics.score_many`'s set RMSD over the
validation episodes decoded with the same weights."""

import csv
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from degusta_learn.baselines.learned import LearnedTrainConfig, load_model, predict_episodes, train
from degusta_learn.baselines.learned.module import monitor_keys
from degusta_learn.config import from_dict, read_yaml
from degusta_learn.metrics import score_many
from degusta_learn.training.protocol import selection_episodes

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py
CONFIGS = Path(__file__).resolve().parent.parent / "configs"


@pytest.mark.parametrize("name", ["learned_cpu.yaml", "learned_gpu.yaml"])
def test_shipped_learned_configs_monitor_the_set_aware_score(name):
    cfg = from_dict(LearnedTrainConfig, read_yaml(CONFIGS / name), where=name)
    assert cfg.trainer.monitor == "val/set_rmsd" and cfg.trainer.monitor_mode == "min"
    assert cfg.trainer.monitor in monitor_keys(cfg.data.val_contexts)


def test_the_logged_set_rmsd_is_the_metrics_set_rmsd_of_the_decoded_validation(tmp_path):
    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import make_small_dataset

    ds = make_small_dataset(n_participants=12)
    torch.set_num_threads(1)
    cfg = {"kind": "learned", "num_threads": 1, "dataset": "unused",
           "data": {"batch_size": 8, "repeats": 1, "val_contexts": [2, 4]},
           "model": {"d_model": 16, "n_layers": 1, "n_heads": 2, "d_ff": 32, "max_objects": 8},
           "trainer": {"run_dir": str(tmp_path), "run_name": "tiny", "max_epochs": -1, "max_steps": 2,
                       "val_check_interval": 2, "accelerator": "cpu", "devices": 1, "progress_bar": False,
                       "log_every_n_steps": 1, "monitor": "val/set_rmsd"}}
    run = train(from_dict(LearnedTrainConfig, cfg), ds)
    with open(run / "csv/version_0/metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("val/set_rmsd")]
    assert {"val/set_rmsd", "val/set_rmsd_k2", "val/set_rmsd_k4"} <= set(rows[-1])
    assert (run / "best.ckpt").is_file()

    model, hp = load_model(run / "last.ckpt")  # the weights of that last (only) validation
    episodes = selection_episodes(ds, [2, 4], 0)
    with torch.no_grad():
        preds = predict_episodes(model, ds, episodes, hp["population"], hp["min_objects"])
    scores = score_many(ds.catalog, [ds.arrangement(e.participant, e.target) for e in episodes], preds)
    for key, keep in (("val/set_rmsd", lambda e: True), ("val/set_rmsd_k4", lambda e: len(e.context) == 4)):
        expected = np.mean([s.set_rmsd for s, e in zip(scores, episodes) if keep(e)])
        assert float(rows[-1][key]) == pytest.approx(expected, abs=1e-6), key
