"""predictions.jsonl: one line per episode, the same for every method (DESIGN.md section 9).

`degusta predict` records in every prediction's `diagnostics` which participants it was made on (`split`) and the
choices it was made with (`choices`: method, config fingerprint, checkpoint, adapter, decoding); docs/data.md,
"Predictions files". `recorded_split` reads the split back for reports; a file written before degusta recorded it
reads as "not recorded".
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_jsonl, read_jsonl
from degusta_learn.scene.catalog import Catalog
from degusta_learn.scene.dataset import parse_placements
from degusta_learn.scene.types import Episode, Prediction
from degusta_learn.scene.validate import Where, get, require_mapping


def write_predictions(path: str | Path, predictions: list[Prediction]) -> None:
    atomic_write_jsonl(path, (p.to_json() for p in predictions))


def read_predictions(path: str | Path, catalog: Catalog, episodes: dict[str, Episode] | None = None) -> list[Prediction]:
    """Read and validate predictions; unknown objects or (with `episodes`) unknown episodes are errors.

    Placements of a failed prediction are still validated (they are usually empty).
    """
    out, seen = [], set()
    for lineno, entry in read_jsonl(path):
        w = Where(path, line=lineno)
        require_mapping(entry, w)
        eid = get(entry, "episode", "str", w)
        if eid in seen:
            raise w.fail("episode", f"episode {eid!r} predicted twice")
        seen.add(eid)
        if episodes is not None and eid not in episodes:
            raise w.fail("episode", f"unknown episode {eid!r} (not in the episode set)")
        failed = entry.get("failed", False)
        if not isinstance(failed, bool):
            raise w.fail("failed", f"expected true or false, got {failed!r}")
        diagnostics = entry.get("diagnostics") or {}
        if not isinstance(diagnostics, dict):
            raise w.fail("diagnostics", "expected a JSON object")
        out.append(Prediction(
            episode=eid, participant=get(entry, "participant", "id", w), target=get(entry, "target", "int", w),
            method=get(entry, "method", "str", w),
            placements=parse_placements(get(entry, "placements", "list", w), catalog, w),
            failed=failed, diagnostics=diagnostics))
    if not out:
        raise DegustaError(f"{path}: no predictions")
    return out


SPLIT_KEY = "split"
"""The `diagnostics` key of the participants a prediction was made on."""

CHOICES_KEY = "choices"
"""The `diagnostics` key of the choices a prediction was made with (method, config fingerprint, ...)."""

EPISODES_FILE = "episodes file"
"""The split of predictions on an episodes file whose participants no split of the dataset places (too few
participants to split)."""

NOT_RECORDED = "not recorded"
"""What `recorded_split` says of a file written before degusta recorded the split."""

_SPLIT_NAMES = ("train", "val", "test")
_LABEL = re.compile(r"all|episodes file|(?:train|val|test)(?:\+(?:train|val|test))*")


def split_label(splits: Iterable[str]) -> str:
    """The `diagnostics.split` of predictions on participants of `splits` (any of train, val, test): one name, or
    several joined by '+' in split order ("val+test"); "episodes file" when none."""
    given = set(splits)
    return "+".join(s for s in _SPLIT_NAMES if s in given) or EPISODES_FILE


def recorded_split(predictions: Iterable) -> str:
    """The split a set of predictions records: its one `diagnostics.split` (train, val, test, all, a '+'-joined
    mix, "episodes file"), "mixed: a, b" when its records disagree, "not recorded" for a file written before
    degusta recorded it. A value that is no split label counts as not recorded (the field is never an error)."""
    labels = set()
    for p in predictions:
        value = (p.diagnostics or {}).get(SPLIT_KEY) if isinstance(p.diagnostics, dict) else None
        labels.add(value if isinstance(value, str) and _LABEL.fullmatch(value) else NOT_RECORDED)
    if len(labels) == 1:
        return labels.pop()
    return "mixed: " + ", ".join(sorted(labels, key=_split_order)) if labels else NOT_RECORDED


def _split_order(label: str) -> tuple:
    """Sort key of split labels: train, val, test first (in that order), then all, episodes file, not recorded."""
    order = (*_SPLIT_NAMES, "all", EPISODES_FILE, NOT_RECORDED)
    return tuple(order.index(part) for part in label.split("+"))


def holds_test(label: str) -> bool:
    """Whether a `recorded_split` label says that some prediction is on a test participant."""
    return bool(re.search(r"\b(test|all)\b", label))
