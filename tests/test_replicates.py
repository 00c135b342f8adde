"""The onset correction's GP: per-bin means over replicated groups (tests), each with its standard error."""

import numpy as np
import pytest

from crashfuse.gp.replicates import ReplicateMeanGP, bin_means

WIDTH = 0.001  # s
T = np.arange(0.0, 0.022, 0.00025)  # 88 rows per test over 22 ms


def _tests(shared, noise, n_tests=10, seed=0):
    """Rows of ``n_tests`` tests: ``shared(t)`` plus each test's own smooth deviation of std ``noise``
    (correlated along the record, as a filtered measurement is)."""
    rng = np.random.default_rng(seed)
    t, y, g = [], [], []
    for k in range(n_tests):
        a, phase, period = rng.normal(0.0, noise * np.sqrt(2)), rng.uniform(0, 2 * np.pi), rng.uniform(0.004, 0.01)
        t.append(T), y.append(shared(T) + a * np.sin(2 * np.pi * T / period + phase)), g.append(np.full(T.size, k))
    return np.concatenate(t), np.concatenate(y), np.concatenate(g)


def _rms(v):
    return float(np.sqrt(np.mean(np.square(v))))


def test_a_feature_every_test_shares_is_followed():
    hump = lambda t: 0.2 * np.exp(-0.5 * ((t - 0.006) / 0.002) ** 2)
    t, y, g = _tests(hump, noise=0.05)
    gp = ReplicateMeanGP(WIDTH).fit(t, y, g)
    assert _rms(gp.predict(T) - hump(T)) < 0.3 * _rms(hump(T))


def test_each_tests_own_correlated_noise_is_shrunk_away():
    """Ten tests of smooth noise only: the plain mean over tests keeps about a third of the noise
    (1 / sqrt 10); the GP, knowing each bin mean's standard error, keeps far less."""
    t, y, g = _tests(lambda t: 0.0 * t, noise=0.05)
    gp = ReplicateMeanGP(WIDTH).fit(t, y, g)
    centres, means, _, _ = bin_means(t, y, g, WIDTH, 3)
    assert _rms(means) > 0.2 * 0.05  # the naive correction would carry this
    assert _rms(gp.predict(T)) < 0.3 * _rms(means)


def test_held_out_residuals_are_the_other_tests_bin_means_conditioned_at_fixed_hyperparameters():
    t, y, g = _tests(lambda t: 0.1 * np.sin(t / 0.003), noise=0.03)
    gp = ReplicateMeanGP(WIDTH).fit(t, y, g)
    res = gp.grouped_residuals(t, y, g)
    own = g == 4
    other = ReplicateMeanGP(WIDTH).fit(t[~own], y[~own], g[~own])
    other.length_, other.sf2_ = gp.length_, gp.sf2_
    other._condition()
    np.testing.assert_allclose(res[own], y[own] - other.predict(t[own]), rtol=1e-10, atol=1e-12)


def test_a_new_tests_std_includes_the_spread_between_tests():
    t, y, g = _tests(lambda t: 0.0 * t, noise=0.05)
    gp = ReplicateMeanGP(WIDTH).fit(t, y, g)
    _, sd = gp.predict(T, return_std=True)
    _, sd_new = gp.predict(T, return_std=True, include_noise=True)
    assert np.all(sd_new > sd) and np.all(sd_new > 0.02)


def test_too_few_tests_in_the_bins_is_an_error():
    t, y, g = _tests(lambda t: 0.0 * t, noise=0.05, n_tests=2)
    with pytest.raises(ValueError, match="two bins with 3 groups"):
        ReplicateMeanGP(WIDTH).fit(t, y, g)
