"""`degusta predict`: the keys every predict config has (`PredictConfig`), the episodes it names, and
`run_predict`, which runs the method and writes predictions.jsonl atomically.

Every prediction it writes records, in its `diagnostics`, the participants it was made on (`split`: the config's
split, or for an episodes file the splits its participants fall in under the config's seed) and the choices it was
made with (`choices`: method, a fingerprint of the resolved config, seed, episodes file, and the checkpoint, model,
adapter and decoding keys the method's config has), so a report can say which split a number is on and what made it
(docs/data.md, "Predictions files").
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from degusta_learn.config import apply_overrides, check_choices, read_yaml, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.files.guard import check_output_file
from degusta_learn.methods.registry import build_config, get_method
from degusta_learn.scene import (
    CONTEXT_LENGTHS,
    Dataset,
    Episode,
    Prediction,
    load_dataset,
    make_episodes,
    read_episodes,
    split_participants,
    write_predictions,
)
from degusta_learn.scene.predictions import CHOICES_KEY, EPISODES_FILE, SPLIT_KEY, split_label


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


CHOICE_KEYS = ("checkpoint", "backend.name", "model.name", "model.adapter", "prompt_style", "modality",
               "decoding.constrained", "decoding.n", "decoding.temperature", "decoding.aggregation")
"""Config keys a prediction's `choices` repeats where the method's config has them (as `--set` would name them):
which weights answered and how their answers were decoded and combined."""


def run_split(cfg: PredictConfig, ds: Dataset, episodes: list[Episode]) -> str:
    """The participants a run predicts, as `diagnostics.split` says it: `cfg.split` for episodes built from it;
    for an episodes file, the splits (under `cfg.seed`) its participants fall in, e.g. "test" or "val+test", or
    "episodes file" when the dataset has too few participants to split."""
    if not cfg.episodes:
        return cfg.split
    try:
        split = split_participants(ds.participants, cfg.seed)
    except DegustaError:  # fewer than 3 participants: no split places them
        return EPISODES_FILE
    mine = {e.participant for e in episodes}
    return split_label(name for name, ids in split.items() if mine.intersection(ids))


_ABSENT = object()


def run_choices(cfg: PredictConfig) -> dict[str, Any]:
    """What a prediction was made with: method, `config_sha256` (of the resolved config without `out`: two runs
    with the same value ran the same config), seed, episodes file, and every `CHOICE_KEYS` key the config has."""
    values = dataclasses.asdict(cfg)
    resolved = json.dumps({k: v for k, v in values.items() if k != "out"}, sort_keys=True, default=str)
    choices = {"method": cfg.method, "config_sha256": hashlib.sha256(resolved.encode()).hexdigest(),
               "seed": cfg.seed, "episodes": cfg.episodes}
    for key in CHOICE_KEYS:
        node: Any = values
        for part in key.split("."):
            node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
        if node is not _ABSENT:
            choices[key] = node if node is None or isinstance(node, (str, int, float, bool)) else str(node)
    return choices


def record_run(predictions: list[Prediction], cfg: PredictConfig, ds: Dataset, episodes: list[Episode]) -> None:
    """Add `split` and `choices` to every prediction's diagnostics (run_split, run_choices)."""
    split, choices = run_split(cfg, ds, episodes), run_choices(cfg)
    for p in predictions:
        p.diagnostics = {**(p.diagnostics or {}), SPLIT_KEY: split, CHOICES_KEY: choices}


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
    from degusta_learn.task.aggregate import failure_summary

    record_run(predictions, cfg, ds, episodes)
    out = Path(cfg.out)
    write_predictions(out, predictions)
    log(f"{cfg.method}: {failure_summary(predictions)}")
    return out
