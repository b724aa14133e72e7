"""What a model folder trained by degusta says about itself: typed, versioned records, one writer, one reader.

- `degusta_finetune.json` (`FinetuneRecord`), written by `degusta train` (kind finetune) into `adapter/`,
  `model/`, `merged/` and the run folder: how the model was prompted in training (method, grid, image
  groups and canvases, image budget, the size the lifted images were rendered at) and what it was trained
  on (the dataset's path and fingerprint, `scene.dataset.dataset_identity`; the participant split seed;
  the train and validation participants; the context lengths).
- `degusta_base.json` (`BaseRecord`), written by the pretrain export (`pretrain/export.py`): the
  architecture, image budget, grid and prompt layout of a base pretrained by degusta, and its training facts.

`write_record` is the only writer and `read_record` the only reader (strict JSON, every key and type
checked; anything wrong is one `DegustaError` naming the file and what to do); `locate_record` finds the
record of a model (adapter folder first, then model folder; a fine-tuning record before a base record).
The `hf` backend prompts the model as the record says and, before predicting, calls `check_prediction`:
a `FinetuneRecord` refuses a run that would score the model on participants it was trained on, or validated on
when validation chose the weights (train/test leakage: another split `seed`, or another `dataset` whose participant
ids overlap; the last weights of a run without early stopping may be predicted on `split: val`), and
both records refuse images rendered at another size than in training (the predict config's `render_size`).

Format versions: a fine-tuning record is format FINETUNE_VERSION; the unversioned file that degusta wrote
before (format 1) is refused, since it lacks what the leakage guard needs: re-running the run's training
command rewrites it. A base record without a version is format 1, the current one (nothing was added).

Example:
    write_record(out, FinetuneRecord(base_model=..., method="mogma", ...))
    record = read_record(locate_record("runs/finetune_tiny_cpu/adapter", "runs/tiny/idefics3"))
    record.check_prediction(dataset_identity(ds), {e.participant for e in episodes}, render_size=224)
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

from degusta_learn.config import bounded, from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_json, read_json
from degusta_learn.render.grid import Grid
from degusta_learn.vlm.prompt_options import PromptOptions

FINETUNE_FILE = "degusta_finetune.json"
BASE_FILE = "degusta_base.json"
FINETUNE_VERSION = 2
"""Format 1: the unversioned dict of earlier versions (no dataset, seed or participants). 2: this record."""
BASE_VERSION = 1


@dataclass(kw_only=True)
class TrainingData:
    """What a fine-tuned model was trained on: the leakage guard compares a prediction run with it."""

    dataset: str
    """The dataset folder as the training config named it."""
    fingerprint: str
    """`scene.dataset.dataset_identity` of that dataset when the record was written."""
    seed: int
    """The participant split seed (`seed` of the training config)."""
    contexts: list[int] = bounded(lo=0, hi=1000)
    """Context lengths of the training episodes (as `--context`: 0 to 1,000)."""
    train_participants: list[str]
    """The participants of the training split (all of them, also when `data.max_train_episodes` subsampled)."""
    val_participants: list[str]
    """The participants of the validation split, which chose the best checkpoint (empty: no validation)."""
    chosen_on_val: bool = True
    """Whether validation on `val_participants` chose these weights (a best folder, or a run that early stopping
    ended; records without the key: true). The last weights of a run without early stopping were not: predicting
    them on `split: val` is accepted, to choose a decoding on the participants validation is for."""

    def check_unseen(self, fingerprint: str, participants: set[str], src: str) -> None:
        """Refuse (one line naming `seed` or `dataset`) predicting on participants the model was trained or
        validated on (`src` names the record in the message)."""
        n = len(participants)
        seen = len(participants & set(self.train_participants))
        val = len(participants & set(self.val_participants))
        if not self.chosen_on_val and fingerprint == self.fingerprint:
            val = 0  # the last weights: validation chose neither them nor when to stop
        if (seen or val) and fingerprint == self.fingerprint:
            what = (f"{seen} of the {n} participants predicted here are in this model's training split" if seen else
                    f"{val} of the {n} participants predicted here are the validation participants of this "
                    "model's training run, which chose these weights (to choose a decoding on them, predict the "
                    "run's last weights, adapter/ or model/, of a run without early stopping)")
            raise DegustaError(f"seed: {what} ({src}: trained with seed {self.seed} on this dataset); predict with "
                               f"seed={self.seed} and split=test, the participants it never saw")
        if seen or val:
            raise DegustaError(
                f"dataset: {seen or val} of the {n} participant ids predicted here are "
                f"{'training' if seen else 'validation'} participants of this model ({src}), trained with seed "
                f"{self.seed} on another dataset ({self.dataset}, fingerprint {self.fingerprint[:12]}; this one's: "
                f"{fingerprint[:12]}; any change to a dataset folder's files changes it), and the same ids may be "
                f"the same people; predict on that dataset with seed={self.seed} and split=test, or give these "
                "participants new ids")


@dataclass(kw_only=True)
class FinetuneRecord:
    """`degusta_finetune.json`: how a fine-tuned model is prompted and what it was trained on."""

    FILE: ClassVar[str] = FINETUNE_FILE
    kind: Literal["degusta_finetune"] = "degusta_finetune"
    version: int = FINETUNE_VERSION
    base_model: str
    """`model.name` of the training config (hub id or folder)."""
    method: str
    """The prompting method trained on (its prompts and answer format)."""
    mode: Literal["lora", "qlora", "full"]
    """`lora.mode`."""
    grid: Grid
    """The grid of grid methods."""
    prompt: PromptOptions
    """Image groups sent and groups composed into one canvas (`data.include`, `data.compose`)."""
    image_size: int | None = bounded(lo=16, hi=4096)
    """The processor's image budget (`model.image_size`, 16 to 4,096; null: the model's default)."""
    render_size: int = bounded(lo=16, hi=4096)
    """Pixels per side the lifted images were drawn at (`data.render_size`)."""
    processor_size: dict[str, Any]
    """The image processor's `size` after the budget was set (for reference)."""
    trained_on: TrainingData
    """Dataset, split seed and participants."""

    def check_prediction(self, fingerprint: str, participants: set[str], render_size: int, where: str = "") -> None:
        """Refuse (one line naming `seed`, `dataset` or `render_size`) predicting on participants this model
        was trained or validated on, or on images rendered at another size than in training."""
        self.trained_on.check_unseen(fingerprint, participants, where or FINETUNE_FILE)
        _check_render_size(self.render_size, render_size, "data.render_size", where)


@dataclass(kw_only=True)
class BaseRecord:
    """`degusta_base.json`: a base pretrained by degusta: how it sees images and how it was trained."""

    FILE: ClassVar[str] = BASE_FILE
    kind: Literal["degusta_base"] = "degusta_base"
    version: int = BASE_VERSION
    architecture: dict[str, Any]
    """`BaseArchitecture` as a dict."""
    parameters: int = bounded(lo=0, hi=10**13)
    image_size: int = bounded(lo=16, hi=4096)
    """The model's image size (the processor's budget)."""
    render_size: int = bounded(lo=16, hi=4096)
    """Pixels per side the images were drawn at in pretraining (= image_size: no resizing)."""
    tokens_per_image: int = bounded(lo=1, hi=2**16)
    """Image tokens an image costs (at most 2^16, as vlm/bounds.py bounds a processor)."""
    grid: Grid
    prompt: PromptOptions
    """The prompt layout of pretraining; the hf backend prompts the base this way zero-shot."""
    catalog: str
    """The dataset (catalog and tables) pretrained on, or the embedded default."""
    training: dict[str, Any]
    """Command, steps, batch size, examples, learning rate, seed, task mix."""
    validation_curve: list[dict[str, Any]]
    """Validation rows {step, val/...} of the training run."""

    def check_prediction(self, fingerprint: str, participants: set[str], render_size: int, where: str = "") -> None:
        """Refuse images rendered at another size than in pretraining (it saw no participant's data)."""
        _check_render_size(self.render_size, render_size, "render_size", where)


def _check_render_size(trained: int, asked: int, key: str, where: str) -> None:
    if asked != trained:
        raise DegustaError(f"render_size: this model was trained on images rendered at {trained} px ({key} in "
                           f"{where or 'its record'}), the predict config renders them at {asked} px; set "
                           f"render_size={trained}")


def write_record(folder: str | os.PathLike, record: FinetuneRecord | BaseRecord) -> Path:
    """Write `record` as `folder/<its file name>` (atomically); returns the path."""
    path = Path(folder) / record.FILE
    atomic_write_json(path, dataclasses.asdict(record))
    return path


def read_record(path: str | os.PathLike) -> FinetuneRecord | BaseRecord:
    """Read `degusta_finetune.json` or `degusta_base.json` (the type follows the file name), checked strictly."""
    path = Path(path)
    cls = {FINETUNE_FILE: FinetuneRecord, BASE_FILE: BaseRecord}.get(path.name)
    if cls is None:
        raise DegustaError(f"{path}: not a record file (expected {FINETUNE_FILE} or {BASE_FILE})")
    data = read_json(path)
    kind = cls.kind
    remedy = (_retrain(path) if cls is FinetuneRecord
              else "export the base again (degusta train --config <its pretrain config>)")
    if not isinstance(data, dict):
        raise DegustaError(f"{path}: not a degusta record (expected a JSON object, got {type(data).__name__}); "
                           f"{remedy}")
    version = data.get("version")
    current = FINETUNE_VERSION if cls is FinetuneRecord else BASE_VERSION
    if cls is FinetuneRecord and "version" not in data and "kind" not in data and "method" in data:
        raise DegustaError(f"{path}: written by an older degusta (format 1: no dataset fingerprint, split seed or "
                           f"trained participants, which the train/test leakage guard needs); {remedy}")
    if data.get("kind") != kind:
        raise DegustaError(f"{path}: not a record degusta wrote (\"kind\" is {data.get('kind')!r}, expected "
                           f"{kind!r}); {remedy}")
    if cls is BaseRecord and "version" not in data:
        data = {**data, "version": 1}  # format 1 was written without a version
        version = 1
    if isinstance(version, bool) or not isinstance(version, int):
        raise DegustaError(f"{path}: field 'version': expected an integer, got {version!r}"[:300] + f"; {remedy}")
    if version > current:
        raise DegustaError(f"{path}: written by a newer degusta (format {version}; this one reads format "
                           f"{current}): upgrade degusta_learn")
    if version < current:
        raise DegustaError(f"{path}: written by an older degusta (format {version}; this one reads format "
                           f"{current}); {remedy}")
    try:
        record = from_dict(cls, data, where=str(path), probe_paths=False)  # paths as they were then
    except DegustaError as e:
        raise DegustaError(f"{e}; {remedy}") from None
    free = {"architecture": record.architecture} if cls is BaseRecord else {"processor_size": record.processor_size}
    for field, value in free.items():  # free-form numbers: finite, and within 32 bits (sizes, counts, pixels)
        _check_free_numbers(value, field, path, remedy)
    if cls is BaseRecord:
        _check_architecture(record.architecture, path, remedy)
    return record


def _check_architecture(arch: dict, path: Path, remedy: str) -> None:
    """The architecture's sizes within the bounds of the pretrain config that made it (`BaseArchitecture`)."""
    from degusta_learn.config import check_bounds
    from degusta_learn.vlm.random_models.fastvlm import BaseArchitecture

    for f in dataclasses.fields(BaseArchitecture):
        bounds = f.metadata.get("bounds")
        if bounds is not None and f.name in arch:
            try:
                check_bounds(arch[f.name], bounds, str(path), f"architecture.{f.name}")
            except DegustaError as e:
                raise DegustaError(f"{e}; {remedy}") from None


MAX_FREE_NUMBER = 2**31
"""Largest number in a record's free-form fields (`architecture`, `processor_size`)."""


def _check_free_numbers(value: Any, field: str, path: Path, remedy: str) -> None:
    import math

    stack = [(field, value)]
    while stack:
        name, v = stack.pop()
        if isinstance(v, dict):
            stack.extend((f"{name}.{k}", x) for k, x in list(v.items())[:10_000])
        elif isinstance(v, list):
            stack.extend((f"{name}[{i}]", x) for i, x in enumerate(v[:10_000]))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) and not (
                math.isfinite(v) and abs(v) <= MAX_FREE_NUMBER):
            shown = f"{v:,}" if isinstance(v, float) or v.bit_length() < 100 else f"an integer of {len(str(v))} digits"
            raise DegustaError(f"{path}: {name}: expected a number of at most {MAX_FREE_NUMBER:,}, got {shown}; "
                               f"{remedy}")


def _retrain(path: Path) -> str:
    """What to do about an unreadable fine-tuning record at `path` (in `<run>/adapter/` or `<run>/`)."""
    run = next((d for d in (path.parent, path.parent.parent) if (d / "config.yaml").is_file()), None)
    config = run / "config.yaml" if run is not None else "<run folder>/config.yaml"
    return (f"re-run its training command (degusta train --config {config}: a finished run resumes at its last "
            "step, trains no further and rewrites this file), or train again")


SELECTION_FILE = "degusta_selection.json"
"""In a best folder (`finetune/export.py`): the validation that chose its weights: monitor, mode, score, step, epoch,
checkpoint, split ("val"), val_episodes, val_participants and `decoding` (the fine-tune's `decoding:` section, in
predict's spelling: what the validation answers were generated with)."""
ANSWER_DECODING_KEYS = ("constrained", "on_repeat", "max_new_tokens", "n", "aggregation", "temperature")
"""The `decoding:` keys that change the scored answers (`report_unconstrained` only adds free-decoding counts)."""


def selection_decoding(folder: str | os.PathLike | None):
    """The `DecodingSettings` the validation that chose the weights in `folder` decoded with (its
    `degusta_selection.json`), or None: no folder, no selection file (the last weights), or one written before the
    decoding was recorded. A file that is there but unreadable is one `DegustaError` naming it."""
    from degusta_learn.vlm.settings import DecodingSettings

    path = Path(folder) / SELECTION_FILE if folder else None
    if path is None or not path.is_file():
        return None
    data = read_json(path)
    if not isinstance(data, dict) or "decoding" not in data:
        return None
    return from_dict(DecodingSettings, data["decoding"], where=str(path), prefix="decoding.").resolved(local=True)


def decoding_differences(recorded, asked) -> list[str]:
    """The `ANSWER_DECODING_KEYS` on which two `DecodingSettings` differ (`temperature` compared as sampled: null
    is 0 at n = 1)."""
    def value(d, key):
        return d.sampling_temperature if key == "temperature" else getattr(d, key)

    return [k for k in ANSWER_DECODING_KEYS if value(recorded, k) != value(asked, k)]


def locate_record(*folders: str | os.PathLike | None) -> Path | None:
    """The record file of a model given as (adapter folder, model folder): the first folder's fine-tuning
    record, else the next one's, else a base record likewise; None when there is none (any other model)."""
    for name in (FINETUNE_FILE, BASE_FILE):
        for folder in folders:
            if folder and os.path.lexists(Path(folder) / name):
                return Path(folder) / name
    return None
