"""predictions.jsonl: one line per episode, the same for every method (DESIGN.md section 9)."""

from __future__ import annotations

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
