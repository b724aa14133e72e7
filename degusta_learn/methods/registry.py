"""The registries: every prediction method (`METHODS`, the `method` key of a predict config) and every trainer
(`TRAINERS`, the `kind` key of a train config) by name, as "module:attribute" strings imported on first use, so
`degusta predict` with a heuristic baseline never imports torch; `build_config` reads a config against the class
its name selects.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from degusta_learn.config import apply_overrides, from_dict, read_yaml, show_value
from degusta_learn.errors import DegustaError
from degusta_learn.scene import (
    Dataset,
    Episode,
    Prediction,
)


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
    dry_run: Callable[..., None] | None = None
    """(config, log) -> None: print sizes, token budget, steps and memory; load no weights, write nothing. A check
    this machine fails is a `dryrun.fails` line (as `dryrun.dry_run_trainer_lines` makes): `run_train` collects it."""


METHODS: dict[str, str] = {
    "random": "degusta_learn.baselines.heuristic:RANDOM",
    "population_mean": "degusta_learn.baselines.heuristic:POPULATION_MEAN",
    "copy_nearest": "degusta_learn.baselines.heuristic:COPY_NEAREST",
    "copy_context_text": "degusta_learn.baselines.copy_context_text:COPY_CONTEXT_TEXT",
    "consensus": "degusta_learn.baselines.heuristic:CONSENSUS",
    "slot_heuristic": "degusta_learn.baselines.slot_heuristic:SLOT_HEURISTIC",
    "collaborative": "degusta_learn.baselines.collaborative:COLLABORATIVE",
    "oracle": "degusta_learn.synth.oracle:ORACLE",
    "posterior": "degusta_learn.synth.posterior:POSTERIOR",
    "louma": "degusta_learn.prompting.runner:LOUMA",
    "logma": "degusta_learn.prompting.runner:LOGMA",
    "mouma": "degusta_learn.prompting.runner:MOUMA",
    "mogma": "degusta_learn.prompting.runner:MOGMA",
    "text_llm": "degusta_learn.prompting.text_llm:TEXT_LLM",
    "learned": "degusta_learn.baselines.learned:METHOD",
    "set_transformer": "degusta_learn.baselines.set_transformer:METHOD",
}


TRAINERS: dict[str, str] = {
    "learned": "degusta_learn.baselines.learned:TRAINER",
    "set_transformer": "degusta_learn.baselines.set_transformer:TRAINER",
    "finetune": "degusta_learn.finetune.train:TRAINER",
    "pretrain": "degusta_learn.pretrain.train:TRAINER",
}


def _load(registry: dict[str, str], name: Any, what: str, key: str):
    # `name` comes raw from the YAML (before the dataclass check): a list or number must not reach `in`.
    if not isinstance(name, str):
        raise DegustaError(f"{key}: expected the name of a {what} (one of {', '.join(sorted(registry))}), "
                           f"got {show_value(name)}")
    if name not in registry:
        raise DegustaError(f"{key}: unknown {what} {name!r} (known: {', '.join(sorted(registry))})")
    module, attr = registry[name].split(":")
    return getattr(importlib.import_module(module), attr)


def get_method(name: str) -> MethodSpec:
    return _load(METHODS, name, "method", "method")


def get_trainer(name: str) -> TrainerSpec:
    return _load(TRAINERS, name, "trainer kind", "kind")


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
