"""Percentile bootstrap confidence intervals over episodes, and a paired bootstrap for two methods.

Both ignore nan values (a paired comparison drops the episodes where either method has nan). Results
are deterministic for a seed. Resampling runs in chunks of about 2 million indices, so memory stays
small for any number of episodes.

Usage:
    from degusta_learn.metrics import bootstrap_ci, paired_bootstrap
    mean, lo, hi = bootstrap_ci([s.rmsd for s in scores])
    paired_bootstrap(acc_method_a, acc_method_b)   # {"diff", "lo", "hi", "p_value"}
"""

from __future__ import annotations

import numpy as np

from degusta_learn.config import check_seed, show_value
from degusta_learn.errors import DegustaError

_CHUNK = 2_000_000  # indices drawn per chunk
MAX_RESAMPLES = 1_000_000
"""Most bootstrap resamples (the means alone take 8 bytes each; more adds nothing to a 95% interval)."""


def _check(n_resamples: int, alpha: float, seed: int) -> None:
    # Named as the user knows it: `--bootstrap` of evaluate, `n_bootstrap` of a compare config.
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, int | np.integer) \
            or not 1 <= n_resamples <= MAX_RESAMPLES:
        raise DegustaError(f"bootstrap (n_bootstrap): expected a number of resamples from 1 to "
                           f"{MAX_RESAMPLES:,}, got {show_value(n_resamples)}")
    check_seed(seed)
    if not isinstance(alpha, int | float | np.floating) or not 0.0 < alpha < 1.0:
        raise DegustaError(f"alpha: expected a number between 0 and 1, got {show_value(alpha)}")


def _resampled_means(x: np.ndarray, n_resamples: int, seed: int) -> np.ndarray:
    """(n_resamples,) means of bootstrap resamples of x (n,)."""
    rng = np.random.default_rng(seed)
    n = len(x)
    out = np.empty(int(n_resamples))
    step = max(1, _CHUNK // n)
    for start in range(0, n_resamples, step):
        b = min(step, n_resamples - start)
        out[start:start + b] = x[rng.integers(0, n, size=(b, n))].mean(axis=1)
    return out


def bootstrap_ci(values, n_resamples: int = 1000, seed: int = 0, alpha: float = 0.05
                 ) -> tuple[float, float, float]:
    """Mean and percentile bootstrap (1 - alpha) confidence interval, ignoring nan.

    Args:
        values: per-episode values (nan = missing).
        n_resamples: bootstrap resamples.
        seed: random seed (same seed, same interval).
        alpha: 0.05 gives a 95% interval.

    Returns:
        (mean, lo, hi); all nan when no value is finite, (v, v, v) for a single value.
    """
    _check(n_resamples, alpha, seed)
    x = np.asarray(values, dtype=float).ravel()
    x = x[~np.isnan(x)]
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    means = _resampled_means(x, n_resamples, seed)
    lo, hi = np.percentile(means, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return float(x.mean()), float(lo), float(hi)


def paired_bootstrap(a, b, n_resamples: int = 1000, seed: int = 0, alpha: float = 0.05) -> dict[str, float]:
    """Paired bootstrap of mean(a - b) for two methods scored on the same episodes.

    Episodes are resampled as pairs. The two-sided p-value tests mean difference 0 against the
    null-centred bootstrap distribution: p = (1 + #{|d* - d| >= |d|}) / (1 + n_resamples).

    Args:
        a: per-episode values of method A.
        b: per-episode values of method B, same episodes in the same order.
        n_resamples, seed, alpha: as for `bootstrap_ci`.

    Returns:
        {"diff": mean(a - b), "lo": ..., "hi": ..., "p_value": ...}; all nan without a complete pair.
    """
    _check(n_resamples, alpha, seed)
    xa, xb = np.asarray(a, dtype=float).ravel(), np.asarray(b, dtype=float).ravel()
    if xa.shape != xb.shape:
        raise DegustaError(f"paired_bootstrap: {xa.size} values vs {xb.size}; both methods must score the same episodes")
    d = xa - xb
    d = d[~np.isnan(d)]
    if d.size == 0:
        return {"diff": float("nan"), "lo": float("nan"), "hi": float("nan"), "p_value": float("nan")}
    diff = float(d.mean())
    means = _resampled_means(d, n_resamples, seed)
    lo, hi = np.percentile(means, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    # Tolerance: identical resamples of constant data must count as "as extreme" despite rounding.
    extreme = np.abs(means - diff) >= abs(diff) - 1e-12 * max(1.0, abs(diff))
    p = (1 + int(extreme.sum())) / (1 + n_resamples)
    return {"diff": diff, "lo": float(lo), "hi": float(hi), "p_value": float(p)}
