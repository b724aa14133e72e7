"""`trainer.loggers`: CSV / TensorBoard / W&B / MLflow by config, offline into the run folder, and a missing
optional package as one line naming the key and the pip command."""

import importlib.util
import sys
from pathlib import Path

import pytest

from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.training import TrainerConfig, build_loggers, check_trainer

sys.path.insert(0, str(Path(__file__).parent))
from test_learned_train import tiny_config  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py

MLFLOW = importlib.util.find_spec("mlflow") is not None
WANDB = importlib.util.find_spec("wandb") is not None


def test_default_is_csv_and_tensorboard(tmp_path):
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    cfg = TrainerConfig()
    assert cfg.loggers == ["csv", "tensorboard"] and cfg.tracking_offline
    made = build_loggers(cfg, tmp_path)
    assert [type(m).__mro__[1] for m in made] == [CSVLogger, TensorBoardLogger]  # guarded subclasses (one-line write errors)
    assert build_loggers(from_dict(TrainerConfig, {"loggers": []}), tmp_path) == []


@pytest.mark.parametrize("value, message", [
    (["csv", "comet"], "trainer.loggers: unknown logger 'comet'"),
    (["csv", "csv"], "names a logger twice"),
    ("csv", "loggers: expected a list"),
])
def test_bad_logger_names_are_one_line(value, message):
    with pytest.raises(DegustaError, match=message) as e:
        from_dict(TrainerConfig, {"loggers": value})
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("name, module", [("wandb", "wandb"), ("mlflow", "mlflow")])
def test_missing_package_is_one_line_with_the_pip_command(monkeypatch, name, module):
    monkeypatch.setitem(sys.modules, module, None)  # `import module` now raises ImportError
    cfg = TrainerConfig(loggers=["csv", name], accelerator="cpu", devices=1)
    with pytest.raises(DegustaError) as e:
        check_trainer(cfg)
    text = str(e.value)
    assert "\n" not in text and text.startswith("trainer.loggers:")
    assert f"pip install 'degusta_learn[{name}]'" in text


def test_missing_package_stops_training_before_the_run_folder_exists(monkeypatch, tmp_path, small_dataset_dir):
    from degusta_learn.methods import run_train

    monkeypatch.setitem(sys.modules, "wandb", None)
    cfg = _write(tmp_path, tiny_config(tmp_path, small_dataset_dir, loggers=["csv", "wandb"]))
    with pytest.raises(DegustaError, match=r"trainer.loggers: 'wandb' needs the wandb package"):
        run_train(cfg)
    assert not (tmp_path / "tiny").exists()


def test_online_mlflow_needs_a_tracking_uri(monkeypatch):
    if not MLFLOW:
        monkeypatch.setitem(sys.modules, "mlflow", sys)  # any importable module: only the URI check is tested
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    with pytest.raises(DegustaError, match="MLFLOW_TRACKING_URI"):
        check_trainer(TrainerConfig(loggers=["mlflow"], tracking_offline=False, accelerator="cpu", devices=1))


def _train_tiny(tmp_path, dataset_dir, loggers):
    from degusta_learn.methods import run_train

    run_train(_write(tmp_path, tiny_config(tmp_path, dataset_dir, loggers=loggers, max_steps=2,
                                                val_check_interval=2)))
    return tmp_path / "tiny"


def _write(folder, cfg: dict) -> Path:
    import yaml

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "train.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.skipif(not MLFLOW, reason="mlflow not installed (pip install 'degusta_learn[mlflow]')")
def test_mlflow_offline_logs_into_the_run_folder(tmp_path, small_dataset_dir, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)  # nothing may land in the working directory (./mlruns)
    run = _train_tiny(tmp_path / "ckpt", small_dataset_dir, ["mlflow"])
    assert not (tmp_path / "mlruns").exists()
    assert not (run / "csv").exists() and not (run / "tb").exists()  # only what was asked for
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=(run / "mlruns").resolve().as_uri())
    exp = client.get_experiment_by_name("degusta")
    (found,) = client.search_runs([exp.experiment_id])
    assert found.info.run_name == "tiny"
    assert "train/loss" in found.data.metrics and "val/rmsd" in found.data.metrics
    assert found.data.params.get("kind") == "learned"


@pytest.mark.skipif(not WANDB, reason="wandb not installed (pip install 'degusta_learn[wandb]')")
def test_wandb_offline_logs_into_the_run_folder(tmp_path, small_dataset_dir, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = _train_tiny(tmp_path, small_dataset_dir, ["csv", "wandb"])
    (offline,) = (run / "wandb").glob("offline-run-*")
    assert list(offline.glob("*.wandb")) and (run / "csv").is_dir()
