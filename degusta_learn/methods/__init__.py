"""Every prediction method and every trainer, reachable by name from a config.

`METHODS` maps a method name (the `method` key of a predict config) to the `MethodSpec` that runs it;
`TRAINERS` maps a trainer name (the `kind` key of a train config) to a `TrainerSpec`. A test keeps both registries
complete (every entry imports and has the right type).

A method takes a validated config, the dataset and the episodes, and returns one `Prediction` per episode;
`run_predict` resolves the episodes, calls it and writes predictions.jsonl atomically. A method of its own: write
its config class (a subclass of `PredictConfig`) and its run function, and add one line to `METHODS`.

Modules: registry.py (`METHODS`, `TRAINERS`, `get_method`, `get_trainer`, `build_config`), predict.py
(`PredictConfig`, `run_predict`), train.py (`run_train`).
"""

from degusta_learn.methods.predict import PredictConfig, resolve_episodes, run_predict
from degusta_learn.methods.registry import (
    METHODS,
    TRAINERS,
    MethodSpec,
    TrainerSpec,
    build_config,
    get_method,
    get_trainer,
)
from degusta_learn.methods.train import run_train

__all__ = ["METHODS", "TRAINERS", "MethodSpec", "PredictConfig", "TrainerSpec", "build_config", "get_method",
           "get_trainer", "resolve_episodes", "run_predict", "run_train"]
