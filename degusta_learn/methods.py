"""Every prediction method and every trainer, reachable by name from a config.

`METHODS` maps a method name (the `method` key of a predict config) to the `MethodSpec` that runs it;
`TRAINERS` maps a trainer name (the `kind` key of a train config) to a `TrainerSpec`. Entries are
"module:attribute" strings imported on first use, so `degusta predict` with a heuristic baseline never
imports torch. A test keeps both registries complete (every entry imports and has the right type).

A method takes a validated config, the dataset and the episodes, and returns one `Prediction` per
episode; `run_predict` resolves the episodes, calls it and writes predictions.jsonl atomically.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from degusta_learn.config import apply_overrides, from_dict, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.scene import (
    CONTEXT_LENGTHS,
    Dataset,
    Episode,
    Prediction,
    load_dataset,
    make_episodes,
    read_episodes,
    write_predictions,
)


@dataclass
class PredictConfig:
    """Keys every predict config has; a method's own config class adds its keys to these."""

    method: str
    """Method name, one of `METHODS`."""
    dataset: str
    """Dataset folder (see README, data section)."""
    out: str
    """Where predictions.jsonl is written."""
    episodes: str | None = None
    """An episodes.jsonl file; if unset, episodes are built from `context` and `split`."""
    context: int = 4
    """Context length (0, 2 or 4) when `episodes` is unset."""
    split: str = "test"
    """Participant split (train, val, test, all) when `episodes` is unset."""
    seed: int = 0
    """Seed of the split and of any sampling the method does."""

    def __post_init__(self):
        if self.context not in CONTEXT_LENGTHS:
            raise DegustaError(f"context: expected one of {list(CONTEXT_LENGTHS)}, got {self.context}")


@dataclass(frozen=True)
class MethodSpec:
    """How to run one method: its config class and a function (config, dataset, episodes) -> predictions."""

    config_cls: type
    run: Callable[[Any, Dataset, list[Episode]], list[Prediction]]
    description: str = ""


@dataclass(frozen=True)
class TrainerSpec:
    """How to train one model kind: its config class and a function (config) -> output folder."""

    config_cls: type
    run: Callable[[Any], Path]
    description: str = ""


METHODS: dict[str, str] = {
    "random": "degusta_learn.baselines.heuristic:RANDOM",
    "population_mean": "degusta_learn.baselines.heuristic:POPULATION_MEAN",
    "copy_nearest": "degusta_learn.baselines.heuristic:COPY_NEAREST",
    "consensus": "degusta_learn.baselines.heuristic:CONSENSUS",
    "oracle": "degusta_learn.synth.oracle:ORACLE",
    "louma": "degusta_learn.prompting.runner:LOUMA",
    "logma": "degusta_learn.prompting.runner:LOGMA",
    "mouma": "degusta_learn.prompting.runner:MOUMA",
    "mogma": "degusta_learn.prompting.runner:MOGMA",
    "learned": "degusta_learn.baselines.learned:METHOD",
}

TRAINERS: dict[str, str] = {
    "learned": "degusta_learn.baselines.learned:TRAINER",
    "finetune": "degusta_learn.finetune.train:TRAINER",
    "pretrain": "degusta_learn.finetune.pretrain.train:TRAINER",
}


def _load(registry: dict[str, str], name: Any, what: str, key: str):
    if name not in registry:
        raise DegustaError(f"{key}: unknown {what} {name!r} (known: {', '.join(sorted(registry))})")
    module, attr = registry[name].split(":")
    return getattr(importlib.import_module(module), attr)


def get_method(name: str) -> MethodSpec:
    return _load(METHODS, name, "method", "method")


def get_trainer(name: str) -> TrainerSpec:
    return _load(TRAINERS, name, "trainer kind", "kind")


def resolve_episodes(cfg: PredictConfig, ds: Dataset) -> list[Episode]:
    if cfg.episodes:
        return read_episodes(cfg.episodes, ds)
    return make_episodes(ds, cfg.context, cfg.split, cfg.seed)


def build_config(path: str | Path | None, overrides: list[str] | None, key: str, registry_get) -> tuple[Any, Any]:
    """Read YAML + overrides, look up the spec named by `key`, and validate against its config class."""
    raw = apply_overrides(read_yaml(path) if path else {}, overrides)
    where = str(path) if path else "config"
    if key not in raw:
        raise DegustaError(f"{where}: missing required key '{key}'")
    try:
        spec = registry_get(raw[key])
    except DegustaError as e:
        raise DegustaError(f"{where}: {e}") from None
    return spec, from_dict(spec.config_cls, raw, where=where)


def run_predict(path: str | Path | None, overrides: list[str] | None = None, dry_run: bool = False,
                log=print) -> Path | None:
    """`degusta predict`: run the configured method on its episodes and write predictions.jsonl.

    With `dry_run`, a method whose config has a `dry_run` key (the paid API methods) prints its request
    count and cost estimate; any other method makes no paid calls, so it only says what it would do.
    A method returns None for a dry run: nothing is written, None returned. After writing, one line
    summarises failures: failed episodes and, where answers were parsed, failed samples and dropped
    items with their rates. A method that could not produce every prediction (e.g. a zero-shot run
    whose server kept failing) raises DegustaError instead and nothing is written.
    """
    overrides = list(overrides or [])
    if dry_run:
        raw = apply_overrides(read_yaml(path) if path else {}, overrides)
        spec = get_method(raw.get("method"))
        if any(f.name == "dry_run" for f in dataclasses.fields(spec.config_cls)):
            overrides.append("dry_run=true")
        else:
            _, cfg = build_config(path, overrides, "method", get_method)
            n = len(resolve_episodes(cfg, load_dataset(cfg.dataset)))
            log(f"dry run: method {cfg.method!r} calls no paid API; it would predict {n} episodes into {cfg.out}")
            return None
    spec, cfg = build_config(path, overrides, "method", get_method)
    ds = load_dataset(cfg.dataset)
    episodes = resolve_episodes(cfg, ds)
    predictions = spec.run(cfg, ds, episodes)
    if predictions is None:
        return None
    from degusta_learn.prompting.aggregate import failure_summary

    out = Path(cfg.out)
    write_predictions(out, predictions)
    log(f"{cfg.method}: {failure_summary(predictions)}")
    return out


def run_train(path: str | Path | None, overrides: list[str] | None = None) -> Path:
    """`degusta train`: build the configured trainer and run it; returns its output folder."""
    spec, cfg = build_config(path, overrides, "kind", get_trainer)
    return spec.run(cfg)
