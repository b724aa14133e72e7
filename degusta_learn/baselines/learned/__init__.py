"""Learned baseline: the slot model. The context arrangements are aligned into slots (slots.py); a
transformer over the slots decides which the target gets, with which object, where and in which order
(see slot_model.py for the architecture and why).

Usage:
    degusta train --config configs/learned_cpu.yaml              # -> runs/learned_cpu/
    degusta predict --config configs/learned_predict.yaml        # -> predictions.jsonl

Registered as TRAINERS["learned"] (`TRAINER`) and METHODS["learned"] (`METHOD`).
"""

from degusta_learn.baselines.learned.predict import LearnedPredictConfig, load_model, predict_episodes, run
from degusta_learn.baselines.learned.train import LearnedTrainConfig, build, dry_run, train
from degusta_learn.methods import MethodSpec, TrainerSpec

TRAINER = TrainerSpec(LearnedTrainConfig, train, "slot model: a transformer over the participant's aligned context objects (PyTorch + Lightning)",
                      dry_run=dry_run)
METHOD = MethodSpec(LearnedPredictConfig, run, "a trained learned arrangement model (config key: checkpoint)")

__all__ = ["METHOD", "TRAINER", "LearnedPredictConfig", "LearnedTrainConfig", "build", "load_model",
           "predict_episodes", "run", "train"]
