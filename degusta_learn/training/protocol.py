"""The evaluation protocol where code can hold it: every choice is made on the validation participants, and the
test participants are looked at once per result, after every choice is frozen (docs/metrics.md, "Protocol:
validation for choices, test once").

What chooses, and where it is held to the validation participants:

- best.ckpt, best_adapter/ and early stopping (`trainer.monitor`): `TrainerConfig` refuses a monitor that names
  the test split (`check_monitor`), and the data modules of the learned model and of fine-tuning build their
  validation episodes only through `selection_episodes`, which has no split argument: the validation loader can
  hold no other participants;
- a decoding or an aggregation chosen from stored answers (`benchmarks/choose_decoding.py`): `refuse_test_split`
  on its `--split` unless it only scores the way chosen on validation.

Example:
    refuse_test_split(args.split, "--split", "choosing a decoding")   # DegustaError for "test" or "all"
    val = selection_episodes(ds, contexts=[0, 2, 4], seed=0)
"""

from __future__ import annotations

from collections.abc import Iterable

from degusta_learn.errors import DegustaError

SELECTION_SPLIT = "val"
"""The participant split every choice is made on."""

HOLDS_TEST = ("test", "all")
"""Splits that hold test participants (`all` is every participant)."""

PROTOCOL_DOC = 'docs/metrics.md, "Protocol: validation for choices, test once"'

WHY = ("choices are made on the validation participants (val); the test split is for the final number, "
       "looked at once after every choice is frozen")
"""Why a tool that chooses refuses the test split, as its one-line error says it."""


def refuse_test_split(split: str, key: str, what: str) -> None:
    """Raise DegustaError when `split` holds test participants and `what` (e.g. "choosing a decoding") would
    choose on them; `key` names the option or config key that gave `split`."""
    if split in HOLDS_TEST:
        raise DegustaError(f"{key}: {split!r} refused for {what}: {WHY} ({PROTOCOL_DOC})")


def check_monitor(monitor: str | None, key: str = "trainer.monitor") -> None:
    """Refuse a checkpoint / early-stopping monitor that names a test metric (`test/...`, `test_...`).

    Every trainer logs its selection metrics from the validation participants under `val/`; a `test/` name would
    select on the participants the final number is reported on."""
    if monitor is None:
        return
    head = monitor.strip().split("/", 1)[0].split("_", 1)[0].lower()
    if head == "test":
        raise DegustaError(f"{key}: {monitor[:60]!r} refused: the monitor picks best.ckpt and drives early stopping, "
                           f"and {WHY}; monitor a validation metric such as val/set_rmsd ({PROTOCOL_DOC})")


def selection_episodes(ds, contexts: Iterable[int], seed: int) -> list:
    """The episodes validation (and so best.ckpt and early stopping) sees: every context length of `contexts` on
    the validation participants of the seeded split (`scene.make_episodes(ds, k, "val", seed)`, in that order)."""
    from degusta_learn.scene import make_episodes

    return [e for k in contexts for e in make_episodes(ds, k, SELECTION_SPLIT, seed)]
