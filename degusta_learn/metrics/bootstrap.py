"""Percentile bootstrap intervals and a paired bootstrap test, over episodes or clustered by participant.

Episodes of one participant are not independent (the same person, the same habits, often the same
context trials), so treating them as independent understates the uncertainty. With `clusters` (one
label per value: the participant id) a resample draws participants with replacement and keeps all of a
drawn participant's episodes together; the statistic is the mean over all episodes of the resampled
participants (sum of their values / number of their values: a participant with more episodes weighs
more, as in the plain mean). Without `clusters` (None) episodes are resampled one by one, as before:
the same numbers, bit for bit, as the earlier per-episode version for a seed. Fewer than two clusters
give no interval (nan bounds): one participant says nothing about the next.

The paired test and its interval come from the same resamples: p is twice the share of bootstrap means
on the far side of 0 (the inversion of the percentile interval, read off the same linear interpolation
`np.percentile` uses), so "the (1 - alpha) interval excludes 0" and "p < alpha" always agree. A p of 0
means every resample fell on one side (report it as below 1 / n_resamples).

Both ignore nan values (a paired comparison drops the episodes where either method has nan). Results
are deterministic for a seed. Resampling runs in chunks of about 2 million indices, so memory stays
small for any number of episodes.

Usage:
    from degusta_learn.metrics import bootstrap_ci, paired_bootstrap
    mean, lo, hi = bootstrap_ci([s.rmsd for s in scores], clusters=[r.participant for r in rows])
    paired_bootstrap(acc_method_a, acc_method_b, clusters=participants)   # {"diff", "lo", "hi", "p_value"}
    bootstrap_ci(values)                                                  # per-episode resampling
"""

from __future__ import annotations

import numpy as np

from degusta_learn.config import check_seed, show_value
from degusta_learn.errors import DegustaError

_CHUNK = 2_000_000  # indices drawn per chunk
MAX_RESAMPLES = 1_000_000
"""Most bootstrap resamples (the means alone take 8 bytes each; more adds nothing to a 95% interval)."""
NAN = float("nan")


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


def _clustered_means(sums: np.ndarray, counts: np.ndarray, n_resamples: int, seed: int) -> np.ndarray:
    """(n_resamples,) means over all values of C clusters drawn with replacement (per-cluster sums, counts)."""
    rng = np.random.default_rng(seed)
    c = len(sums)
    out = np.empty(int(n_resamples))
    step = max(1, _CHUNK // c)
    for start in range(0, n_resamples, step):
        b = min(step, n_resamples - start)
        idx = rng.integers(0, c, size=(b, c))
        out[start:start + b] = sums[idx].sum(axis=1) / counts[idx].sum(axis=1)
    return out


def _finite(values, clusters, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """The finite values (flattened) and, with clusters, their cluster codes (0..C-1)."""
    x = np.asarray(values, dtype=float).ravel()
    if clusters is None:
        return x[~np.isnan(x)], None
    labels = np.asarray(clusters, dtype=object).ravel()
    if labels.shape != x.shape:
        raise DegustaError(f"{what}: {x.size} values but {labels.size} cluster labels; give one label per value")
    keep = ~np.isnan(x)
    _, codes = np.unique(labels[keep].astype(str), return_inverse=True)
    return x[keep], codes.ravel()


def bootstrap_means(values, n_resamples: int = 1000, seed: int = 0, clusters=None) -> np.ndarray:
    """The bootstrap distribution of the mean (nan ignored): (n_resamples,) resampled means.

    Args:
        values: per-episode values (nan = missing).
        n_resamples, seed: as for `bootstrap_ci`.
        clusters: one label per value (e.g. the participant id): resample clusters, not values; None
            resamples values one by one.

    Returns:
        The resampled means; empty when no value is finite. With clusters, all equal to the mean when
        there is a single cluster.
    """
    _check(n_resamples, 0.05, seed)
    x, codes = _finite(values, clusters, "bootstrap")
    if x.size == 0:
        return np.zeros(0)
    if codes is None:
        return _resampled_means(x, n_resamples, seed)
    sums, counts = np.bincount(codes, weights=x), np.bincount(codes).astype(float)
    return _clustered_means(sums, counts, n_resamples, seed)


def n_clusters(values, clusters) -> int:
    """How many clusters hold a finite value (the number of units a clustered bootstrap resamples)."""
    x, codes = _finite(values, clusters, "bootstrap")
    return int(x.size) if codes is None else (int(codes.max()) + 1 if codes.size else 0)


def bootstrap_ci(values, n_resamples: int = 1000, seed: int = 0, alpha: float = 0.05, clusters=None
                 ) -> tuple[float, float, float]:
    """Mean and percentile bootstrap (1 - alpha) confidence interval, ignoring nan.

    Args:
        values: per-episode values (nan = missing).
        n_resamples: bootstrap resamples.
        seed: random seed (same seed, same interval).
        alpha: 0.05 gives a 95% interval.
        clusters: one label per value (the participant of each episode): resample participants, keeping
            their episodes together. None: resample episodes (the per-episode interval).

    Returns:
        (mean, lo, hi); all nan when no value is finite; (v, v, v) for a single value without clusters;
        (mean, nan, nan) with fewer than two clusters.
    """
    _check(n_resamples, alpha, seed)
    x, codes = _finite(values, clusters, "bootstrap_ci")
    if x.size == 0:
        return NAN, NAN, NAN
    if codes is not None and codes.max() < 1:
        return float(x.mean()), NAN, NAN
    means = bootstrap_means(values, n_resamples, seed, clusters)
    lo, hi = np.percentile(means, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return float(x.mean()), float(lo), float(hi)


def percentile_p_value(means) -> float:
    """Two-sided p of "mean 0" from a bootstrap distribution, by inverting the percentile interval.

    With q_le the largest and q_ge the smallest level q at which `np.percentile(means, 100 q)` is <= 0 and
    >= 0 respectively (the same linear interpolation), p = min(1, 2 * min(q_le, 1 - q_ge)). Then the
    percentile (1 - alpha) interval excludes 0 exactly when p < alpha. 0: every resample on one side.
    """
    m = np.sort(np.asarray(means, dtype=float).ravel())
    b = len(m)
    if b == 0:
        return NAN
    span = max(b - 1, 1)
    i = int(np.searchsorted(m, 0.0, side="right")) - 1  # last m <= 0
    if i < 0:
        q_le = 0.0
    elif i >= b - 1:
        q_le = 1.0
    else:
        q_le = (i + (0.0 - m[i]) / (m[i + 1] - m[i])) / span
    j = int(np.searchsorted(m, 0.0, side="left"))  # first m >= 0
    if j <= 0:
        q_ge = 0.0
    elif j >= b:
        q_ge = 1.0
    else:
        q_ge = (j - 1 + (0.0 - m[j - 1]) / (m[j] - m[j - 1])) / span
    return float(min(1.0, 2.0 * min(q_le, 1.0 - q_ge)))


def paired_bootstrap(a, b, n_resamples: int = 1000, seed: int = 0, alpha: float = 0.05, clusters=None
                     ) -> dict[str, float]:
    """Paired bootstrap of mean(a - b) for two methods scored on the same episodes.

    Episodes are resampled as pairs (with `clusters`, participants are resampled, each with all of its
    pairs). The interval is the percentile interval of the resampled mean differences; the two-sided
    p-value inverts that same interval (`percentile_p_value`), so the interval excludes 0 exactly when
    p < alpha.

    Args:
        a: per-episode values of method A.
        b: per-episode values of method B, same episodes in the same order.
        n_resamples, seed, alpha: as for `bootstrap_ci`.
        clusters: one label per episode (its participant), or None for per-episode resampling.

    Returns:
        {"diff": mean(a - b), "lo": ..., "hi": ..., "p_value": ...}; all nan without a complete pair;
        diff with nan lo, hi and p_value for pairs from fewer than two clusters.
    """
    _check(n_resamples, alpha, seed)
    xa, xb = np.asarray(a, dtype=float).ravel(), np.asarray(b, dtype=float).ravel()
    if xa.shape != xb.shape:
        raise DegustaError(f"paired_bootstrap: {xa.size} values vs {xb.size}; both methods must score the same episodes")
    d = xa - xb
    x, codes = _finite(d, clusters, "paired_bootstrap")
    if x.size == 0:
        return {"diff": NAN, "lo": NAN, "hi": NAN, "p_value": NAN}
    diff = float(x.mean())
    if codes is not None and codes.max() < 1:
        return {"diff": diff, "lo": NAN, "hi": NAN, "p_value": NAN}
    means = bootstrap_means(d, n_resamples, seed, clusters)
    lo, hi = np.percentile(means, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return {"diff": diff, "lo": float(lo), "hi": float(hi), "p_value": percentile_p_value(means)}
