"""Score predictions episode by episode: the rows of per_episode.csv.

Every method's predictions are scored the same way (degusta_learn.metrics.score_many, equal to
score_prediction on each, against the held-out target arrangement of the dataset), so zero-shot, baseline
and fine-tuned methods are compared on equal terms.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import score_many
from degusta_learn.scene import Dataset, Episode, Prediction

_CONTEXT_IN_ID = re.compile(r"/k(\d+)$")

CSV_COLUMNS = ("method", "episode", "participant", "target", "context", "task", "failed", "n_gt", "n_pred",
               "n_matched", "object_accuracy", "rmsd", "rmsd_unregistered", "count_error", "set_rmsd", "tokens",
               "cost_usd")


@dataclass
class EpisodeRow:
    """One method's scores on one episode (a row of per_episode.csv)."""

    method: str
    episode: str
    participant: str
    target: int
    context: int | None
    task: str
    failed: bool
    n_gt: int
    n_pred: int
    n_matched: int
    object_accuracy: float
    rmsd: float
    rmsd_unregistered: float
    count_error: float
    set_rmsd: float  # set-aware (OSPA) RMSD: c = SET_PENALTY per unmatched object; c for a failed prediction
    tokens: float | None = None
    cost_usd: float | None = None

    def to_row(self) -> dict:
        return asdict(self)


def score_predictions(ds: Dataset, predictions: list[Prediction],
                      episodes: dict[str, Episode] | None = None) -> list[EpisodeRow]:
    """Score each prediction against the dataset's target arrangement.

    Args:
        ds: the dataset holding the ground truth.
        predictions: one method's (or several methods') predictions.
        episodes: the episode set, if known; gives context length and task. Without it the context
            length is read from ids of the form ``.../kN`` and the task is "unknown".
    """
    for pred in predictions:
        ep = episodes.get(pred.episode) if episodes else None
        if ep is not None and (ep.participant, ep.target) != (pred.participant, pred.target):
            raise DegustaError(f"prediction for episode {pred.episode!r} names participant {pred.participant!r} "
                               f"trial {pred.target}, but the episode's target is {ep.participant!r} trial {ep.target}")
    gts = [ds.arrangement(pred.participant, pred.target) for pred in predictions]
    rows = []
    for pred, score in zip(predictions, score_many(ds.catalog, gts, predictions)):
        ep = episodes.get(pred.episode) if episodes else None
        if ep is not None:
            context, task = len(ep.context), ep.task
        else:
            m = _CONTEXT_IN_ID.search(pred.episode)
            context, task = (int(m.group(1)) if m else None), "unknown"
        usage = pred.diagnostics.get("usage") or {}
        rows.append(EpisodeRow(
            method=pred.method, episode=pred.episode, participant=pred.participant, target=pred.target,
            context=context, task=task, failed=pred.failed or not pred.placements, n_gt=score.n_gt,
            n_pred=score.n_pred, n_matched=score.n_matched, object_accuracy=score.object_accuracy,
            rmsd=score.rmsd, rmsd_unregistered=score.rmsd_unregistered, count_error=score.count_error,
            set_rmsd=score.set_rmsd, tokens=usage.get("tokens"), cost_usd=usage.get("cost_usd")))
    return rows
