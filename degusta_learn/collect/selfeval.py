"""The self-evaluation's numbers: the jittered copy of a scene and the distances the ratings are filed with.

The jitter is drawn as the simulated study draws it (synth/ratings.py): a magnitude t ~ U[0, 1]; the whole scene is
translated by `shift * t` in a uniformly random direction and turned by `turn * t` degrees (random sign) about its
centroid, each object's rotation turning with it. Positions that would leave the table image are held at its edge
(the participant must see every object), so `rmsd_jitter` is measured on what was shown: the unregistered RMSD
between the participant's arrangement and the jittered copy, object by object (`metrics.ACCEPTABILITY_ERROR`, the
error the acceptability curve pairs with the ratings). `rmsd_correct` is the same distance between the corrected
copy and the participant's arrangement (the paper's d(a_correct, a_initial)).
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from degusta_learn.scene.types import Placement


def jitter_rng(seed: int, participant: str, trial: int) -> np.random.Generator:
    """The jitter's random numbers for one participant's trial: reproducible from the study seed."""
    digest = hashlib.sha256(f"{seed}\0{participant}\0{trial}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def jittered(placements: list[Placement], shift: float, turn: float,
             rng: np.random.Generator) -> tuple[float, list[Placement]]:
    """(t, the jittered copy of `placements`), in the same order."""
    t = float(rng.random())
    draws = rng.random(2)
    direction = 2 * math.pi * draws[0]
    degrees = turn * t * (1 if draws[1] < 0.5 else -1)
    xy = np.array([[p.x, p.y] for p in placements], dtype=float)
    c = xy.mean(0)
    a = math.radians(degrees)  # clockwise on screen: y grows downward, so this is the usual rotation matrix
    rel = xy - c
    turned = np.stack([rel[:, 0] * math.cos(a) - rel[:, 1] * math.sin(a),
                       rel[:, 0] * math.sin(a) + rel[:, 1] * math.cos(a)], -1)
    moved = np.clip(c + turned + shift * t * np.array([math.cos(direction), math.sin(direction)]), 0.0, 1.0)
    out = [Placement(p.object, round(float(x), 6), round(float(y), 6), (p.rotation + degrees) % 360.0)
           for p, (x, y) in zip(placements, moved)]
    return t, out


def displacement_rmsd(a: list[Placement], b: list[Placement]) -> float:
    """Unregistered RMSD between two placements of the same objects, paired by object id."""
    where = {p.object: (p.x, p.y) for p in b}
    d = [(p.x - where[p.object][0]) ** 2 + (p.y - where[p.object][1]) ** 2 for p in a]
    return round(math.sqrt(sum(d) / len(d)), 6)


__all__ = ["displacement_rmsd", "jitter_rng", "jittered"]
