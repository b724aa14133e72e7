"""Bootstrap intervals: contain the mean, deterministic, narrow with n, agree with scipy.stats.bootstrap;
paired bootstrap finds a clear difference and none where there is none. Clustered (participant) resampling:
widens where episodes of one person agree, equals a reference loop, is deterministic; the per-episode option
reproduces the old numbers; the paired p-value and interval always agree."""

import math

import numpy as np
import pytest
from scipy import stats

from degusta_learn.errors import DegustaError
from degusta_learn.metrics import bootstrap_ci, bootstrap_means, paired_bootstrap, percentile_p_value


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


# --- clustered (participant) resampling -----------------------------------------------------------------------


def _old_resampled_means(x, n_resamples, seed):
    """The per-episode resampling as it was before clustering existed (a verbatim copy)."""
    rng = np.random.default_rng(seed)
    n = len(x)
    out = np.empty(int(n_resamples))
    step = max(1, 2_000_000 // n)
    for start in range(0, n_resamples, step):
        b = min(step, n_resamples - start)
        out[start:start + b] = x[rng.integers(0, n, size=(b, n))].mean(axis=1)
    return out


def _old_bootstrap_ci(values, n_resamples=1000, seed=0, alpha=0.05):
    x = np.asarray(values, dtype=float).ravel()
    x = x[~np.isnan(x)]
    means = _old_resampled_means(x, n_resamples, seed)
    lo, hi = np.percentile(means, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return float(x.mean()), float(lo), float(hi)


def test_per_episode_option_reproduces_the_old_numbers():
    rng = np.random.default_rng(11)
    for n, seed in ((7, 0), (200, 3), (1500, 9)):
        x = rng.exponential(size=n)
        x[rng.random(n) < 0.1] = np.nan
        assert bootstrap_ci(x, seed=seed) == _old_bootstrap_ci(x, seed=seed)
        assert bootstrap_ci(x, seed=seed, clusters=None) == _old_bootstrap_ci(x, seed=seed)
        y = x + rng.normal(0, 0.3, n)
        old = _old_bootstrap_ci(y - x, seed=seed)  # the paired difference, its interval unchanged
        new = paired_bootstrap(y, x, seed=seed)
        assert (new["diff"], new["lo"], new["hi"]) == pytest.approx(old, abs=0, rel=0)


def test_clustering_widens_the_interval_two_participants():
    # 2 participants x 50 identical episodes: A always 0, B always 1. Per episode the 100 values look like 100
    # independent coin flips (interval about 0.5 +- 0.1); but there are only two people. Resampling them gives
    # {A, A} (mean 0), {A, B} (0.5) or {B, B} (1) with probabilities 1/4, 1/2, 1/4: the 95% interval is [0, 1].
    values = [0.0] * 50 + [1.0] * 50
    people = ["A"] * 50 + ["B"] * 50
    mean, lo, hi = bootstrap_ci(values, clusters=people)
    assert (mean, lo, hi) == (0.5, 0.0, 1.0)
    _, lo_e, hi_e = bootstrap_ci(values)
    assert 0.38 < lo_e < 0.45 and 0.55 < hi_e < 0.62
    means = bootstrap_means(values, n_resamples=4000, clusters=people)
    assert set(np.unique(means)) == {0.0, 0.5, 1.0}
    assert np.mean(means == 0.5) == pytest.approx(0.5, abs=0.03)
    # The statistic is the mean over all episodes of the drawn participants: A (10 episodes of 0) with B (30 of 1)
    # gives 30 / 40 = 0.75, the plain mean of the data.
    uneven = bootstrap_means([0.0] * 10 + [1.0] * 30, n_resamples=2000, clusters=["A"] * 10 + ["B"] * 30)
    assert set(np.unique(uneven)) == {0.0, 0.75, 1.0}
    assert bootstrap_ci([0.0] * 10 + [1.0] * 30, clusters=["A"] * 10 + ["B"] * 30)[0] == 0.75


def test_clustered_resampling_matches_a_reference_loop_and_is_deterministic():
    rng = np.random.default_rng(4)
    people = np.repeat([f"p{i:02d}" for i in range(12)], rng.integers(1, 9, 12))
    values = rng.normal(size=len(people))
    values[3] = np.nan
    ok = ~np.isnan(values)
    labels = sorted(set(people[ok]))
    sums = np.array([values[ok][people[ok] == p].sum() for p in labels])
    counts = np.array([(people[ok] == p).sum() for p in labels], dtype=float)
    draw = np.random.default_rng(5).integers(0, len(labels), size=(300, len(labels)))
    ref = np.array([sums[d].sum() / counts[d].sum() for d in draw])
    got = bootstrap_means(values, n_resamples=300, seed=5, clusters=people)
    assert np.allclose(got, ref, rtol=1e-12, atol=1e-15)
    ci = bootstrap_ci(values, seed=5, clusters=people)
    assert ci == bootstrap_ci(values, seed=5, clusters=people)  # same seed, same interval
    assert ci != bootstrap_ci(values, seed=6, clusters=people)
    assert ci[0] == pytest.approx(np.nanmean(values))
    paired = paired_bootstrap(values + 0.1, values, seed=5, clusters=people)
    assert paired == paired_bootstrap(values + 0.1, values, seed=5, clusters=people)


def test_clustered_edge_cases():
    assert bootstrap_ci([1.0, 2.0, 3.0], clusters=["a", "a", "a"])[0] == 2.0
    assert all(math.isnan(v) for v in bootstrap_ci([1.0, 2.0, 3.0], clusters=["a", "a", "a"])[1:])  # one person
    assert all(math.isnan(v) for v in bootstrap_ci([np.nan, np.nan], clusters=["a", "b"]))
    # a participant whose every value is nan drops out: one participant left, no interval
    assert math.isnan(bootstrap_ci([1.0, np.nan], clusters=["a", "b"])[1])
    one = paired_bootstrap([1.0, 2.0], [0.0, 0.0], clusters=["a", "a"])
    assert one["diff"] == 1.5 and math.isnan(one["lo"]) and math.isnan(one["p_value"])
    with pytest.raises(DegustaError, match="cluster labels"):
        bootstrap_ci([1.0, 2.0], clusters=["a"])


def test_p_value_and_interval_agree():
    # The old shift test could print p = 0.057 beside an interval excluding 0; now both come from the same
    # resamples: the interval excludes 0 exactly when p < alpha, per episode and per participant.
    rng = np.random.default_rng(8)
    checked = near = 0
    for trial in range(300):
        n = int(rng.integers(5, 60))
        people = rng.integers(0, max(2, n // 4), n).astype(str)
        shift = rng.normal(0, 0.35) * 1.0 / math.sqrt(n)
        a, b = rng.normal(shift, 1.0, n), rng.normal(0, 1.0, n)
        for clusters in (None, people):
            for alpha in (0.05, 0.1):
                r = paired_bootstrap(a, b, n_resamples=200, seed=trial, alpha=alpha, clusters=clusters)
                if math.isnan(r["p_value"]):
                    continue
                assert (r["p_value"] < alpha) == (r["lo"] > 0 or r["hi"] < 0), (trial, r)
                checked += 1
                near += abs(r["p_value"] - alpha) < 0.02
    assert checked > 1000 and near > 20  # many cases near the threshold
    assert percentile_p_value([0.1, 0.2, 0.3]) == 0.0  # every resample on one side
    assert percentile_p_value([0.0, 0.0]) == 1.0
    # sorted means -1, 1, 2, 3 (levels 0, 1/3, 2/3, 1): 0 is crossed at level 1/6 -> p = 2 * 1/6
    assert percentile_p_value([3.0, -1.0, 2.0, 1.0]) == pytest.approx(1 / 3)
    assert np.percentile([3.0, -1.0, 2.0, 1.0], 100 / 6) == pytest.approx(0.0, abs=1e-12)


def test_paired_clustering_widens_too():
    # Method b beats a by 0.1 on every episode of 3 participants and loses by 0.1 on every episode of 2 others
    # (40 episodes each). Per episode that looks decisive (200 pairs); over 5 people it is not.
    d_per_person = [0.1, 0.1, 0.1, -0.1, -0.1]
    people = np.repeat(list("abcde"), 40)
    d = np.repeat(d_per_person, 40)
    per_episode = paired_bootstrap(d, np.zeros_like(d))
    clustered = paired_bootstrap(d, np.zeros_like(d), clusters=people)
    assert per_episode["p_value"] < 0.01 and per_episode["lo"] > 0
    assert clustered["p_value"] > 0.05 and clustered["lo"] < 0 < clustered["hi"]
    assert per_episode["diff"] == clustered["diff"] == pytest.approx(0.02)
