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
from typing import TYPE_CHECKING, Any, Literal

from degusta_learn.config import _show, apply_overrides, check_choices, from_dict, read_yaml, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.fileio import check_output_file
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

if TYPE_CHECKING:
    from degusta_learn.dryrun import DryRunReport


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
    context: int | None = 4
    """Context length (0, 2 or 4). With `episodes`, every episode of the file is run as it is, and the file must
    hold episodes of this length (a mixed file, e.g. quickstart's 0/2/4 set, among others; null: any file)."""
    split: Literal["train", "val", "test", "all"] = "test"
    """Participant split (train, val, test, all) when `episodes` is unset."""
    seed: int = seed_field(0)
    """Seed of the split and of any sampling the method does (0 .. 2**32 - 1)."""

    def __post_init__(self):
        check_choices(self, "")  # split, and a subclass's choices (e.g. aggregation): a config built in Python too
        if self.context is None and not self.episodes:
            raise DegustaError("context: null is only allowed with an episodes file; expected one of "
                               f"{list(CONTEXT_LENGTHS)}")
        if self.context is not None and self.context not in CONTEXT_LENGTHS:
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
    dry_run: Callable[..., None] | None = None
    """(config, log) -> None: print sizes, token budget, steps and memory; load no weights, write nothing. A check
    this machine fails is a `dryrun.fails` line (as `dryrun.dry_run_trainer_lines` makes): `run_train` collects it."""


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
    # `name` comes raw from the YAML (before the dataclass check): a list or number must not reach `in`.
    if not isinstance(name, str):
        raise DegustaError(f"{key}: expected the name of a {what} (one of {', '.join(sorted(registry))}), "
                           f"got {_show(name)}")
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
        episodes = read_episodes(cfg.episodes, ds)
        lengths = sorted({len(e.context) for e in episodes})
        # A file of one length must match `context` (else `context` would be silently ignored); a mixed
        # file (e.g. quickstart's 0/2/4 set) must at least contain it. `context: null` takes any file.
        if cfg.context is not None and cfg.context not in lengths:
            raise DegustaError(
                f"context: {cfg.context} contradicts episodes: {cfg.episodes} holds episodes of context length "
                f"{', '.join(map(str, lengths))}; set context to {lengths[0] if len(lengths) == 1 else 'null'} "
                "or unset episodes")
        return episodes
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


_NOT_PATHS = ("out", "method", "split", "dataset")


def _config_files(cfg: Any) -> list[tuple[str, str]]:
    """(what, path) of every existing file a config value names (episodes, checkpoint, cache, ...)."""
    found: list[tuple[str, str]] = []

    def walk(value: Any, key: str) -> None:
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            for f in dataclasses.fields(value):
                walk(getattr(value, f.name), f"{key}.{f.name}" if key else f.name)
        elif isinstance(value, dict):
            for k, v in value.items():
                walk(v, f"{key}.{k}" if key else str(k))
        elif isinstance(value, (list, tuple)):
            for i, v in enumerate(value):
                walk(v, f"{key}[{i}]")
        elif isinstance(value, str) and key not in _NOT_PATHS and value.strip() and len(value) < 4096:
            try:
                if Path(value).is_file():
                    found.append((f"the file of config key '{key}'", value))
            except (OSError, ValueError):
                pass

    walk(cfg, "")
    return found


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
    # refuse an `out` that would replace an input or cannot be written, before any (paid) work
    check_output_file(cfg.out, [("the config file", path), *_config_files(cfg)], key="out", datasets=[cfg.dataset])
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


def run_train(path: str | Path | None, overrides: list[str] | None = None, dry_run: bool = False,
              log=print) -> Path | DryRunReport:
    """`degusta train`: build the configured trainer and run it; returns its output folder.

    With `dry_run`, the trainer kind's `dry_run` prints the model size, trainable parameters, the
    per-example budget against its limit, steps per epoch and a predicted memory, loading no weights and
    writing nothing; it refuses (DegustaError naming the key) a config whose examples cannot fit. Returns
    the `dryrun.DryRunReport` of the checks that FAIL on this machine (empty `failures`: none; the CLI
    then exits 3).
    """
    spec, cfg = build_config(path, overrides, "kind", get_trainer)
    if dry_run:
        from degusta_learn.dryrun import recording

        if spec.dry_run is None:
            raise DegustaError(f"kind: {cfg.kind!r} has no dry run")
        with recording() as report:  # every kind's FAILS line (dryrun.fails) lands here
            spec.dry_run(cfg, log=log)
        return report
    return spec.run(cfg)
