"""Degenerate answers, defined by what an answer does: too few objects, padding, one answer for everyone.

A score can be won by a shortcut instead of a better arrangement. Three shortcuts show in the answers
themselves, whatever they score, and each makes a method *degenerate* (ranked after every other method,
docs/metrics.md "Degenerate answers and shortcuts"). Each is counted over the method's scored episodes
(prediction not failed, ground truth not empty); a reason applies when its share is strictly above
`DEGENERATE_FRACTION` (more than half):

- **"too few"**: the answer has at most half the ground truth's objects (`n_pred <= SHORT_RATIO * n_gt`),
  or, the older rule kept beside it, it matches at most 2 objects of a ground truth of 3 or more
  (`set_score.few_matched_fraction`). Kabsch RMSD and acc@t are ~0 on such answers by construction.
- **"padding"**: the answer has at least twice the ground truth's objects, or at least `PAD_MARGIN` more
  (`n_pred >= PAD_RATIO * n_gt` or `n_pred >= n_gt + PAD_MARGIN`). Object accuracy (the recall) only rises
  with more guesses.
- **"constant"**: one answer (`answer_key`: the same object ids at the same positions rounded to
  `KEY_DECIMALS`) is given on more than half of the scored episodes, and those episodes belong to at
  least 2 participants: an answer that does not depend on the person.

The thresholds are set so that no honest method of the default data reaches them, at any context
length (the measured shares: benchmarks/RESULTS.md, "Context 0, 2 and 4, the shortcuts and the templates, on the
plausible default"; the highest, 0.40, is the set transformer's one answer on two of the five tables at context 0).

Usage:
    from degusta_learn.metrics import answer_key, degenerate_answers
    key = answer_key([p.object for p in placements], [(p.x, p.y) for p in placements])
    verdict = degenerate_answers(n_gt, n_pred, failed, answer_keys=keys, participants=people)
    verdict.degenerate, verdict.reasons            # True, ("too few",)
"""

from __future__ import annotations

import hashlib
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.metrics.set_score import DEGENERATE_FRACTION, few_matched_fraction

SHORT_RATIO = 0.5
"""An answer is short when it has at most this fraction of the ground truth's objects."""
PAD_RATIO = 2.0
"""An answer is padded when it has at least this many times the ground truth's objects ..."""
PAD_MARGIN = 4
"""... or at least this many objects more than the ground truth."""
KEY_DECIMALS = 2
"""Positions are rounded to this many decimals in `answer_key` (0.01 of the image: the same answer)."""
MIN_CONSTANT_PARTICIPANTS = 2
"""A constant answer must be given to at least this many participants (not one person's repeated table)."""
REASONS = ("too few", "padding", "constant")
"""The reasons, in the order `DegenerateVerdict.reasons` lists them."""


def answer_key(objects: Sequence[int], xy) -> str | None:
    """A short fingerprint of one answer: a hash of its sorted (object id, x, y), positions rounded to
    `KEY_DECIMALS`. Rotation and placement order are left out, so a reordered or turned copy of an answer
    is the same answer. None for an empty answer."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(objects) != len(xy):
        raise DegustaError(f"answer_key: {len(objects)} objects but {len(xy)} positions")
    if not len(objects):
        return None
    rounded = np.round(xy, KEY_DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0
    text = ";".join(sorted(f"{int(o)}:{x:.{KEY_DECIMALS}f}:{y:.{KEY_DECIMALS}f}" for o, (x, y) in zip(objects, rounded)))
    return hashlib.sha1(text.encode()).hexdigest()[:12]


@dataclass(frozen=True)
class DegenerateVerdict:
    """What `degenerate_answers` found for one method: the share of its scored episodes behind each reason.

    A share is None when no episode counts for it (the constant share also without answer keys).
    """

    n_scored: int
    """Episodes counted: prediction not failed, ground truth not empty."""
    short_fraction: float | None
    """Share with n_pred <= SHORT_RATIO * n_gt."""
    few_matched_fraction: float | None
    """The older rule: share of the scored episodes with a ground truth of >= 3 that match <= 2 objects."""
    padded_fraction: float | None
    """Share with n_pred >= PAD_RATIO * n_gt or n_pred >= n_gt + PAD_MARGIN."""
    constant_fraction: float | None
    """Share given the most common answer (counted only when it reaches >= MIN_CONSTANT_PARTICIPANTS people)."""
    reasons: tuple[str, ...]
    """The reasons that apply, in REASONS order; () for a method that is not degenerate."""

    @property
    def degenerate(self) -> bool:
        return bool(self.reasons)

    def fractions(self) -> dict[str, float | None]:
        """{"too few", "few matched", "padding", "constant": share} rounded to 6 decimals (for metrics.json)."""
        def r(v):
            return None if v is None else round(float(v), 6)

        return {"too few": r(self.short_fraction), "few matched": r(self.few_matched_fraction),
                "padding": r(self.padded_fraction), "constant": r(self.constant_fraction)}


def _share(mask: np.ndarray) -> float | None:
    return float(mask.mean()) if mask.size else None


def constant_fraction(answer_keys: Sequence[str | None], participants: Sequence[str] | None = None,
                      min_participants: int = MIN_CONSTANT_PARTICIPANTS) -> float | None:
    """Share of the answers that equal the most common one, 0 when that answer reaches fewer than
    `min_participants` participants (without `participants`, every answer counts as its own participant);
    None without any key. Missing keys (None) count as answers of their own."""
    keys = list(answer_keys)
    if not keys:
        return None
    people = list(participants) if participants is not None else list(range(len(keys)))
    if len(people) != len(keys):
        raise DegustaError(f"constant_fraction: {len(keys)} answer keys but {len(people)} participants")
    counts = Counter(k for k in keys if k is not None)
    if not counts:
        return 0.0
    reach: dict[str, set] = {}
    for key, who in zip(keys, people):
        if key is not None:
            reach.setdefault(key, set()).add(who)
    best = max(counts, key=lambda k: (counts[k], len(reach[k])))
    return counts[best] / len(keys) if len(reach[best]) >= min_participants else 0.0


def degenerate_answers(n_gt, n_pred, failed, answer_keys: Sequence[str | None] | None = None,
                       participants: Sequence[str] | None = None, n_matched=None,
                       threshold: float = DEGENERATE_FRACTION) -> DegenerateVerdict:
    """Decide whether one method's answers are degenerate, and why (module docstring).

    Args:
        n_gt, n_pred, failed: one value per episode (sequences or arrays of equal length); a failed
            episode is left out (it scores c in set RMSD and shows in the failure rate).
        answer_keys: `answer_key` of each episode's answer (None where unknown); without them the
            "constant" reason is not tested.
        participants: each episode's participant, for the constant answer's reach.
        n_matched: matched pairs per episode, for the older rule; default min(n_gt, n_pred) (what the
            Hungarian matching pairs).
        threshold: a reason applies when its share is strictly above this.

    Returns:
        A DegenerateVerdict; its `reasons` are () when no episode counts.
    """
    n_gt, n_pred = np.asarray(n_gt, dtype=int), np.asarray(n_pred, dtype=int)
    failed = np.asarray(failed, dtype=bool)
    if not n_gt.shape == n_pred.shape == failed.shape:
        raise DegustaError(f"degenerate_answers: n_gt, n_pred and failed differ in length "
                         f"({n_gt.size}, {n_pred.size}, {failed.size})")
    scored = ~failed & (n_gt > 0)
    g, p = n_gt[scored], n_pred[scored]
    short = _share(p <= SHORT_RATIO * g)
    matched = np.minimum(n_gt, n_pred) if n_matched is None else np.asarray(n_matched, dtype=int)
    few, _ = few_matched_fraction(n_gt, matched, failed, threshold=threshold)
    padded = _share((p >= PAD_RATIO * g) | (p >= g + PAD_MARGIN))
    constant = None
    if answer_keys is not None:
        keys = list(answer_keys)
        if len(keys) != n_gt.size:
            raise DegustaError(f"degenerate_answers: {len(keys)} answer keys for {n_gt.size} episodes")
        who = None if participants is None else [w for w, s in zip(participants, scored) if s]
        constant = constant_fraction([k for k, s in zip(keys, scored) if s], who)
    found = {"too few": any(v is not None and v > threshold for v in (short, few)),
             "padding": padded is not None and padded > threshold,
             "constant": constant is not None and constant > threshold}
    return DegenerateVerdict(n_scored=int(scored.sum()), short_fraction=short, few_matched_fraction=few,
                             padded_fraction=padded, constant_fraction=constant,
                             reasons=tuple(r for r in REASONS if found[r]))
