"""The auto model's inner error: held-out residuals of the whole bias model, and the choice among candidates."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.method.mixture import GMMGPBias
from crashfuse.method.onset import OnsetCorrectedBias
from crashfuse.method.selection import choose


def _tests(seed=0, n_tests=8, per=25, depends_on_c=True):
    """Bias rows of ``n_tests`` tests: a smooth function of x (and of c, constant within a test, like v0)."""
    rng = np.random.default_rng(seed)
    c = np.repeat(np.linspace(0.0, 3.0, n_tests), per)
    x = np.tile(np.linspace(0.0, 2.0, per), n_tests)
    y = np.sin(2 * x) * (1.0 + c * depends_on_c) + 0.02 * rng.standard_normal(c.size)
    return np.column_stack([x, c]), y, np.repeat(np.arange(n_tests), per)


def _mse(est, X, y, groups):
    return float(np.mean(est.fit(X, y, groups).held_out_residuals(X, y, groups) ** 2))


def test_the_candidate_that_sees_the_cause_of_the_bias_is_chosen():
    """Right by construction: the bias grows with c; a candidate without c cannot predict a left-out test."""
    X, y, groups = _tests()
    blind = GMMGPBias(cluster_inputs=[0], random_state=0)
    scores = [_mse(blind, X[:, :1], y, groups), _mse(GMMGPBias(random_state=0), X, y, groups)]
    assert scores[1] < 0.1 * scores[0]
    assert choose(scores).index == 1


def test_a_cluster_holding_one_test_cannot_be_scored():
    """Its test cannot be left out: no score (None), so the auto model never picks it."""
    X, y, groups = _tests()
    X = np.vstack([X, np.column_stack([np.linspace(0, 2, 25), np.full(25, 40.0)])])  # one far-away test
    y, groups = np.append(y, 1 + 0.3 * np.sin(np.linspace(0, 2, 25))), np.append(groups, np.full(25, 99))
    est = GMMGPBias(n_clusters=2, cluster_inputs=[1], min_cluster_points=10).fit(X, y, groups)
    assert len(est.gps_) == 2
    assert est.held_out_residuals(X, y, groups) is None
    assert choose([np.inf, 3.0]).index == 1
    with pytest.raises(ValueError, match="finite"):
        choose([np.inf, np.inf])


def test_a_more_complex_candidate_must_earn_its_place():
    """Listed simplest first, a candidate replaces the choice only by removing MIN_GAIN of its error."""
    assert choose([10.0, 9.5, 9.2]).index == 0  # small gains: the simplest stays
    assert choose([10.0, 8.0, 7.5]).index == 1  # 20 % off K1; K3 only 6 % off K2
    assert choose([10.0, 9.5, 8.5]).index == 2  # judged against the current choice, not its neighbour
    assert choose([10.0, 9.5, 8.5], min_gain=0.0).index == 2 and choose([3.0, 2.0], min_gain=0.5).index == 0


def test_pooled_cluster_gps_count_where_they_speak_only():
    """A pooled model's held-out residuals are the pooled GP's, less each speaking cluster GP's held-out prediction."""
    X, y, groups = _tests(n_tests=10, depends_on_c=False)
    y = y + np.where(X[:, 1] > 1.5, 0.8 * np.cos(3 * X[:, 0]), 0.0)  # a second regime in the upper half of c
    est = GMMGPBias(n_clusters=2, cluster_inputs=[1], pooled=True, random_state=0).fit(X, y, groups)
    pooled_only = est.grouped_residuals(X, y, groups)
    est.residual_var_ = np.zeros(2)  # no cluster GP speaks: the pooled GP's residuals
    np.testing.assert_array_equal(est.held_out_residuals(X, y, groups), pooled_only)
    est.residual_var_ = np.array([0.0, 1.0])  # cluster GP 1 speaks: its rows change, the others do not
    whole = est.held_out_residuals(X, y, groups)
    rows = np.argmax(est.predict_responsibilities(X), axis=1) == 1
    np.testing.assert_array_equal(whole[~rows], pooled_only[~rows])
    r = y[rows] - est.pooled_gp_.predict(X[rows])  # what cluster GP 1 was fitted on
    said = r - est.gps_[1].grouped_residuals(X[rows], r, groups[rows])  # its held-out prediction
    assert np.abs(said).max() > 1e-6
    np.testing.assert_allclose(pooled_only[rows] - whole[rows], said, rtol=1e-9, atol=1e-12)


def test_the_onset_correction_counts_only_early_and_held_out():
    """The correction GP changes the early held-out residuals only (faded out by the window's end), and
    there it predicts a left-out test better than the base model alone."""
    X, y, groups = _tests()

    def time(Z):  # like s / v0: a step at a fixed time lies at another x in every test
        return Z[:, 0] / (1.0 + Z[:, 1])

    y = y + np.where(time(X) < 0.15, 0.5, 0.0)  # an early step the base model smooths over
    base = GMMGPBias(random_state=0)
    est = OnsetCorrectedBias(base=base, time=time, window=(0.25, 0.35)).fit(X, y, groups)
    e_base = est.base_.held_out_residuals(X, y, groups)
    e = est.held_out_residuals(X, y, groups)
    late = time(X) >= 0.35
    np.testing.assert_array_equal(e[late], e_base[late])
    assert est.onset_gp_ is not None
    assert np.mean(e[~late] ** 2) < 0.8 * np.mean(e_base[~late] ** 2)
