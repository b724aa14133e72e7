"""Plain value types of the task: placements, arrangements, ratings, episodes and predictions.

Coordinates are normalized image coordinates of the table image: origin top-left, y downward, both in
[0, 1], at the object's centroid. Rotation is degrees clockwise from image north, in [0, 360).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

TASKS = ("reconstruction", "generalization")


def normalized_rotation(degrees: float) -> float:
    """`degrees` in [0, 360), rounded to 4 decimals as every JSON file the toolkit writes: 359.99999 and 360 are 0."""
    value = round(float(degrees) % 360.0, 4)
    return 0.0 if value >= 360.0 else value + 0.0  # + 0.0: no -0.0


@dataclass(frozen=True)
class Placement:
    """One object put on the table: which object, where (centroid) and how rotated."""

    object: int
    x: float
    y: float
    rotation: float = 0.0

    def to_json(self) -> dict:
        return {"object": self.object, "x": round(self.x, 6), "y": round(self.y, 6),
                "rotation": normalized_rotation(self.rotation)}


@dataclass(frozen=True)
class Arrangement:
    """A participant's set table: placements in placement order on one table."""

    participant: str
    trial: int
    table: int
    placements: tuple[Placement, ...]

    @property
    def objects(self) -> list[int]:
        return [p.object for p in self.placements]

    @property
    def positions(self) -> np.ndarray:
        """(N, 2) array of x, y."""
        return np.array([[p.x, p.y] for p in self.placements], dtype=float).reshape(-1, 2)

    @property
    def rotations(self) -> np.ndarray:
        return np.array([p.rotation for p in self.placements], dtype=float)

    def to_json(self) -> dict:
        return {"participant": self.participant, "trial": self.trial, "table": self.table,
                "placements": [p.to_json() for p in self.placements]}


@dataclass(frozen=True)
class Rating:
    """One jitter-study trial: ratings (0..100) of the initial scene and of a jittered copy."""

    participant: str
    trial: int
    b_initial: float
    b_jitter: float
    rmsd_jitter: float
    b_correct: float | None = None
    rmsd_correct: float | None = None

    @property
    def drop(self) -> float:
        """Normalized rating drop (b_initial - b_jitter) / 100."""
        return (self.b_initial - self.b_jitter) / 100.0

    def to_json(self) -> dict:
        return {"participant": self.participant, "trial": self.trial, "b_initial": self.b_initial,
                "b_jitter": self.b_jitter, "rmsd_jitter": self.rmsd_jitter, "b_correct": self.b_correct,
                "rmsd_correct": self.rmsd_correct}


@dataclass(frozen=True)
class Episode:
    """The unit of prediction: a participant's context trials and the held-out target trial."""

    id: str
    participant: str
    context: tuple[int, ...]
    target: int
    task: str

    def to_json(self) -> dict:
        return {"id": self.id, "participant": self.participant, "context": list(self.context),
                "target": self.target, "task": self.task}


@dataclass
class Prediction:
    """Any method's answer for one episode (the same type for zero-shot, baseline and fine-tuned)."""

    episode: str
    participant: str
    target: int
    method: str
    placements: list[Placement]
    failed: bool = False
    diagnostics: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"episode": self.episode, "participant": self.participant, "target": self.target,
                "method": self.method, "placements": [p.to_json() for p in self.placements],
                "failed": self.failed, "diagnostics": self.diagnostics}
