"""Tests for crashfuse.gp.kriging: kriging checked against independent derivations and sklearn."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime
from sklearn.base import clone
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, DotProduct, WhiteKernel

from crashfuse.gp.kriging import KrigingGP
from crashfuse.method.config import MethodConfig
from crashfuse.method.mixture import GMMGPBias, TooFewPointsError
from crashfuse.method.onset import OnsetCorrectedBias
from crashfuse.method.projection import bias_columns


def _oracle_loglik(eta, Z, u, trend):
    """Concentrated log-likelihood written directly from Eq. 18 with dense solves.

    Independent of the estimator's Cholesky/GLS code: beta = (H'K^-1H)^-1 H'K^-1 u,
    sigma^2 = r'K^-1 r / n, ll = -n/2 log(2 pi sigma^2) - 1/2 log|K| - n/2.
    """
    n, d = Z.shape
    theta, nugget = np.exp(eta[:d]), np.exp(eta[d])
    diff2 = (Z[:, None, :] - Z[None, :, :]) ** 2
    K = np.exp(-(diff2 * theta).sum(-1)) + nugget * np.eye(n)
    H = _oracle_design(Z, trend)
    Kinv_H, Kinv_u = np.linalg.solve(K, H), np.linalg.solve(K, u)
    beta = np.linalg.solve(H.T @ Kinv_H, H.T @ Kinv_u)
    r = u - H @ beta
    sigma2 = r @ np.linalg.solve(K, r) / n
    return -0.5 * n * np.log(2 * np.pi * sigma2) - 0.5 * np.linalg.slogdet(K)[1] - 0.5 * n


def _oracle_design(Z, trend):
    """Trend basis: none (simple kriging), [1] or [1, z]."""
    n = len(Z)
    return {"zero": np.empty((n, 0)), "constant": np.ones((n, 1)), "linear": np.column_stack([np.ones(n), Z])}[trend]


def _standardised(gp, X, y):
    """The (Z, u) the estimator's likelihood sees (no subsampling at these sizes; no centring without a trend)."""
    Z = gp.scaler_.transform(X)
    return Z, (y - (0.0 if gp.trend == "zero" else y.mean())) / y.std()


@pytest.fixture(scope="module")
def noisy_2d():
    rng = np.random.default_rng(1)
    X = rng.uniform(-2, 2, (40, 2))
    y = np.sin(1.5 * X[:, 0]) + 0.4 * X[:, 1] + 0.05 * rng.standard_normal(40)
    return X, y


# ------------------------------------------------------------------- KrigingGP
def test_recovers_known_function_noise_free():
    X = np.linspace(0, 6, 25)[:, None]
    gp = KrigingGP(random_state=0).fit(X, np.sin(X[:, 0]))
    Xt = np.linspace(0.1, 5.9, 97)[:, None]
    mean, std = gp.predict(Xt, return_std=True)
    assert np.max(np.abs(mean - np.sin(Xt[:, 0]))) < 1e-4
    assert gp.nugget_ < 1e-5
    assert np.all(std < 1e-3)


def test_recovers_known_function_noisy():
    rng = np.random.default_rng(2)
    noise = 0.1
    X = rng.uniform(0, 6, (150, 1))
    y = np.sin(X[:, 0]) + noise * rng.standard_normal(150)
    gp = KrigingGP(random_state=0).fit(X, y)
    Xt = np.linspace(0.2, 5.8, 50)[:, None]
    mean = gp.predict(Xt)
    assert np.max(np.abs(mean - np.sin(Xt[:, 0]))) < 0.1  # noise averaged over ~25 neighbours
    # the estimated noise variance sigma^2 * nugget recovers the true one within 30 %
    assert np.sqrt(gp.sigma2_ * gp.nugget_) == pytest.approx(noise, rel=0.3)


@pytest.mark.parametrize("trend", ["zero", "constant", "linear"])
def test_loglik_matches_dense_oracle(noisy_2d, trend):
    X, y = noisy_2d
    gp = KrigingGP(trend=trend, random_state=0).fit(X, y)
    Z, u = _standardised(gp, X, y)
    for eta in ([0.0, 0.0, -3.0], [-2.0, 1.0, -6.0], [1.5, -1.0, -1.0]):
        assert gp.log_marginal_likelihood(eta) == pytest.approx(_oracle_loglik(np.array(eta), Z, u, trend), abs=1e-7)


@pytest.mark.parametrize("trend", ["zero", "constant", "linear"])
def test_analytic_gradient_matches_finite_differences(noisy_2d, trend):
    X, y = noisy_2d
    gp = KrigingGP(trend=trend, random_state=0).fit(X, y)
    for eta in (np.array([0.3, -1.0, -4.0]), np.array([-1.5, 0.5, -1.0])):
        _, grad = gp.log_marginal_likelihood(eta, eval_gradient=True)
        fd = approx_fprime(eta, lambda e: _oracle_loglik(e, *_standardised(gp, X, y), trend), 1e-6)
        np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-4)


def test_mle_matches_brute_force_scan_1d():
    rng = np.random.default_rng(3)
    X = rng.uniform(0, 5, (30, 1))
    y = np.cos(1.3 * X[:, 0]) + 0.05 * rng.standard_normal(30)
    gp = KrigingGP(random_state=0).fit(X, y)
    Z, u = _standardised(gp, X, y)
    lt, ln = np.linspace(-4, 4, 81), np.linspace(-12, 1, 53)
    scan = np.array([[_oracle_loglik(np.array([a, b]), Z, u, "constant") for b in ln] for a in lt])
    i, j = np.unravel_index(np.argmax(scan), scan.shape)
    assert gp.log_marginal_likelihood_value_ >= scan.max() - 1e-6
    assert abs(np.log(gp.theta_[0]) - lt[i]) <= lt[1] - lt[0]
    assert abs(np.log(gp.nugget_) - ln[j]) <= 2 * (ln[1] - ln[0])


def test_mle_matches_brute_force_scan_2d(noisy_2d):
    X, y = noisy_2d
    gp = KrigingGP(trend="linear", random_state=0).fit(X, y)
    Z, u = _standardised(gp, X, y)
    # inside the bounds: theta2 sits on its lower bound (the trend already has x2)
    lo = np.log(gp.theta_bounds[0])
    g1, g2, gn = np.linspace(lo, 3, 33), np.linspace(lo, 1, 33), np.linspace(-9, -1, 17)
    best, arg = -np.inf, None
    for a in g1:
        for b in g2:
            for c in gn:
                val = _oracle_loglik(np.array([a, b, c]), Z, u, "linear")
                if val > best:
                    best, arg = val, (a, b, c)
    assert gp.log_marginal_likelihood_value_ >= best - 1e-6
    eta = np.r_[np.log(gp.theta_), np.log(gp.nugget_)]
    steps = np.array([g1[1] - g1[0], g2[1] - g2[0], gn[1] - gn[0]])
    assert np.all(np.abs(eta - np.array(arg)) <= 2 * steps)  # correlated ridge: two grid steps


@pytest.mark.parametrize("trend", ["zero", "constant", "linear"])
def test_predictive_variance_matches_bordered_kriging_system(noisy_2d, trend):
    """BLUP with unknown beta from the Lagrangian system [[K, H], [H', 0]] [w; l] = [r; h]."""
    X, y = noisy_2d
    gp = KrigingGP(trend=trend, normalize_y=False, random_state=0).fit(X[:12], y[:12])
    Z = gp.scaler_.transform(X[:12])
    Xs = np.array([[0.1, 0.2], [1.9, -1.9], [4.0, 4.0]])
    Zs = gp.scaler_.transform(Xs)
    n = len(Z)
    K = np.exp(-(((Z[:, None] - Z[None]) ** 2) * gp.theta_).sum(-1)) + gp.nugget_ * np.eye(n)
    r = np.exp(-(((Z[:, None] - Zs[None]) ** 2) * gp.theta_).sum(-1))
    H, h = _oracle_design(Z, trend), _oracle_design(Zs, trend).T
    p = H.shape[1]
    A = np.block([[K, H], [H.T, np.zeros((p, p))]])
    rhs = np.vstack([r, h])
    sol = np.linalg.solve(A, rhs)
    mean = sol[:n].T @ y[:12]
    var = gp.sigma2_ * (1.0 - np.einsum("ij,ij->j", rhs, sol))
    m, s = gp.predict(Xs, return_std=True)
    np.testing.assert_allclose(m, mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(s, np.sqrt(var), rtol=1e-6)


def test_gls_form_matches_bayesian_form_as_prior_broadens(noisy_2d):
    """sklearn GPR with a linear kernel (prior beta ~ N(0, B I)) tends to the GLS kriging form."""
    X, y = noisy_2d
    gp = KrigingGP(trend="linear", normalize_y=False, random_state=0).fit(X, y)
    Z = gp.scaler_.transform(X)
    Zs = gp.scaler_.transform(np.array([[0.0, 0.0], [1.5, -1.0], [3.5, 3.0], [8.0, -6.0]]))
    m_k, s_k = gp.predict(gp.scaler_.inverse_transform(Zs), return_std=True, include_noise=True)
    errors = []
    for B in (1e0, 1e2, 1e4):
        kernel = (ConstantKernel(gp.sigma2_, "fixed") * RBF(1 / np.sqrt(2 * gp.theta_), "fixed")
                  + ConstantKernel(B * gp.sigma2_, "fixed") * DotProduct(1.0, "fixed")
                  + WhiteKernel(gp.sigma2_ * gp.nugget_, "fixed"))
        sk = GaussianProcessRegressor(kernel, alpha=0.0, optimizer=None).fit(Z, y)
        m_b, s_b = sk.predict(Zs, return_std=True)  # sklearn's std includes the WhiteKernel
        errors.append(max(np.max(np.abs(m_b - m_k) / s_k), np.max(np.abs(s_b / s_k - 1))))
    # the gap closes like 1/B (measured: 6e-2, 7e-4, 7e-6) and is tiny at B = 1e4
    assert errors[0] > 30 * errors[1] > 900 * errors[2]
    assert errors[2] < 5e-5


@pytest.mark.parametrize("trend", ["zero", "constant", "linear"])
def test_function_draws_have_predicted_mean_and_width(noisy_2d, trend):
    X, y = noisy_2d
    gp = KrigingGP(trend=trend, random_state=0).fit(X, y)
    grid = np.column_stack([np.linspace(-3, 3, 60), np.full(60, 0.5)])  # 1-D line, leaves the data
    mean, std = gp.predict(grid, return_std=True)
    n = 4000
    draws = gp.sample_functions(grid, n, random_state=7)
    assert draws.shape == (n, 60)
    np.testing.assert_allclose(draws.std(axis=0), std, rtol=0.06)  # std error ~1.1 %
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 5 * std / np.sqrt(n))
    # joint draws are smooth: neighbouring grid values are strongly correlated
    cov = gp.predict_cov(grid)[1]
    emp = np.cov(draws.T)
    np.testing.assert_allclose(emp[0, 1], cov[0, 1], rtol=0.1, atol=0.06 * std[0] * std[1])
    np.testing.assert_array_equal(draws, gp.sample_functions(grid, n, random_state=7))


def test_reverts_to_trend_with_widening_band_far_from_data(noisy_2d):
    X, y = noisy_2d
    gp = KrigingGP(trend="linear", random_state=0).fit(X, y)
    far = np.column_stack([np.linspace(3, 40, 30), np.zeros(30)])
    mean, std = gp.predict(far, return_std=True)
    trend = np.column_stack([np.ones(30), gp.scaler_.transform(far)]) @ gp.beta_
    np.testing.assert_allclose(mean[-10:], trend[-10:], atol=1e-8 * np.abs(trend).max())
    assert np.all(np.diff(std) > 0)
    assert std[-1] > np.sqrt(gp.sigma2_)  # trend uncertainty on top of the process variance


def test_constant_trend_far_variance_includes_trend_term():
    rng = np.random.default_rng(4)
    X = rng.uniform(0, 1, (20, 1))
    gp = KrigingGP(random_state=0).fit(X, np.sin(4 * X[:, 0]))
    mean, std = gp.predict(np.array([[100.0]]), return_std=True)
    assert mean[0] == pytest.approx(gp.beta_[0], rel=1e-10)
    assert np.sqrt(gp.sigma2_) < std[0] < np.sqrt(2 * gp.sigma2_)


def test_linear_trend_drops_constant_and_collinear_columns():
    rng = np.random.default_rng(5)
    s = np.tile(np.linspace(0, 0.6, 30), 2)
    v0 = np.repeat([10.0, 15.0], 30)
    X = np.column_stack([s, v0, 2 * v0 + 1, np.full(60, 900.0)])  # col 2 collinear, col 3 constant
    y = np.sin(5 * s) * v0 / 10 + 0.01 * rng.standard_normal(60)
    gp = KrigingGP(trend="linear", random_state=0).fit(X, y)
    assert gp.trend_columns_ == [0, 1]
    mean, std = gp.predict(X, return_std=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
    assert np.max(np.abs(mean - y)) < 0.05


def test_subsample_fit_close_to_exact():
    rng = np.random.default_rng(6)
    X = rng.uniform(0, 1, (600, 2))
    f = lambda A: np.sin(6 * A[:, 0]) * A[:, 1]
    y = f(X) + 0.02 * rng.standard_normal(600)
    Xt = rng.uniform(0.05, 0.95, (200, 2))
    exact = KrigingGP(max_fit_points=None, random_state=0).fit(X, y)
    sub = KrigingGP(max_fit_points=150, max_condition_points=300, random_state=0).fit(X, y)
    assert sub.n_condition_ == 300 and exact.n_condition_ == 600
    rmse = lambda gp: np.sqrt(np.mean((gp.predict(Xt) - f(Xt)) ** 2))
    assert rmse(exact) < 0.01 and rmse(sub) < 0.01  # noise 0.02; measured 0.0047, 0.0066


@pytest.mark.parametrize("bad", [
    dict(X=np.zeros((2, 1)), y=np.zeros(2)),
    dict(X=np.array([[0.0], [np.nan], [1.0], [2.0]]), y=np.arange(4.0)),
    dict(X=np.arange(10.0)[:, None], y=np.full(10, 3.0)),
])
def test_bad_input_raises_value_error(bad):
    with pytest.raises(ValueError):
        KrigingGP().fit(bad["X"], bad["y"])


def test_unknown_trend_raises():
    with pytest.raises(ValueError, match="trend"):
        KrigingGP(trend="quadratic").fit(np.arange(10.0)[:, None], np.arange(10.0))


def test_estimator_manners():
    gp = KrigingGP(trend="linear", random_state=3)
    assert clone(gp).get_params() == gp.get_params()
    X = np.linspace(0, 1, 15)[:, None]
    assert gp.fit(X, X[:, 0] ** 2) is gp
    assert not hasattr(clone(gp), "theta_")


# ------------------------------------------------------------------- GMMGPBias
def _two_regime_data(seed=0):
    """Bias on a displacement grid for six 'tests': low speeds follow f_lo(s), high f_hi(s)."""
    rng = np.random.default_rng(seed)
    rows, ys = [], []
    for v0 in (8.0, 9.0, 10.0, 15.0, 16.0, 17.0):
        s = np.linspace(0, 0.5, 40)
        bias = 20 * np.sin(8 * s) if v0 < 12 else -30 * s + 5 * np.cos(12 * s)
        rows.append(np.column_stack([s, np.full(40, v0), np.full(40, 1000 + 10 * v0)]))
        ys.append(bias + 0.2 * rng.standard_normal(40))
    return np.vstack(rows), np.concatenate(ys)


@pytest.fixture(scope="module")
def two_regimes():
    X, y = _two_regime_data()
    model = GMMGPBias(n_clusters=2, cluster_inputs=[1, 2], random_state=0).fit(X, y)
    return X, y, model


def test_gmm_separates_regimes_and_predicts_each(two_regimes):
    X, y, model = two_regimes
    low = X[:, 1] < 12
    assert len(model.gps_) == 2
    assert len(set(model.labels_[low])) == 1 and len(set(model.labels_[~low])) == 1
    assert model.labels_[low][0] != model.labels_[~low][0]
    np.testing.assert_array_equal(np.sort(model.n_points_per_cluster_), [120, 120])
    s = np.linspace(0.02, 0.48, 20)
    new_lo = np.column_stack([s, np.full(20, 9.5), np.full(20, 1095.0)])
    new_hi = np.column_stack([s, np.full(20, 16.5), np.full(20, 1165.0)])
    assert np.max(np.abs(model.predict(new_lo) - 20 * np.sin(8 * s))) < 1.0
    assert np.max(np.abs(model.predict(new_hi) - (-30 * s + 5 * np.cos(12 * s)))) < 1.0


def test_select_uses_most_responsible_gp(two_regimes):
    X, _, model = two_regimes
    resp = model.predict_responsibilities(X)
    np.testing.assert_allclose(resp.sum(axis=1), 1.0)
    pick = np.argmax(resp, axis=1)
    mean, std = model.predict(X, return_std=True)
    for g, gp in enumerate(model.gps_):
        m, s = gp.predict(X[pick == g], return_std=True)
        np.testing.assert_allclose(mean[pick == g], m)
        np.testing.assert_allclose(std[pick == g], s, rtol=1e-10)


def test_blend_is_mixture_of_cluster_predictions(two_regimes):
    X, y, select = two_regimes
    blend = clone(select).set_params(assignment="blend").fit(X, y)
    Xb = np.column_stack([np.full(5, 0.2), np.linspace(8, 17, 5), 1000 + 10 * np.linspace(8, 17, 5)])
    w = blend.predict_responsibilities(Xb)
    mus, sds = zip(*(gp.predict(Xb, return_std=True) for gp in blend.gps_))
    mus, sds = np.array(mus).T, np.array(sds).T
    mean, std = blend.predict(Xb, return_std=True)
    np.testing.assert_allclose(mean, (w * mus).sum(axis=1))
    # law of total variance for the mixture
    np.testing.assert_allclose(std**2, (w * sds**2).sum(1) + (w * (mus - mean[:, None]) ** 2).sum(1))
    # on the training tests responsibilities are one-hot, so blend equals select there
    np.testing.assert_allclose(blend.predict(X), select.predict(X), atol=1e-6 * np.abs(y).max())


def _assert_draws_have_predicted_width(model):
    grid = np.column_stack([np.linspace(0, 0.7, 50), np.full(50, 12.0), np.full(50, 1120.0)])
    mean, std = model.predict(grid, return_std=True)
    draws = model.sample_functions(grid, 3000, random_state=1)
    np.testing.assert_allclose(draws.std(axis=0), std, rtol=0.07)
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 5 * std / np.sqrt(3000))
    np.testing.assert_array_equal(draws, model.sample_functions(grid, 3000, random_state=1))


def test_mixture_draws_have_predicted_width(two_regimes):
    _assert_draws_have_predicted_width(two_regimes[2])


def test_small_clusters_merge_not_nan():
    X, y = _two_regime_data(1)
    model = GMMGPBias(n_clusters=3, cluster_inputs=[1], min_cluster_points=150, random_state=0).fit(X, y)
    assert len(model.gps_) < 3
    assert model.n_points_per_cluster_.sum() == len(y)
    assert np.all(model.n_points_per_cluster_ >= 150) or len(model.gps_) == 1
    mean, std = model.predict(X, return_std=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
    assert model.predict_responsibilities(X).shape == (len(y), len(model.gps_))


@pytest.mark.filterwarnings("ignore:Number of distinct clusters")  # k-means init, expected here
def test_components_without_points_get_no_gp():
    X, y = _two_regime_data()
    # eight components on six distinct v0 values: some components own no training point
    model = GMMGPBias(n_clusters=8, cluster_inputs=[1], min_cluster_points=1, random_state=0).fit(X, y)
    assert len(model.gps_) <= 6
    assert np.all(model.n_points_per_cluster_ > 0)
    assert np.all(np.isfinite(model.predict(X)))


def test_too_few_points_raises():
    X, y = _two_regime_data()
    with pytest.raises(TooFewPointsError, match="at least"):
        GMMGPBias(n_clusters=2, trend="linear").fit(X[:20], y[:20])


def test_same_seed_same_model():
    X, y = _two_regime_data()
    a = GMMGPBias(n_clusters=2, random_state=11).fit(X, y)
    b = GMMGPBias(n_clusters=2, random_state=11).fit(X, y)
    np.testing.assert_array_equal(a.predict(X), b.predict(X))


# ------------------------------------------------- grouped CV and the theta bound
def _grouped_data(seed=0, n_groups=6, per=12):
    """Smooth function of (x, c) where c is constant within a group (like v0 within a test)."""
    rng = np.random.default_rng(seed)
    c = np.repeat(rng.uniform(0, 3, n_groups), per)
    x = np.tile(np.linspace(0, 2, per), n_groups)
    y = np.sin(2 * x) + 0.5 * c + 0.02 * rng.standard_normal(c.size)
    return np.column_stack([x, c]), y, np.repeat(np.arange(n_groups), per)


def test_grouped_cv_matches_brute_force_refits():
    """Closed form vs refitting beta (GLS) without each group at the same theta, nugget, sigma^2."""
    X, y, groups = _grouped_data()
    gp = KrigingGP(trend="linear", max_fit_points=None).fit(X, y, groups)
    Z, u = _standardised(gp, X, y)
    diff2 = (Z[:, None, :] - Z[None, :, :]) ** 2
    K = np.exp(-(diff2 * gp.theta_).sum(-1)) + gp.nugget_ * np.eye(len(u))
    H = np.column_stack([np.ones(len(u)), Z])
    sigma2 = gp.sigma2_ / y.std() ** 2
    total = 0.0
    for g in np.unique(groups):
        out, keep = groups == g, groups != g
        Kk = K[np.ix_(keep, keep)]
        beta = np.linalg.solve(H[keep].T @ np.linalg.solve(Kk, H[keep]), H[keep].T @ np.linalg.solve(Kk, u[keep]))
        k_star = K[np.ix_(out, keep)]
        mean = H[out] @ beta + k_star @ np.linalg.solve(Kk, u[keep] - H[keep] @ beta)
        # variance with the trend-estimation term (universal kriging), noisy observation
        U = H[out].T - H[keep].T @ np.linalg.solve(Kk, k_star.T)
        M = H[keep].T @ np.linalg.solve(Kk, H[keep])
        var = sigma2 * (np.diag(K[np.ix_(out, out)]) - np.einsum("ij,ji->i", k_star, np.linalg.solve(Kk, k_star.T))
                        + np.einsum("ji,ji->i", U, np.linalg.solve(M, U)))
        total += np.sum(-0.5 * (np.log(2 * np.pi * var) + (u[out] - mean) ** 2 / var))
    assert gp.grouped_cv_log_density() == pytest.approx(total / len(u), rel=1e-6)


@pytest.mark.parametrize("trend", ["zero", "constant"])
def test_grouped_residuals_match_conditioning_on_the_other_groups(trend):
    """Each group's residual is y minus the prediction of the GP conditioned on the other groups
    alone (same theta, nugget; the trend re-estimated)."""
    X, y, groups = _grouped_data()
    gp = KrigingGP(trend=trend, max_fit_points=None).fit(X, y, groups)
    Z, u = _standardised(gp, X, y)
    if trend == "zero":
        u = y / y.std()  # a zero-mean prior is not centred
    K = np.exp(-(((Z[:, None, :] - Z[None, :, :]) ** 2) * gp.theta_).sum(-1)) + gp.nugget_ * np.eye(len(u))
    H = np.ones((len(u), int(trend == "constant")))
    expected = np.empty(len(u))
    for g in np.unique(groups):
        out, keep = groups == g, groups != g
        Kk = K[np.ix_(keep, keep)]
        beta = (np.linalg.solve(H[keep].T @ np.linalg.solve(Kk, H[keep]), H[keep].T @ np.linalg.solve(Kk, u[keep]))
                if H.shape[1] else np.zeros(0))
        mean = H[out] @ beta + K[np.ix_(out, keep)] @ np.linalg.solve(Kk, u[keep] - H[keep] @ beta)
        expected[out] = u[out] - mean
    scale = y.std()
    np.testing.assert_allclose(gp.grouped_residuals(X, y, groups), expected * scale, atol=1e-8 * scale)
    with pytest.raises(ValueError, match="two groups"):
        gp.grouped_residuals(X, y, np.zeros(len(y)))


def test_theta_bound_is_chosen_by_grouped_cv():
    X, y, groups = _grouped_data(seed=3)
    gp = KrigingGP(theta_max_candidates=(0.1, 1e3)).fit(X, y, groups)
    assert set(gp.cv_scores_) == {0.1, 1e3}
    assert gp.theta_max_ == max(gp.cv_scores_, key=gp.cv_scores_.get)
    assert np.all(gp.theta_ <= gp.theta_max_ * (1 + 1e-9))
    single = KrigingGP(theta_bounds=(1e-5, gp.theta_max_)).fit(X, y, groups)
    np.testing.assert_allclose(single.theta_, gp.theta_, rtol=1e-3)  # same optimum, other restarts
    assert not KrigingGP(theta_max_candidates=(0.1, 1e3)).fit(X, y).cv_scores_  # no groups: no choice


def test_grouped_subset_is_even_within_groups_and_seed_free():
    X, y, groups = _grouped_data(n_groups=5, per=40)
    a = KrigingGP(max_fit_points=50, n_restarts=0, random_state=1).fit(X, y, groups)
    b = KrigingGP(max_fit_points=50, n_restarts=0, random_state=2).fit(X, y, groups)
    np.testing.assert_array_equal(a.Z_fit_, b.Z_fit_)
    assert np.bincount(a.groups_fit_).tolist() == [10] * 5
    with pytest.raises(ValueError, match="groups"):
        KrigingGP().fit(X, y, groups[:-1])


def test_scatter_is_wider_where_the_held_out_tests_scatter_more():
    """Tests that differ by a per-test offset on x < 1 only and agree on x > 1: the scatter near a point
    is what the held-out tests needed there - wide where they scatter, narrow where they agree - and
    the pooled scatter lies between. Far from every test it falls back on the pooled one."""
    rng = np.random.default_rng(0)
    n_tests, per = 8, 40
    x = np.tile(np.linspace(0.0, 2.0, per), n_tests)
    offset = np.repeat(0.4 * rng.standard_normal(n_tests), per)
    y = np.sin(6 * x) + np.where(x < 1.0, offset, 0.0) + 0.01 * rng.standard_normal(x.size)
    gp = KrigingGP(trend="zero", calibrate_variance=True, estimate_scatter=True, random_state=0).fit(
        x[:, None], y, np.repeat(np.arange(n_tests), per))
    spread, agree, far = gp.scatter_var_at(np.array([[0.4], [1.7], [40.0]]))
    assert agree < 0.2 * gp.scatter_var_ < 0.2 * spread
    assert agree < 0.01 and spread > 0.02  # offsets of std 0.4 against noise of 0.01
    np.testing.assert_allclose(far, gp.scatter_var_, rtol=0.1)


def test_the_held_out_errors_need_a_band_wide_where_the_tests_scatter_and_narrow_where_they_agree():
    """Tests offset on x < 1 only: the variance a held-out test's errors need near a point is at least
    the scatter there (the latent variance added back), wide where the tests scatter, narrow where they
    agree; a GP fitted without tests has no such bound."""
    rng = np.random.default_rng(0)
    n_tests, per = 8, 40
    x = np.tile(np.linspace(0.0, 2.0, per), n_tests)
    y = np.sin(6 * x) + np.where(x < 1.0, np.repeat(0.4 * rng.standard_normal(n_tests), per), 0.0)
    groups = np.repeat(np.arange(n_tests), per)
    gp = KrigingGP(trend="zero", calibrate_variance=True, random_state=0).fit(x[:, None], y, groups)
    at = np.array([[0.4], [1.7]])
    need = gp.held_out_var_at(at)
    assert np.all(need >= gp.scatter_var_at(at)) and need[1] < 0.1 * need[0]
    assert np.all(np.isinf(KrigingGP(random_state=0).fit(x[:, None], y).held_out_var_at(at)))


def test_scatter_of_a_model_fitted_before_it_existed_is_a_clear_error(two_regimes):
    import copy

    from crashfuse.errors import InputError
    X, _, model = two_regimes
    assert np.all(model.scatter_std(X[:3]) == 0.0)  # no groups: no scatter estimated
    old = copy.deepcopy(model)
    del old.gps_[0].scatter_var_
    with pytest.raises(InputError, match="refit"):
        old.scatter_std(X[:3])


# ------------------------------------------------------------------ fast paths
def test_likelihood_linear_algebra_is_bit_identical_to_the_plain_forms():
    """The symmetric correlation, the in-place factor and the mirrored inverse give exactly the bits
    of the plain expressions they stand for: the optimiser's path, and so every score, depends on them."""
    from scipy.linalg import cholesky, lapack

    from crashfuse.gp.kernels import correlation, factor_with_nugget, inverse_from_factor, self_correlation
    rng = np.random.default_rng(3)
    Z, theta, nugget = rng.normal(size=(120, 4)), np.array([0.3, 5.0, 1e-4, 80.0]), 1e-3
    R = self_correlation(Z, theta)
    np.testing.assert_array_equal(R, correlation(Z, Z, theta))
    plain_L = cholesky(correlation(Z, Z, theta) + nugget * np.eye(len(Z)), lower=True)
    L = factor_with_nugget(R, nugget)
    np.testing.assert_array_equal(L, plain_L)
    Kinv = lapack.dpotri(plain_L, lower=1)[0]
    plain_inverse = np.tril(Kinv) + np.tril(Kinv, -1).T
    inverse, info = inverse_from_factor(L)
    assert info == 0 and inverse.flags.c_contiguous == plain_inverse.flags.c_contiguous
    np.testing.assert_array_equal(inverse, plain_inverse)


@pytest.mark.parametrize("assignment", ["select", "blend"])
def test_mean_alone_equals_the_mean_beside_the_std(assignment):
    X, y = _two_regime_data()
    model = GMMGPBias(n_clusters=2, cluster_inputs=[1, 2], assignment=assignment, random_state=0).fit(X, y)
    np.testing.assert_array_equal(model.predict(X), model.predict(X, return_std=True)[0])
    gp = model.gps_[0]
    np.testing.assert_array_equal(gp.predict(X), gp.predict(X, return_std=True)[0])


def test_zero_trend_reverts_to_zero_far_from_the_data():
    """Simple kriging: beyond the data the bias goes to 0 (the CAE), ordinary kriging to a level."""
    X = np.linspace(0, 4, 30)[:, None]
    y = 3.0 + np.sin(2 * X[:, 0])  # a bias with a clear non-zero level
    far = np.array([[40.0]])
    zero = KrigingGP(trend="zero", random_state=0).fit(X, y)
    const = KrigingGP(trend="constant", random_state=0).fit(X, y)
    assert zero.beta_.size == 0
    assert abs(zero.predict(far)[0]) < 1e-6
    assert const.predict(far)[0] == pytest.approx(const.beta_[0], abs=1e-6)
    assert const.beta_[0] > 2.0
    # inside the data both interpolate
    inside = np.array([[1.3]])
    assert zero.predict(inside)[0] == pytest.approx(3.0 + np.sin(2.6), abs=1e-3)
    # far away the latent variance is sigma^2 alone (no trend-estimation term)
    assert zero.predict(far, return_std=True)[1][0] == pytest.approx(np.sqrt(zero.sigma2_), rel=1e-9)


# ------------------------------------------------------------------ pooled clusters
@pytest.fixture(scope="module")
def pooled_regimes():
    X, y = _two_regime_data()
    groups = np.repeat(np.arange(6), 40)
    model = GMMGPBias(n_clusters=2, cluster_inputs=[1, 2], pooled=True, trend="constant",
                      random_state=0).fit(X, y, groups)
    return X, y, groups, model


def test_pooled_clusters_model_the_residual_of_one_gp_over_all_points(pooled_regimes):
    X, y, groups, model = pooled_regimes
    pooled = model.pooled_gp_
    assert pooled.trend == "constant" and pooled.n_condition_ == len(y)
    np.testing.assert_array_equal(pooled.predict(X), clone(pooled).fit(X, y, groups).predict(X))
    assert all(gp.trend == "zero" and gp.scatter_var_ == 0.0 for gp in model.gps_)
    pick = np.argmax(model.predict_responsibilities(X), axis=1)
    mean, std = model.predict(X, return_std=True)
    p_mean, p_std = pooled.predict(X, return_std=True)
    for g, gp in enumerate(model.gps_):
        rows = pick == g
        # each residual GP is fitted on its cluster's residual of the pooled mean
        np.testing.assert_allclose(gp.predict(X[rows]), (y - pooled.predict(X))[rows], atol=0.05 * np.abs(y).max())
        r_mean, r_std = model._cluster_predict(g, X[rows], return_std=True)
        np.testing.assert_allclose(mean[rows], p_mean[rows] + r_mean, rtol=1e-12)
        np.testing.assert_allclose(std[rows], np.hypot(p_std[rows], r_std), rtol=1e-10)
    np.testing.assert_allclose(model.scatter_std(X), np.sqrt(pooled.scatter_var_at(X)))
    assert pooled.scatter_var_ > 0.0


def test_pooled_draws_add_the_pooled_gp_draw_and_have_the_predicted_width(pooled_regimes):
    _assert_draws_have_predicted_width(pooled_regimes[3])


def test_pooled_prediction_falls_back_on_the_pooled_gp_far_from_the_clusters():
    """Where the residual GPs have no data they revert to 0: the prediction is the pooled model's,
    not a cluster's level as with the paper's independent cluster GPs."""
    X, y = _two_regime_data()
    groups = np.repeat(np.arange(6), 40)
    far = np.column_stack([np.linspace(5.0, 6.0, 5), np.full(5, 40.0), np.full(5, 1400.0)])  # beyond every s
    pooled = GMMGPBias(n_clusters=2, cluster_inputs=[1, 2], pooled=True, trend="constant",
                       random_state=0).fit(X, y, groups)
    np.testing.assert_allclose(pooled.predict(far), pooled.pooled_gp_.predict(far), atol=1e-6 * np.abs(y).max())
    apart = GMMGPBias(n_clusters=2, cluster_inputs=[1, 2], trend="constant").fit(X, y, groups)
    picked = apart.gps_[np.argmax(apart.predict_responsibilities(far)[0])]
    np.testing.assert_allclose(apart.predict(far), picked.beta_[0], atol=1e-6 * np.abs(y).max())


def _noise_tests(seed, n_tests=8, n_points=30):
    """Pure noise as 'bias' of tests at 5-15 m/s: per test a random offset, white and slightly smooth noise.

    Inputs as the state mode's ``[x, sqrt v, v0, w_f, w_r]``; nothing in ``y`` depends on them.
    """
    rng = np.random.RandomState(seed)
    X, y = [], []
    for t in range(n_tests):
        v0 = 5.0 + 10.0 * t / (n_tests - 1)
        x = np.linspace(0.0, 0.04 * v0, n_points)
        v = v0 * np.sqrt(1.0 - 0.95 * x / x[-1])
        X.append(np.column_stack([x, np.sqrt(v), np.full(n_points, v0), np.full(n_points, 1000.0 + 50 * (t % 3)),
                                  np.full(n_points, 700.0 + 40 * (t % 2))]))
        smooth = np.convolve(rng.randn(n_points + 4), np.ones(5) / 5, "valid")
        y.append(0.05 * (smooth / smooth.std() + rng.randn(n_points) + 0.7 * rng.randn()))
    return np.vstack(X), np.concatenate(y), np.repeat(np.arange(n_tests), n_points)


@pytest.mark.parametrize("seed, k", [(0, 3), (4, 3)])
def test_cluster_gps_fitted_to_noise_neither_move_the_mean_nor_widen_the_band(seed, k):
    """On noise the pooled clusters must predict what the pooled model does: the slowest test, held out,
    along its own path and on past its crush. Cluster GPs of two or three tests that each fit their
    tests' noise (theta at its bound, nugget near 0) widened the band there by 35 % (seed 0) and 54 %
    (seed 4) over the pooled model's."""
    X, y, groups = _noise_tests(seed)
    train = groups != 0
    path = np.vstack([X[~train], X[~train] * [1.6, 1, 1, 1, 1]])
    model = GMMGPBias(n_clusters=k, pooled=True, trend="zero", random_state=seed,
                      estimate_scatter=False).fit(X[train], y[train], groups[train])
    mean, std = model.predict(path, return_std=True)
    p_mean, p_std = model.pooled_gp_.predict(path, return_std=True)
    rms = np.sqrt(np.mean(y[train] ** 2))
    assert np.max(np.abs(mean - p_mean)) < 0.1 * rms
    assert np.all(std <= 1.05 * p_std)
    draws = model.sample_functions(path, 400, 1)
    assert np.all(draws.std(axis=0) <= 1.15 * p_std)


def test_cluster_gp_speaks_only_with_enough_tests():
    """A cluster GP whose points come from fewer than ``min_cluster_tests`` tests adds nothing; its prior
    variance is the out-of-sample part of its residual, never more than the residual itself."""
    X, y, groups = _noise_tests(1, n_tests=6)
    strict = GMMGPBias(n_clusters=2, pooled=True, trend="zero", random_state=0, estimate_scatter=False,
                       min_cluster_tests=100).fit(X, y, groups)
    assert np.all(strict.residual_var_ == 0.0)
    np.testing.assert_array_equal(strict.predict(X), strict.pooled_gp_.predict(X))
    np.testing.assert_array_equal(strict.sample_functions(X[:40], 3, 0),
                                  strict.pooled_gp_.sample_functions(X[:40], 3, np.random.RandomState(0).randint(
                                      2**31 - 1, size=len(strict.gps_) + 1)[-1]))
    free = GMMGPBias(n_clusters=2, pooled=True, trend="zero", random_state=0, estimate_scatter=False,
                     min_cluster_tests=2).fit(X, y, groups)
    residual = y - free.pooled_gp_.predict(X)
    for g in range(len(free.gps_)):
        assert 0.0 <= free.residual_var_[g] <= np.mean(residual[free.labels_ == g] ** 2)


def test_pooled_with_one_cluster_is_the_plain_model():
    X, y = _two_regime_data()
    groups = np.repeat(np.arange(6), 40)
    plain = GMMGPBias(n_clusters=1, random_state=3).fit(X, y, groups)
    pooled = GMMGPBias(n_clusters=1, pooled=True, random_state=3).fit(X, y, groups)
    assert pooled.pooled_gp_ is None
    np.testing.assert_array_equal(pooled.predict(X), plain.predict(X))
    np.testing.assert_array_equal(pooled.sample_functions(X[:30], 5, 2), plain.sample_functions(X[:30], 5, 2))


def test_a_larger_k_reuses_the_smaller_ks_gp_as_its_pooled_gp_and_gets_the_same_model():
    """The pooled GP of K = 2 and 3 is the K = 1 model's GP (same rows, settings and seed): taken over,
    the models predict bit for bit what they predict fitted from scratch."""
    X, y = _two_regime_data()
    groups = np.repeat(np.arange(6), 40)
    settings = dict(pooled=True, trend="zero", random_state=5, estimate_scatter=False)
    one = GMMGPBias(n_clusters=1, **settings).fit(X, y, groups)
    for k in (2, 3):
        fresh = GMMGPBias(n_clusters=k, **settings).fit(X, y, groups)
        reused = GMMGPBias(n_clusters=k, **settings).fit(X, y, groups, pooled_gp=one.all_rows_gp())
        assert reused.pooled_gp_ is one.gps_[0] and fresh.all_rows_gp() is fresh.pooled_gp_
        np.testing.assert_array_equal(reused.predict(X, return_std=True), fresh.predict(X, return_std=True))
        np.testing.assert_array_equal(reused.sample_functions(X[:30], 4, 1), fresh.sample_functions(X[:30], 4, 1))


@pytest.mark.parametrize("change", ["rows", "seed", "settings"])
def test_a_pooled_gp_of_another_fit_is_refused(change):
    X, y = _two_regime_data()
    groups = np.repeat(np.arange(6), 40)
    settings = dict(pooled=True, trend="zero", random_state=5, estimate_scatter=False)
    other_rows = groups != 0
    donor = GMMGPBias(n_clusters=1, **{**settings, "random_state": 6 if change == "seed" else 5,
                                        "trend": "constant" if change == "settings" else "zero"})
    donor.fit(*((X[other_rows], y[other_rows], groups[other_rows]) if change == "rows" else (X, y, groups)))
    with pytest.raises(ValueError, match="not this model's pooled GP"):
        GMMGPBias(n_clusters=2, **settings).fit(X, y, groups, pooled_gp=donor.all_rows_gp())


# --------------------------------------------------------------------------- onset correction
def _onset_data(speeds=(4.0, 6.0, 8.0, 10.0, 12.0, 14.0), per=60):
    """Bias = a smooth function of (x, v0) + a ringing locked in time t = x / v0 (gone by t = 1).

    A GP over (x, v0) moves the ringing with speed in x; the time-locked part is what the
    onset correction is for.
    """
    rows = []
    for v0 in speeds:
        x = np.linspace(0.0, 1.6 * v0, per)
        t = x / v0
        y = 0.3 * np.sin(x / 8.0) + 0.02 * v0 + np.sin(2 * np.pi * t / 0.4) * np.exp(-3.0 * t) * (t < 1.0)
        rows.append((np.column_stack([x, np.full(per, v0)]), y, np.full(per, v0)))
    X, y, g = (np.concatenate(c) for c in zip(*rows))
    return X, y, g


def _time(X):
    return X[:, 0] / X[:, 1]


@pytest.fixture(scope="module")
def onset_model():
    X, y, groups = _onset_data()
    base = GMMGPBias(n_clusters=1, trend="zero", random_state=0)
    return OnsetCorrectedBias(base=base, time=_time, window=(1.0, 1.3)).fit(X, y, groups)


def test_onset_correction_learns_the_time_locked_error_of_the_base_model(onset_model):
    """At a new speed the corrected model misses the ringing far less than its base model."""
    X, y, _ = _onset_data(speeds=(9.0,))
    early = _time(X) < 1.0
    base_err = np.abs(onset_model.base_.predict(X) - y)[early].mean()
    err = np.abs(onset_model.predict(X) - y)[early].mean()
    assert err < 0.5 * base_err
    # the correction GP learned the tests' mean leave-one-test-out residual over time, in bins before the window's end
    gp = onset_model.onset_gp_
    assert gp.centres_.max() < 1.3 and np.allclose(gp.bin_width, 1.3 / 22)


def test_onset_correction_fades_out_and_leaves_the_latent_band_to_the_base_model(onset_model):
    X, _, _ = _onset_data(speeds=(9.0,))
    late = _time(X) >= 1.3
    mean, std = onset_model.predict(X, return_std=True)
    base_mean, base_std = onset_model.base_.predict(X, return_std=True)
    np.testing.assert_array_equal(mean[late], base_mean[late])
    np.testing.assert_array_equal(std, base_std)
    draws = onset_model.sample_functions(X, 4, random_state=3)
    np.testing.assert_allclose(draws, onset_model.base_.sample_functions(X, 4, random_state=3)
                               + onset_model.correction(X), rtol=1e-12)
    assert onset_model.gps_ is onset_model.base_.gps_


def test_onset_correction_widens_the_test_scatter_by_its_own_spread_while_it_acts(onset_model):
    """A new test's held-out error lies about the correction as the training tests' residuals lie about the
    correction GP: its predictive std of a new residual (noise included), faded as the correction, is
    added in quadrature to the base model's scatter; past the window the scatter is the base model's."""
    X, _, _ = _onset_data(speeds=(9.0,))
    t = _time(X)
    base = onset_model.base_.scatter_std(X)
    sd = onset_model.onset_gp_.predict(t[:, None], return_std=True, include_noise=True)[1]
    fade = np.clip(np.cos(0.5 * np.pi * np.clip((t - 1.0) / 0.3, 0.0, 1.0)) ** 2, 0.0, 1.0)
    np.testing.assert_allclose(onset_model.scatter_std(X), np.sqrt(base**2 + (fade * sd) ** 2), rtol=1e-12)
    assert np.all(onset_model.scatter_std(X)[t < 1.0] > base[t < 1.0]) and np.all(sd > 0)
    np.testing.assert_allclose(onset_model.scatter_std(X)[t >= 1.3], base[t >= 1.3], rtol=1e-12, atol=1e-15)


def test_onset_correction_needs_three_tests_in_its_window():
    X, y, groups = _onset_data(speeds=(4.0, 6.0))
    model = OnsetCorrectedBias(base=GMMGPBias(trend="zero", random_state=0), time=_time, window=(1.0, 1.3)).fit(X, y, groups)
    assert model.onset_gp_ is None
    np.testing.assert_array_equal(model.predict(X), model.base_.predict(X))


# --------------------------------------------------------------------------- held-out shrinkage
def _incoherent_data(speeds=(4.0, 6.0, 8.0, 10.0, 12.0, 14.0), amplitudes=(1.0, -1.0, 1.0, -1.0, 1.0, -1.0), per=60):
    """Bias over x (here also the time, :func:`_x_time`): one shape for every test before x = 1, then a bump
    of each test's own amplitude - of the opposite sign in the next faster test, so no test's neighbours
    predict it."""
    rows = []
    for v0, amp in zip(speeds, amplitudes):
        x = np.linspace(0.0, 2.0, per)
        y = np.where(x < 1.0, np.sin(np.pi * x), amp * np.sin(2 * np.pi * (x - 1.0)))
        rows.append((np.column_stack([x, np.full(per, v0)]), y, np.full(per, v0)))
    return tuple(np.concatenate(c) for c in zip(*rows))


def _x_time(X):
    return X[:, 0]


@pytest.fixture(scope="module")
def shrunk_model():
    X, y, groups = _incoherent_data()
    base = GMMGPBias(n_clusters=1, trend="zero", random_state=0)
    return OnsetCorrectedBias(base=base, time=_x_time, window=None, shrink_width=0.1).fit(X, y, groups)


def test_held_out_shrinkage_keeps_what_predicts_a_left_out_test_and_drops_the_rest(shrunk_model):
    """The factor is 1 where every test's bias has one shape and 0 where the neighbours' bias says the
    opposite; at a new test without a bump the mean there defers to 0, where the base model carries its
    neighbours' bump, and elsewhere it is the base model's."""
    times, c = shrunk_model.shrink_times_, shrunk_model.shrink_
    assert shrunk_model.onset_gp_ is None and np.all((c >= 0) & (c <= 1))
    assert c[times < 0.7].min() > 0.99 and c[times > 1.3].max() < 0.01
    X, y, _ = _incoherent_data(speeds=(8.4,), amplitudes=(0.0,))
    late = _x_time(X) > 1.3
    base, mean = shrunk_model.base_.predict(X), shrunk_model.predict(X)
    assert np.sqrt(np.mean(base[late] ** 2)) > 0.2 and np.abs(mean[late]).max() < 0.01
    early = _x_time(X) < 0.7
    np.testing.assert_allclose(mean[early], base[early], atol=1e-6)


def test_held_out_shrinkage_moves_the_mean_not_the_spread(shrunk_model):
    """Draws shift with the mean and keep the base model's deviations; the latent std is the base model's;
    the held-out residuals are the bias minus the shrunk held-out prediction."""
    X, y, groups = _incoherent_data()
    c = np.interp(_x_time(X), shrunk_model.shrink_times_, shrunk_model.shrink_)
    mean, std = shrunk_model.predict(X, return_std=True)
    base_mean, base_std = shrunk_model.base_.predict(X, return_std=True)
    np.testing.assert_allclose(mean, c * base_mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(std, base_std)
    draws = shrunk_model.sample_functions(X, 3, random_state=5)
    np.testing.assert_allclose(draws - mean, shrunk_model.base_.sample_functions(X, 3, random_state=5) - base_mean,
                               atol=1e-9)
    e_base = shrunk_model.base_.held_out_residuals(X, y, groups)
    np.testing.assert_allclose(shrunk_model.held_out_residuals(X, y, groups), y - c * (y - e_base), atol=1e-12)


def test_held_out_shrinkage_keeps_room_in_the_test_band_for_what_it_took_off(shrunk_model):
    """A new test may have the bump its neighbours had: what the shrinkage took off the mean adds to the
    test-to-test scatter in quadrature; where it took nothing, the scatter is the base model's."""
    X, _, _ = _incoherent_data(speeds=(8.4,), amplitudes=(0.0,))
    c = np.interp(_x_time(X), shrunk_model.shrink_times_, shrunk_model.shrink_)
    base, taken = shrunk_model.base_.scatter_std(X), (1 - c) * shrunk_model.base_.predict(X)
    np.testing.assert_allclose(shrunk_model.scatter_std(X), np.sqrt(base**2 + taken**2), rtol=1e-12)
    late, early = _x_time(X) > 1.3, _x_time(X) < 0.7
    assert np.all(shrunk_model.scatter_std(X)[late] >= base[late]) and np.abs(taken[late]).max() > 0.2
    np.testing.assert_allclose(shrunk_model.scatter_std(X)[early], base[early], rtol=1e-9)


def test_shrink_profile_is_the_windowed_least_squares_scale_clipped_to_0_1():
    from crashfuse.method.onset import shrink_profile

    t = np.array([0.0, 0.0, 1.0, 1.0, 2.0])
    y = np.array([1.0, 2.0, 1.0, -1.0, 0.0])
    m = np.array([2.0, 2.0, 1.0, 1.0, 0.0])
    got = shrink_profile(np.array([0.0, 1.0, 2.0]), t, y, m, 1e-3)  # narrow: each time sees its own rows
    np.testing.assert_allclose(got, [6.0 / 8.0, 0.0, 1.0])  # 0.75; sum y m = 0 -> 0; nothing to judge by -> 1
    assert shrink_profile(np.array([0.0]), t[:2], -y[:2], m[:2], 1e-3)[0] == 0.0  # a negative scale clips to 0
    assert shrink_profile(np.array([0.0]), t[:2], 3 * m[:2], m[:2], 1e-3)[0] == 1.0  # never amplifies


def _labelled_tests(step, seed):
    """Eight tests' state rows and a bias over crush, plus ``step`` after 0.3 m on the tests of one label."""
    rng = np.random.default_rng(seed)
    columns = bias_columns("state", {"powertrain": ["Type I", "Type II"]}, velocity="sqrt")
    X, y, groups = [], [], []
    s = np.linspace(0.0, 0.6, 40)
    for i in range(8):
        v0, label = rng.uniform(5.0, 16.0), i % 2
        v = v0 * np.sqrt(1.0 - 1.5 * s)
        X.append(np.column_stack([s, np.sqrt(v), np.full(40, v0), np.full(40, 1000 + 50 * rng.standard_normal()),
                                  np.full(40, 700 + 50 * rng.standard_normal()), np.full(40, label)]))
        y.append(0.2 * np.sin(8 * s) + step * label * (s > 0.3) + 0.02 * rng.standard_normal(40))
        groups.append(np.full(40, f"T{i}"))
    return columns, np.vstack(X), np.concatenate(y), np.concatenate(groups)


@pytest.mark.parametrize("step", [0.0, 0.3])
def test_a_label_drops_out_where_it_tells_the_tests_bias_apart_nowhere(step):
    """The state bounds (MethodConfig.bias_params): a label's theta free down to the bias model's own bound, so
    the likelihood drops a label the bias does not depend on (theta_min would keep its two levels at most
    0.67 correlated) and keeps one it does (docs/decisions.md, section 78)."""
    columns, X, y, groups = _labelled_tests(step, seed=0)
    est = GMMGPBias(n_clusters=1, random_state=0, **MethodConfig(inputs="state").bias_params(columns))
    theta = est.fit(X, y, groups).gps_[0].theta_
    if step:
        assert theta[-1] > 0.1  # the label separates the tests more than theta_min alone would
    else:
        assert theta[-1] < 1e-3  # dropped: its tests correlate as one
