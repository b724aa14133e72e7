"""The set-prediction transformer (DETR-style): an encoder over every context object, N learned queries, trained end
to end with a Hungarian matching loss; no slot alignment (docs/set_transformer.md).

Modules: encoding.py (an episode as tokens and labels), model.py (`ModelConfig`, `SetTransformer`: architecture and
decoding), matching.py (the matching cost, the assignment and the loss), data.py (the DataModule), module.py (the
LightningModule, validation by `degusta_learn.metrics`), train.py (config, `build`, dry run, `train`), predict.py
(checkpoint loading, `degusta predict`).

Usage:
    degusta train --config configs/set_transformer_cpu.yaml              # -> runs/set_transformer_cpu/
    degusta predict --config configs/set_transformer_predict.yaml        # -> predictions.jsonl

Registered as TRAINERS["set_transformer"] (`TRAINER`) and METHODS["set_transformer"] (`METHOD`).
"""

from degusta_learn.baselines.set_transformer.predict import (
    SetTransformerPredictConfig,
    load_model,
    predict_episodes,
    run,
)
from degusta_learn.baselines.set_transformer.train import SetTransformerTrainConfig, build, dry_run, train
from degusta_learn.methods import MethodSpec, TrainerSpec

TRAINER = TrainerSpec(SetTransformerTrainConfig, train,
                      "set transformer: context objects -> N queries, Hungarian matching loss (PyTorch + Lightning)",
                      dry_run=dry_run)
METHOD = MethodSpec(SetTransformerPredictConfig, run, "a trained set-prediction transformer (config key: checkpoint)")

__all__ = ["METHOD", "TRAINER", "SetTransformerPredictConfig", "SetTransformerTrainConfig", "build", "dry_run",
           "load_model", "predict_episodes", "run", "train"]
