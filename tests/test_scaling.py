"""A test library of dozens of tests: the capped conditioning and scatter refits against the exact GP."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import crashfuse.gp.kriging as kriging
from crashfuse.gp.grouped import scatter_needs
from crashfuse.gp.kriging import KrigingGP
from crashfuse.gp.subsets import condition_subset

N_TESTS, PER = 30, 40


def _library(seed=0):
    """Bias rows of 30 tests: a smooth function of the crush x and the test's speed c, with noise."""
    rng = np.random.default_rng(seed)
    c = np.repeat(np.linspace(0.0, 3.0, N_TESTS), PER)
    x = np.tile(np.linspace(0.0, 2.0, PER), N_TESTS)
    y = np.sin(2 * x) * (1 + 0.3 * c) + 0.05 * rng.standard_normal(c.size) + 0.3 * np.repeat(
        rng.standard_normal(N_TESTS), PER)  # a per-test offset: the test-to-test scatter
    return np.column_stack([x, c]), y, np.repeat(np.arange(N_TESTS), PER)


def test_capped_gp_predicts_as_the_exact_one(monkeypatch):
    """Conditioned on 600 of 1200 rows and 12 scatter refits of 30 tests: mean within 2 % of the bias
    range, latent std at most 1.6x (half the rows), scatter within a factor 1.5 and the test band within
    20 % of the exact GP's."""
    X, y, groups = _library()
    gp = functools.partial(KrigingGP, trend="zero", max_fit_points=300, calibrate_variance=True, estimate_scatter=True,
                           random_state=0)
    capped = gp(max_condition_points=600).fit(X, y, groups)
    monkeypatch.setattr(kriging, "scatter_needs", functools.partial(scatter_needs, max_folds=None, max_rows=None))
    exact = gp(max_condition_points=None).fit(X, y, groups)
    assert capped.n_condition_ < 700 and exact.n_condition_ == len(y)
    grid = np.column_stack([np.linspace(0, 2, 50).repeat(4), np.tile([0.25, 1.1, 2.05, 2.9], 50)])
    (m_c, s_c), (m_e, s_e) = capped.predict(grid, return_std=True), exact.predict(grid, return_std=True)
    np.testing.assert_allclose(m_c, m_e, atol=0.02 * np.ptp(y))
    assert np.all(s_c >= 0.95 * s_e) and np.all(s_c <= 1.6 * s_e)  # half the rows: wider, never narrower
    assert exact.scatter_var_ > 0 and 1 / 1.5 < capped.scatter_var_ / exact.scatter_var_ < 1.5
    band_c, band_e = np.sqrt(s_c**2 + capped.scatter_var_), np.sqrt(s_e**2 + exact.scatter_var_)
    np.testing.assert_allclose(band_c, band_e, rtol=0.2)  # the test band a new test is expected in


def test_every_test_keeps_its_share_of_a_capped_conditioning_set():
    groups = np.repeat(np.arange(20), 50)
    i_fit = np.arange(0, 1000, 10)
    rows = condition_subset(1000, i_fit, 400, np.random.RandomState(0), groups)
    assert set(i_fit) <= set(rows) and 380 <= len(rows) <= 420
    counts = np.bincount(groups[rows])
    assert counts.min() >= 0.8 * counts.max()
    np.testing.assert_array_equal(condition_subset(300, i_fit[:30], None, None, groups[:300]), np.arange(300))
