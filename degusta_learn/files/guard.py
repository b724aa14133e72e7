"""Output guards: no command replaces one of its own inputs or a dataset's files, whatever path it is given.

`refuse_replacing_inputs` is the one guard of every command that writes, for an output file and for an output folder
(every entry it would replace); `check_output_file` runs it for a file output and probes that the file can be
written at all, before any (paid) work. Both raise one `DegustaError` naming the config key or flag and both paths.

Usage:
    from degusta_learn.files.guard import check_output_file, refuse_replacing_inputs
    check_output_file(cfg.out, [("the config file", path)], key="out", datasets=[cfg.dataset])
    refuse_replacing_inputs(out, inputs, kind=EVALUATION, writes=EVALUATION.patterns, datasets=[dataset])
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import write_problem
from degusta_learn.files.jsonio import read_json
from degusta_learn.files.paths import path_problem, refuse_shipped, shown_path, target_problem

if TYPE_CHECKING:
    from degusta_learn.files.folders import OutputKind


DATASET_FILES = ("catalog.json", "tables.json", "arrangements.jsonl", "ratings.jsonl", "meta.json")
"""The files of a dataset folder (scene/dataset.py); with the files its meta.json names and everything in its
subfolders (pictures), an output never replaces them."""


def _real(path: str | os.PathLike) -> str:
    return os.path.realpath(os.path.abspath(path))


def _inside(path: str, folder: str) -> bool:
    return path.startswith(folder.rstrip(os.sep) + os.sep)


def _looks_like_dataset(folder: str) -> bool:
    return all(os.path.isfile(os.path.join(folder, n)) for n in ("catalog.json", "arrangements.jsonl"))


def _dataset_part(root: str, out: str) -> str | None:
    """What of the dataset folder `root` writing `out` (real paths) would replace, or None."""
    if out == root or _inside(root, out):
        return f"holds the dataset folder {root}"
    if not _inside(out, root):
        return None
    rel = Path(os.path.relpath(out, root))
    if len(rel.parts) == 1 and rel.name in DATASET_FILES:
        return f"is the dataset file {rel} of {root}"
    if len(rel.parts) > 1 and os.path.lexists(out):
        return f"is {rel}, a file of the dataset {root}"
    try:
        meta = read_json(Path(root) / "meta.json") if os.path.isfile(os.path.join(root, "meta.json")) else {}
    except DegustaError:
        meta = {}
    if isinstance(meta, dict):
        for key, value in meta.items():
            if isinstance(value, str) and value and _real(os.path.join(root, value)) == out:
                return f"is {rel}, the file the dataset's meta.json names as '{key}'"
    return None


def refuse_replacing_inputs(out: str | os.PathLike, inputs: Iterable[tuple[str, Any]] = (), *, key: str = "out",
                            datasets: Iterable[Any] = (), kind: OutputKind | None = None, writes: Sequence[str] = (),
                            keep: Sequence[str] = ()) -> None:
    """Refuse (DegustaError naming `key` and both paths) an output that would replace or remove an input.

    The one guard of every command that writes (predict, data episodes, evaluate, compare, render, export-sft).
    `inputs` are (what, path) pairs of the files the command reads (its config, episodes, predictions, response
    cache, ...; None skipped). `datasets` are the dataset folders it reads; any dataset folder enclosing an output
    counts too: an output may not be one of its files (DATASET_FILES, a file meta.json names, anything in its
    subfolders), but a new file beside them is fine.

    A file (`kind` None): `out` may be none of the inputs (same path, a link to it, or a folder holding it).
    A folder (`kind`, the `folders.OutputKind` the command writes there): writing replaces every entry named in
    `writes` and moves out every existing entry the command owns (`kind.patterns`) but `keep`; each of them is
    checked as an output file.
    """
    if kind is None:
        _refuse_file(out, inputs, key, datasets)
        return
    problem = path_problem(out)  # before `pathlib` is asked anything about it
    if problem:
        raise DegustaError(f"{key}: {shown_path(out)}: {problem}")
    inputs, datasets = list(inputs), list(datasets)
    target = Path(out)
    names = set(writes)
    if target.is_dir() and not target.is_symlink():
        with contextlib.suppress(OSError):
            names |= {p.name for p in target.iterdir() if kind.owns_name(p.name)}
    for name in sorted(names - set(keep)):
        _refuse_file(target / name, inputs, key, datasets)


def _refuse_file(out: str | os.PathLike, inputs: Iterable[tuple[str, Any]], key: str, datasets: Iterable[Any]) -> None:
    """The guard of one output file (see `refuse_replacing_inputs`)."""
    if str(out).strip() in ("", "."):
        raise DegustaError(f"{key}: the output path is empty; give the path of a file to write")
    refuse_shipped(out, key)
    target = _real(out)
    for what, path in inputs:
        if path is None or not str(path).strip():
            continue
        real = _real(path)
        same = real == target
        if not same and os.path.exists(path) and os.path.exists(out):
            with contextlib.suppress(OSError):
                same = os.path.samefile(path, out)
        if same:
            raise DegustaError(f"{key}: {out} is {what} ({path}); writing there would destroy it, so nothing "
                               "was written: choose another path")
        if _inside(real, target):
            raise DegustaError(f"{key}: {out} holds {what} ({path}); writing there would remove it, so nothing "
                               "was written: choose another path")
    roots = {_real(d) for d in datasets if d is not None and str(d).strip()}
    parent = os.path.dirname(target)
    for _ in range(64):  # every dataset folder above `out`, named or not
        if _looks_like_dataset(parent):
            roots.add(parent)
        if os.path.dirname(parent) == parent:
            break
        parent = os.path.dirname(parent)
    for root in sorted(roots):
        part = _dataset_part(root, target)
        if part:
            raise DegustaError(f"{key}: {out} {part}; writing it would change a dataset, so nothing was written: "
                               "choose a path outside the dataset's files")


def check_output_file(out: str | os.PathLike, inputs: Iterable[tuple[str, Any]] = (), key: str = "out",
                      datasets: Iterable[Any] = ()) -> Path:
    """Before any work: refuse an output file that would replace an input (refuse_replacing_inputs) or
    that cannot be written (a folder, under a file, a folder where files cannot be made); returns the path.
    Probing makes and removes one temporary file in the output's folder when that folder exists."""
    if str(out).strip() in ("", "."):
        raise DegustaError(f"{key}: the output path is empty; give the path of a file to write")
    if isinstance(out, str) and out.endswith(("/", os.sep)):
        raise DegustaError(f"{key}: {out} ends in a slash, a folder; give the path of a file to write (e.g. "
                           f"{out}predictions.jsonl)")
    problem = target_problem(out)
    if problem:
        raise DegustaError(f"{key}: {shown_path(out)}: {problem}")
    path = Path(out)
    _refuse_file(out, inputs, key, datasets)
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if folder == path.parent:
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
            os.close(fd)
            os.unlink(tmp)
        except OSError as e:
            raise DegustaError(f"{key}: {path}: {write_problem(e)}") from None
    elif not os.access(folder, os.W_OK | os.X_OK):
        raise DegustaError(f"{key}: {path}: cannot write here: {folder} is not writable")
    return path
