"""Bootstrap intervals: contain the mean, deterministic, narrow with n, agree with scipy.stats.bootstrap;
paired bootstrap finds a clear difference and none where there is none."""

import math

import numpy as np
import pytest
from scipy import stats

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import bootstrap_ci, paired_bootstrap


def test_ci_contains_mean_and_is_deterministic():
    x = np.random.default_rng(0).exponential(size=200)
    mean, lo, hi = bootstrap_ci(x)
    assert mean == pytest.approx(x.mean()) and lo < mean < hi
    assert bootstrap_ci(x, seed=0) == (mean, lo, hi)
    assert bootstrap_ci(x, seed=1) != (mean, lo, hi)


def test_ci_narrows_with_n_and_matches_scipy():
    rng = np.random.default_rng(1)
    small, large = rng.normal(size=30), rng.normal(size=3000)
    w_small = np.subtract(*bootstrap_ci(small)[2:0:-1])
    w_large = np.subtract(*bootstrap_ci(large)[2:0:-1])
    assert w_large < w_small / 5  # ~ sqrt(100) = 10 times narrower
    ref = stats.bootstrap((small,), np.mean, n_resamples=4000, method="percentile", random_state=0)
    _, lo, hi = bootstrap_ci(small, n_resamples=4000)
    ci = ref.confidence_interval
    assert lo == pytest.approx(ci.low, abs=0.1 * w_small)
    assert hi == pytest.approx(ci.high, abs=0.1 * w_small)


def test_nan_aware_and_degenerate():
    x = np.array([0.1, 0.5, np.nan, 0.3, np.nan, 0.9])
    assert bootstrap_ci(x) == bootstrap_ci(x[~np.isnan(x)])
    assert all(math.isnan(v) for v in bootstrap_ci([np.nan, np.nan]))
    assert bootstrap_ci([0.4]) == (0.4, 0.4, 0.4)
    with pytest.raises(DegustaError, match="alpha"):
        bootstrap_ci(x, alpha=1.5)
    with pytest.raises(DegustaError, match="n_bootstrap"):
        bootstrap_ci(x, n_resamples=0)


def test_paired_bootstrap():
    rng = np.random.default_rng(2)
    base = rng.random(100)
    clear = paired_bootstrap(base + 0.1 + rng.normal(0, 0.02, 100), base)
    assert clear["diff"] == pytest.approx(0.1, abs=0.01)
    assert 0 < clear["lo"] < clear["diff"] < clear["hi"]
    assert clear["p_value"] < 0.01
    null = paired_bootstrap(base + rng.normal(0, 0.05, 100), base + rng.normal(0, 0.05, 100))
    assert null["p_value"] > 0.05 and null["lo"] < 0 < null["hi"]
    same = paired_bootstrap(base, base)
    assert same == {"diff": 0.0, "lo": 0.0, "hi": 0.0, "p_value": 1.0}
    # Episodes where either method is nan are dropped as pairs.
    a, b = np.array([1.0, np.nan, 3.0]), np.array([0.5, 2.0, np.nan])
    assert paired_bootstrap(a, b)["diff"] == 0.5
    with pytest.raises(DegustaError, match="same episodes"):
        paired_bootstrap([1.0, 2.0], [1.0])
