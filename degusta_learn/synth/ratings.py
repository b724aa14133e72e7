"""Simulated jitter-study ratings (SYNTHETIC), calibrated to the paper's acceptability table.

The paper's study: a participant rates their own arrangement (b_initial, 0..100), the scene is translated
and rotated by a random magnitude t in [0, 1], they rate it again (b_jitter). The acceptability curve is
the fraction of trials with RMSD <= t whose drop (b_initial - b_jitter) / 100 is below 0.2; the paper
reports 0.727, 0.333, 0.199 at t = 0.01, 0.05, 0.10.

Our model, one jitter trial per arrangement:

- magnitude `t ~ U[0, 1]`; the whole arrangement is translated by `JITTER_SHIFT * t` in a uniformly random
  direction and turned by `JITTER_TURN * t` degrees (random sign) about its centroid;
- `rmsd_jitter` is the **unregistered** RMSD between the original and jittered positions (the mean
  displacement). The Kabsch RMSD of a rigidly moved arrangement is ~0 by construction, so it cannot
  measure a jitter; the displacement is what the participant saw move;
- `b_initial = clip(round(N(rating_base, 6)), 0, 100)` with a per-person `rating_base ~ U[60, 98]`;
- `drop = RATING_BIAS + rating_sensitivity * rmsd_jitter + N(0, RATING_NOISE)`, with a per-person
  log-normal `rating_sensitivity` (median `SENSITIVITY_MEDIAN`, log-sd `SENSITIVITY_LOG_SD`);
  `b_jitter = clip(round(b_initial - 100 * drop), 0, 100)`;
- `b_correct` and `rmsd_correct` (the correction stage) are not simulated and stay null.

The constants were fitted (benchmarks/bench_baselines.py prints the resulting curve) so that
`metrics.acceptability_curve` on the default seed lands near the paper's three points.
"""

from __future__ import annotations

import math

import numpy as np

from degusta_learn.scene import Arrangement, Rating

JITTER_SHIFT = 0.15  # translation at t = 1 (normalized units)
JITTER_TURN = 30.0  # rotation at t = 1 (degrees)
RATING_BIAS = 0.06  # mean drop of an unmoved scene
RATING_NOISE = 0.12  # per-trial rating noise (fraction of 100)
SENSITIVITY_MEDIAN = 10.0  # drop per unit RMSD, median person
SENSITIVITY_LOG_SD = 0.75  # spread of sensitivity between people


def sample_rating_traits(rng: np.random.Generator) -> tuple[float, float]:
    """A person's (rating_base, rating_sensitivity)."""
    base = float(rng.uniform(60, 98))
    sensitivity = float(SENSITIVITY_MEDIAN * np.exp(rng.normal(0, SENSITIVITY_LOG_SD)))
    return base, sensitivity


def jitter(xy: np.ndarray, t: float, rng: np.random.Generator) -> np.ndarray:
    """Translate (N, 2) positions by JITTER_SHIFT * t and turn them by JITTER_TURN * t about the centroid."""
    direction, angle = _jitter_draws(t, rng)
    c = xy.mean(0)
    rel = xy - c
    turned = np.stack([rel[:, 0] * np.cos(angle) - rel[:, 1] * np.sin(angle),
                       rel[:, 0] * np.sin(angle) + rel[:, 1] * np.cos(angle)], -1)
    return c + turned + JITTER_SHIFT * t * np.array([np.cos(direction), np.sin(direction)])


def _jitter_draws(t: float, rng: np.random.Generator) -> tuple[float, float]:
    """(translation direction, signed turn in radians) of one jitter."""
    draws = rng.random(2)
    return 2 * math.pi * draws[0], math.radians(JITTER_TURN * t) * (1 if draws[1] < 0.5 else -1)


def jitter_rmsd(xy: np.ndarray, t: float, rng: np.random.Generator) -> float:
    """The unregistered RMSD of `jitter(xy, t, rng)` in closed form (same draws, no positions built).

    Displacement of point i: s + (R - I)(x_i - c); its mean square is |s|^2 + 2 (1 - cos a) mean|x_i - c|^2
    (the cross term vanishes because the x_i - c sum to zero).
    """
    _direction, angle = _jitter_draws(t, rng)
    spread = float(((xy - xy.mean(0)) ** 2).sum(1).mean())
    return math.sqrt((JITTER_SHIFT * t) ** 2 + 2 * (1 - math.cos(angle)) * spread)


def simulate_rating(arrangement: Arrangement, base: float, sensitivity: float, rng: np.random.Generator) -> Rating:
    """One jitter-study trial for `arrangement` by a person with the given rating traits."""
    t = float(rng.random())
    rmsd = jitter_rmsd(arrangement.positions, t, rng)
    b_initial, noise = rng.normal([base, RATING_BIAS], [6.0, RATING_NOISE])
    b_initial = float(min(max(round(b_initial), 0), 100))
    drop = noise + sensitivity * rmsd
    b_jitter = float(min(max(round(b_initial - 100 * drop), 0), 100))
    return Rating(arrangement.participant, arrangement.trial, b_initial, b_jitter, round(rmsd, 6))
