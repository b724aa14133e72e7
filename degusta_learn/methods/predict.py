"""`degusta predict`: the keys every predict config has (`PredictConfig`), the episodes it names, and
`run_predict`, which runs the method and writes predictions.jsonl atomically.
"""

from __future__ import annotations

import dataclasses
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

    out = Path(cfg.out)
    write_predictions(out, predictions)
    log(f"{cfg.method}: {failure_summary(predictions)}")
    return out
