"""Universal kriging: a Gaussian process with a GLS trend (paper Eq. 16-20).

Pure array code. Inputs ``X`` have shape (n, d) in whatever SI units the caller uses
(e.g. ``[s m, v0 m/s, w_f kg, w_r kg]``); the target ``y`` has shape (n,). The estimator
standardises its inputs internally, so nothing here depends on units. The equations as
implemented, and the paper's slips fixed, are in ``docs/bias-model.md``.
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.linalg import cholesky, lapack, solve_triangular
from scipy.optimize import minimize
from scipy.spatial.distance import cdist, pdist, squareform
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.preprocessing import StandardScaler
from sklearn.utils import check_random_state
from sklearn.utils.validation import check_array, check_is_fitted, check_X_y

from crashfuse.gp.threads import limit_blas

__all__ = ["KrigingGP", "SEED_MAX", "stratified_subset"]

SEED_MAX = 2**31 - 1  # exclusive upper bound of the integer seeds handed to sub-estimators
_TRENDS = ("zero", "constant", "linear")
_CHUNK = 2048  # prediction points per block: bounds the (n_train, chunk) work arrays
_JITTERS = 10.0 ** np.arange(-12, -3)  # relative jitters tried, in order, for joint draws
_FAILED = 1e300  # objective value where K is not numerically positive definite
# The scatter refits (one per left-out test) stop at a relative likelihood change of 1e-6, not
# scipy's 2e-9: they only size the test band. The main fit keeps scipy's default, where a
# looser tolerance can end in another local optimum (docs/decisions.md).
_SCATTER_LBFGS = {"ftol": 1e-6}
_Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def _correlation(A, B, theta):
    """Anisotropic Gaussian correlation ``prod_i exp(-theta_i (a_i - b_i)^2)``.

    Parameters
    ----------
    A : ndarray, shape (n, d)
    B : ndarray, shape (m, d)
    theta : ndarray, shape (d,)
        Positive correlation parameters (on the standardised inputs).

    Returns
    -------
    ndarray, shape (n, m)
    """
    w = np.sqrt(theta)
    C = cdist(A * w, B * w, "sqeuclidean")
    np.negative(C, out=C)
    return np.exp(C, out=C)


def _self_correlation(A, theta):
    """``_correlation(A, A, theta)``, bit for bit, with one exponential per pair instead of two.

    The exponential dominates the likelihood's correlation matrix; ``pdist`` gives each pair's
    squared distance exactly as ``cdist`` does, so mirroring the upper triangle changes no bit.

    Parameters
    ----------
    A : ndarray, shape (n, d)
    theta : ndarray, shape (d,)

    Returns
    -------
    ndarray, shape (n, n), C-contiguous and exactly symmetric, ones on the diagonal.
    """
    w = np.sqrt(theta)
    d = pdist(A * w, "sqeuclidean")
    np.negative(d, out=d)
    R = squareform(np.exp(d, out=d), checks=False)
    np.fill_diagonal(R, 1.0)  # exp(-0) of cdist's diagonal
    return R


def _factor_with_nugget(R, nugget):
    """Lower Cholesky factor of ``R + nugget I`` for an exactly symmetric ``R``, computed in ``R``'s memory.

    ``R.T`` is Fortran-ordered, so LAPACK factorises it in place instead of copying it first; being
    symmetric it is the same matrix, and the factor is the one
    ``cholesky(R + nugget * np.eye(n), lower=True)`` returns, bit for bit.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``R + nugget I`` is not numerically positive definite.
    """
    R.flat[::len(R) + 1] += nugget
    return cholesky(R.T, lower=True, overwrite_a=True, check_finite=False)


def _inverse_from_factor(L):
    """``K^-1`` from the lower Cholesky factor ``L`` of ``K`` (LAPACK ``dpotri``), overwriting ``L``.

    ``dpotri`` fills the lower triangle; the upper one is zero (``cholesky`` cleans it), so adding
    the transpose and halving the doubled diagonal mirrors it exactly (sums with 0 and the halving
    are exact), in one pass instead of two ``tril`` copies.

    Returns
    -------
    Kinv : ndarray, shape (n, n)
        C-ordered (the transposed view of LAPACK's Fortran-ordered result: the same symmetric
        matrix), so products with it are summed as before.
    info : int
        LAPACK's status; non-zero means ``K`` is singular.
    """
    Kinv, info = lapack.dpotri(L, lower=1, overwrite_c=1)
    Kinv += Kinv.T
    Kinv.flat[::len(Kinv) + 1] *= 0.5
    return Kinv.T, info


def _independent_columns(Z, tol=1e-8):
    """Indices of a maximal linearly independent set of ``[1, Z]`` columns (greedy, in order).

    Parameters
    ----------
    Z : ndarray, shape (n, d)
        Standardised inputs.

    Returns
    -------
    list of int
        Columns of ``Z`` kept in the linear trend (the intercept is always kept).
    """
    kept, basis = [], np.ones((Z.shape[0], 1))
    for j in range(Z.shape[1]):
        trial = np.column_stack([basis, Z[:, j]])
        s = np.linalg.svd(trial, compute_uv=False)
        if s[-1] > tol * s[0]:
            kept.append(j)
            basis = trial
    return kept


class KrigingGP(RegressorMixin, BaseEstimator):
    """Universal kriging: a Gaussian process with an explicit GLS trend ``h(x)^T beta``.

    Model (paper Eq. 16-17 with the sign of Eq. 17 fixed): ``f(x) = h(x)^T beta + Z(x)``,
    ``Cov[Z(x), Z(x')] = sigma^2 prod_i exp(-theta_i (x_i - x'_i)^2)``, and observations
    ``y = f(x) + eps`` with ``Var[eps] = sigma^2 * nugget``. ``beta`` (GLS) and ``sigma^2``
    are profiled out of the likelihood; ``log theta`` and ``log nugget`` are found by
    L-BFGS-B with analytic gradients from several seeded starts.

    Parameters
    ----------
    trend : {'zero', 'constant', 'linear'}
        No trend (simple kriging: a zero-mean process, so far from the data the prediction
        reverts to 0 and the outputs are scaled but not centred), ``h(x) = [1]`` (ordinary
        kriging) or ``[1, x_1, ..., x_d]`` on standardised inputs. Linear columns that are
        constant or collinear in the training data are dropped.
    theta_bounds : (float, float)
        Bounds on every ``theta_i`` for inputs standardised to unit variance; the
        correlation length ``1/sqrt(theta)`` spans 1/30 to 300 standard deviations by
        default. The low end lets the fit switch off an input: with a few tests per cluster
        the test-level inputs (v0, weights) are confounded, and a floor of 1e-3 made
        held-out errors up to 90x larger in ``benchmarks/bench_bias.py`` data.
    nugget_bounds : (float, float)
        Bounds on the noise-to-signal variance ratio. The lower bound keeps the
        correlation matrix's condition number below about ``n / nugget_min``.
    n_restarts : int
        Optimiser starts in addition to the fixed one (theta = 1, nugget = 1e-3), drawn
        log-uniformly within the bounds from ``random_state``.
    max_fit_points : int or None
        At most this many points (a seeded random subset) enter the hyperparameter
        search; ``None`` uses all. ``beta`` and ``sigma^2`` are then re-profiled on the
        conditioning set, which costs one Cholesky factorisation.
    max_condition_points : int or None
        At most this many points (a seeded random subset, containing the fit subset's
        points when it is smaller) are conditioned on (subset of data); ``None`` uses all.
    normalize_y : bool
        Standardise ``y`` before fitting (numerical only: the profiled likelihood is
        affine-equivariant in ``y``).
    blas_threads : int or None
        BLAS threads inside ``fit``, ``predict`` and draws (``None``: the library default).
        One thread, because threaded BLAS on these few-hundred-point matrices ran 2-10x
        slower on the shared 2-core machine (``benchmarks/bench_bias.py``); parallelise
        folds across processes instead.
    random_state : int, RandomState or None
        Seeds the restarts and the subsets.
    theta_max_candidates : sequence of float or None
        Upper bounds on ``theta`` to choose from when ``fit`` gets ``groups`` (at least 3):
        the maximum-likelihood fit under each bound is scored by :meth:`grouped_cv_log_density`
        on the training data and the best one is kept (``theta_max_``). ``None``: only
        ``theta_bounds``. The likelihood alone lets a few groups (tests) each become their
        own function (theta at the bound); held-out groups then fall back on the trend.
    calibrate_variance : bool
        With ``groups`` (at least 3): multiply ``sigma^2`` by ``(q / 1.96)^2``, if above 1,
        where ``q`` is the 95th percentile of the standardised leave-one-group-out residuals
        ``|e| / sd``: the 95 % band then holds 95 % of the errors made on unseen groups
        (``variance_factor_``). The mean is unchanged.
    estimate_scatter : bool
        With ``calibrate_variance`` and groups: also estimate the test-to-test scatter
        (``scatter_var_``) by refitting without each group in turn (about 2.5x the fit time).

    Attributes
    ----------
    theta_ : ndarray, shape (d,)
        Correlation parameters on the standardised inputs.
    nugget_ : float
        Noise-to-signal variance ratio.
    sigma2_ : float
        Process variance in (y units)^2.
    beta_ : ndarray, shape (p,)
        Trend coefficients on the standardised inputs, in y units (intercept first).
    trend_columns_ : list of int
        Input columns used by a linear trend.
    scaler_ : StandardScaler
        Input standardisation fitted in ``fit``.
    n_condition_ : int
        Number of points conditioned on.
    log_marginal_likelihood_value_ : float
        Concentrated log-likelihood at the optimum, on the hyperparameter-fit subset.
    n_fit_ : int
        Points in the hyperparameter search (and in the grouped CV score).
    theta_max_ : float
        Upper bound on ``theta`` the fit used.
    variance_factor_ : float
        Factor applied to ``sigma^2`` by ``calibrate_variance`` (1 otherwise).
    scatter_var_ : float
        Test-to-test scatter in (y units)^2 (0 without ``estimate_scatter``): the
        smallest variance that, added to the latent variance, puts 95 % of the training points
        inside the 95 % band when each test is predicted by the GP refitted without it
        (``_scatter_needs``). What a new group (test) scatters about the latent function beyond
        the function's uncertainty, white noise included; the latent draws leave it out.
    cv_scores_ : dict of float to float
        Grouped leave-one-group-out log density per candidate bound (empty without groups).
    """

    def __init__(self, trend="constant", theta_bounds=(1e-5, 1e3), nugget_bounds=(1e-8, 10.0),
                 n_restarts=2, max_fit_points=300, max_condition_points=None,
                 normalize_y=True, blas_threads=1, random_state=None, theta_max_candidates=None,
                 calibrate_variance=False, estimate_scatter=True):
        self.calibrate_variance = calibrate_variance
        self.estimate_scatter = estimate_scatter
        self.trend = trend
        self.theta_bounds = theta_bounds
        self.theta_max_candidates = theta_max_candidates
        self.nugget_bounds = nugget_bounds
        self.n_restarts = n_restarts
        self.max_fit_points = max_fit_points
        self.max_condition_points = max_condition_points
        self.normalize_y = normalize_y
        self.blas_threads = blas_threads
        self.random_state = random_state

    # ------------------------------------------------------------------ fitting
    @limit_blas
    def fit(self, X, y, groups=None):
        """Fit hyperparameters by maximum likelihood, then condition on the data.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
            Bias, m/s^2 (any unit; predictions come back in it).
        groups : array_like, shape (n,), optional
            Which test each row came from. Makes the hyperparameter subset a deterministic,
            evenly spaced one within each group, and enables ``theta_max_candidates``.

        Returns
        -------
        self
        """
        X, y = self._check_training_data(X, y)
        if groups is not None and len(groups) != len(y):
            raise ValueError(f"groups has {len(groups)} entries for {len(y)} rows")
        Z = self.scaler_.transform(X)
        centre = self.normalize_y and self.trend != "zero"  # a zero-mean prior must stay zero in y units
        self._y_mean, self._y_std = (y.mean() if centre else 0.0), (y.std() if self.normalize_y else 1.0)
        u = (y - self._y_mean) / self._y_std
        rng = check_random_state(self.random_state)
        if groups is None:
            i_fit = self._subset(len(u), self.max_fit_points, rng)
        else:
            groups = np.asarray(groups)
            i_fit = stratified_subset(groups, self.max_fit_points)
        self._Z_hyp, self._u_hyp = Z[i_fit], u[i_fit]
        self._g_hyp = None if groups is None else groups[i_fit]
        self.n_fit_ = len(i_fit)
        eta = self._choose_bound(rng)
        self.theta_, self.nugget_ = np.exp(eta[:-1]), float(np.exp(eta[-1]))
        i_cond = self._condition_subset(len(u), i_fit, rng)
        self._condition(Z[i_cond], u[i_cond])
        self._calibrate(u[i_cond], None if groups is None else groups[i_cond])
        return self

    def _calibrate(self, u_cond, g_cond):
        """Scale ``sigma^2`` so the 95 % band holds 95 % of the grouped leave-one-out residuals (if asked),
        then estimate the test-to-test scatter from grouped refits on the conditioning set."""
        self.variance_factor_, self.scatter_var_ = 1.0, 0.0
        if not self.calibrate_variance or self._g_hyp is None or len(np.unique(self._g_hyp)) < 3:
            return
        eta = np.log(np.r_[self.theta_, self.nugget_])
        self.variance_factor_ = self._variance_factor(eta)
        self._sigma2 *= self.variance_factor_
        self.sigma2_ *= self.variance_factor_
        need = self._scatter_needs(eta, self._Z_train, u_cond, g_cond) if self.estimate_scatter else np.empty(0)
        if need.size:
            self.scatter_var_ = max(0.0, float(np.quantile(need, 0.95))) * self._y_std**2

    def _variance_factor(self, eta):
        """``(q95 / 1.96)^2`` (at least 1) of the closed-form grouped residuals on the hyperparameter subset."""
        if len(np.unique(self._g_hyp)) < 3:
            return 1.0
        res = self._grouped_residuals(eta, self._Z_hyp, self._u_hyp, self._g_hyp)
        if res is None:
            return 1.0
        return max(1.0, (float(np.quantile(np.abs(res[0]) / np.sqrt(res[1]), 0.95)) / _Z95) ** 2)

    def _scatter_needs(self, eta, Z, u, groups):
        """Variance each conditioning point needs beyond the latent band when its test is left out.

        For each group (test) the GP is refitted without it - likelihood re-optimised from ``eta``
        under the chosen theta bound, variance factor recomputed, conditioned on the other groups'
        points - and predicts the group's points: ``need = (e / 1.96)^2 - latent variance``
        (normalised units). The closed-form leave-one-group-out at fixed hyperparameters is far
        more optimistic (state folds of the paper campaign: scatter 0.00-0.06 vs 0.05-0.11
        relative); a refit whose factorisation fails is left out.

        Returns
        -------
        ndarray, shape (n_needs,)
        """
        bounds = self._bounds(self.theta_max_)
        needs = []
        for grp in np.unique(groups):
            inner, keep = copy.copy(self), self._g_hyp != grp  # shares settings, scaler and trend columns
            inner._Z_hyp, inner._u_hyp, inner._g_hyp = self._Z_hyp[keep], self._u_hyp[keep], self._g_hyp[keep]
            e = minimize(inner._objective, eta, jac=True, method="L-BFGS-B", bounds=bounds, options=_SCATTER_LBFGS).x
            inner.theta_, inner.nugget_ = np.exp(e[:-1]), float(np.exp(e[-1]))
            try:
                inner._condition(Z[groups != grp], u[groups != grp])
            except np.linalg.LinAlgError:
                continue
            mean, V, W = inner._parts(Z[groups == grp])
            var = (1.0 - (V**2).sum(axis=0) + (W**2).sum(axis=0)) * inner._sigma2 * inner._variance_factor(e)
            needs.append((u[groups == grp] - mean) ** 2 / _Z95**2 - var)
        return np.concatenate(needs) if needs else np.empty(0)

    def _choose_bound(self, rng):
        """ML hyperparameters under the theta bound with the best grouped CV log density."""
        self.cv_scores_ = {}
        candidates = self.theta_max_candidates
        if not candidates or self._g_hyp is None or len(np.unique(self._g_hyp)) < 3:
            self.theta_max_ = float(self.theta_bounds[1])
            return self._optimise(rng, self.theta_max_)
        best, eta = None, None
        # Largest bound first with every restart; a smaller bound reuses that optimum when it lies
        # inside the bound (it is then optimal there too), else starts from it clipped.
        for hi in sorted((float(c) for c in candidates), reverse=True):
            eta = self._optimise(rng, hi) if eta is None else self._warm_optimise(eta, hi)
            ll = self.log_marginal_likelihood_value_
            score = self._grouped_cv(eta, self._Z_hyp, self._u_hyp, self._g_hyp)
            self.cv_scores_[hi] = score
            if best is None or score > best[0]:
                best = (score, hi, eta, ll)
        _, self.theta_max_, eta, self.log_marginal_likelihood_value_ = best
        return eta

    @limit_blas
    def grouped_cv_log_density(self, groups=None):
        """Leave-one-group-out log predictive density per point at the fitted hyperparameters.

        Each group (test) is predicted from the others with the trend re-estimated (the
        universal-kriging closed form: with ``P = K^-1 - K^-1 H (H^T K^-1 H)^-1 H^T K^-1``,
        the held-out residuals are ``P_II^-1 (P y)_I`` with covariance ``sigma^2 P_II^-1``),
        and every held-out point is scored by its marginal normal density. On the
        hyperparameter-fit subset, in normalised-output units.

        Parameters
        ----------
        groups : array_like, shape (n_hyp,), optional
            Group of each hyperparameter-fit point; default the groups given to ``fit``.

        Returns
        -------
        float
            Mean log density per point (higher is better).
        """
        check_is_fitted(self)
        g = self._g_hyp if groups is None else np.asarray(groups)
        if g is None:
            raise ValueError("grouped_cv_log_density needs groups (pass them to fit or here)")
        eta = np.log(np.r_[self.theta_, self.nugget_])
        return self._grouped_cv(eta, self._Z_hyp, self._u_hyp, g)

    @limit_blas
    def grouped_residuals(self, X, y, groups):
        """Leave-one-group-out residuals at the fitted hyperparameters, conditioned on ``(X, y)``.

        Each group (test) is predicted from the other groups' rows with ``theta``, the nugget
        and ``sigma^2`` fixed and the trend re-estimated (the closed form of
        :meth:`grouped_cv_log_density`); cost ``O(n^3)`` in the rows given.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
        groups : array_like, shape (n,)
            At least two groups.

        Returns
        -------
        ndarray, shape (n,) or None
            ``y`` minus its leave-one-group-out prediction (y units); None where the correlation
            matrix or a group's block is numerically singular.
        """
        check_is_fitted(self)
        X, y, groups = check_array(X), np.asarray(y, dtype=float), np.asarray(groups)
        if len(np.unique(groups)) < 2:
            raise ValueError("grouped_residuals needs at least two groups")
        u = (y - self._y_mean) / self._y_std
        res = self._grouped_residuals(np.log(np.r_[self.theta_, self.nugget_]), self.scaler_.transform(X), u, groups)
        return None if res is None else res[0] * self._y_std

    def _grouped_cv(self, eta, Z, u, groups):
        """Mean leave-one-group-out marginal log density (see :meth:`grouped_cv_log_density`)."""
        res = self._grouped_residuals(eta, Z, u, groups)
        if res is None:
            return -np.inf
        e, var = res
        return float(np.mean(-0.5 * (np.log(2 * np.pi * var) + e**2 / var)))

    def _grouped_residuals(self, eta, Z, u, groups):
        """Leave-one-group-out residuals and their predictive variances (normalised units).

        Returns
        -------
        (e, var) : two ndarrays of shape (n,), or None where ``K`` or a block is singular.
        """
        try:
            L = _factor_with_nugget(_self_correlation(Z, np.exp(eta[:-1])), np.exp(eta[-1]))
        except np.linalg.LinAlgError:
            return None
        H = self._design(Z)
        _, alpha, sigma2, _ = self._gls(L, H, u)  # alpha = P u
        Kinv = _inverse_from_factor(L)[0]
        KiH = Kinv @ H
        P = Kinv - KiH @ np.linalg.solve(H.T @ KiH, KiH.T)
        e, var = np.empty(len(u)), np.empty(len(u))
        for grp in np.unique(groups):
            idx = np.flatnonzero(groups == grp)
            try:
                C = np.linalg.inv(P[np.ix_(idx, idx)])
            except np.linalg.LinAlgError:
                return None
            e[idx], var[idx] = C @ alpha[idx], np.diag(C) * sigma2
        return None if np.any(var <= 0) else (e, var)

    def _check_training_data(self, X, y):
        """Validate settings and data; fit the scaler and choose the trend columns.

        Returns
        -------
        X : ndarray, shape (n, d)
        y : ndarray, shape (n,)
        """
        if self.trend not in _TRENDS:
            raise ValueError(f"trend must be one of {_TRENDS}, got {self.trend!r}")
        X, y = check_X_y(X, y, y_numeric=True)
        self.n_features_in_ = X.shape[1]
        self.scaler_ = StandardScaler().fit(X)
        Z = self.scaler_.transform(X)
        self.trend_columns_ = _independent_columns(Z) if self.trend == "linear" else []
        n_par = (self.trend != "zero") + len(self.trend_columns_)
        if len(y) < n_par + 2:
            raise ValueError(f"KrigingGP needs at least {n_par + 2} points for a {self.trend} "
                             f"trend in {X.shape[1]}-D, got {len(y)}")
        if np.ptp(y) == 0:
            raise ValueError(f"KrigingGP: all {len(y)} outputs equal {y[0]!r}; a constant has no "
                             "process variance to fit")
        return X, y

    @staticmethod
    def _subset(n, limit, rng):
        """Sorted seeded random subset of ``range(n)`` of size ``min(n, limit)``."""
        if limit is None or n <= limit:
            return np.arange(n)
        return np.sort(rng.choice(n, size=int(limit), replace=False))

    def _condition_subset(self, n, i_fit, rng):
        """Conditioning set: all points, or the fit subset topped up at random to the limit."""
        limit = self.max_condition_points
        if limit is None or n <= limit:
            return np.arange(n)
        if len(i_fit) >= limit:
            return np.sort(rng.choice(i_fit, size=int(limit), replace=False))
        rest = np.setdiff1d(np.arange(n), i_fit)
        extra = rng.choice(rest, size=int(limit) - len(i_fit), replace=False)
        return np.sort(np.concatenate([i_fit, extra]))

    def _bounds(self, theta_max):
        """Bounds on ``[log theta_1..d, log nugget]``, shape (d + 1, 2)."""
        d = self.n_features_in_
        lo = np.r_[np.full(d, np.log(self.theta_bounds[0])), np.log(self.nugget_bounds[0])]
        hi = np.r_[np.full(d, np.log(theta_max)), np.log(self.nugget_bounds[1])]
        return np.column_stack([lo, hi])

    def _optimise(self, rng, theta_max):
        """Best ``[log theta, log nugget]`` over the fixed start and the random restarts."""
        bounds = self._bounds(theta_max)
        first = np.clip(np.r_[np.zeros(self.n_features_in_), np.log(1e-3)], bounds[:, 0], bounds[:, 1])
        starts = [first] + [rng.uniform(bounds[:, 0], bounds[:, 1]) for _ in range(self.n_restarts)]
        best_eta, best_f = None, np.inf
        for x0 in starts:
            res = minimize(self._objective, x0, jac=True, method="L-BFGS-B", bounds=bounds)
            if res.fun < min(best_f, _FAILED):
                best_eta, best_f = res.x, res.fun
        if best_eta is None:
            raise ValueError("KrigingGP: the likelihood could not be evaluated at any start "
                             "(duplicate inputs with conflicting outputs and a zero nugget?)")
        self.log_marginal_likelihood_value_ = -best_f
        return best_eta

    def _warm_optimise(self, eta, theta_max):
        """The optimum under a smaller theta bound, from the optimum ``eta`` under a larger one."""
        bounds = self._bounds(theta_max)
        if np.all(eta <= bounds[:, 1]):
            self.log_marginal_likelihood_value_ = -self._objective(eta)[0]
            return eta
        first = np.clip(np.r_[np.zeros(self.n_features_in_), np.log(1e-3)], bounds[:, 0], bounds[:, 1])
        fits = [minimize(self._objective, x0, jac=True, method="L-BFGS-B", bounds=bounds)
                for x0 in (np.clip(eta, bounds[:, 0], bounds[:, 1]), first)]
        res = min(fits, key=lambda r: r.fun)
        self.log_marginal_likelihood_value_ = -res.fun
        return res.x

    def _objective(self, eta):
        """Negative concentrated log-likelihood and its gradient, for the optimiser."""
        ll, grad = self._concentrated(eta, self._Z_hyp, self._u_hyp, gradient=True)
        if not np.isfinite(ll):
            return _FAILED, np.zeros_like(eta)
        return -ll, -grad

    def _design(self, Z):
        """Trend design matrix ``H``, shape (n, p), on standardised inputs ``Z`` (n, d); p = 0 for no trend."""
        if self.trend == "zero":
            return np.empty((len(Z), 0))
        return np.column_stack([np.ones(len(Z)), Z[:, self.trend_columns_]])

    def _concentrated(self, eta, Z, u, gradient=False):
        """Concentrated log-likelihood (beta GLS, sigma^2 = r^T K^-1 r / n) and gradient.

        Parameters
        ----------
        eta : ndarray, shape (d + 1,)
            ``[log theta_1..d, log nugget]``.
        Z : ndarray, shape (n, d)
            Standardised inputs.
        u : ndarray, shape (n,)
            (Normalised) outputs.
        gradient : bool
            Also return the gradient with respect to ``eta``.

        Returns
        -------
        ll : float
            ``-n/2 log(2 pi sigma^2) - 1/2 log|K| - n/2``, ``K = R + nugget I``; ``-inf`` if
            ``K`` is not numerically positive definite.
        grad : ndarray, shape (d + 1,), only if ``gradient``
        """
        n = len(u)
        theta, nugget = np.exp(eta[:-1]), np.exp(eta[-1])
        R = _self_correlation(Z, theta)
        try:
            L = _factor_with_nugget(R.copy(), nugget)  # R is needed for the gradient
        except np.linalg.LinAlgError:
            return (-np.inf, np.zeros_like(eta)) if gradient else -np.inf
        alpha, sigma2 = self._gls(L, self._design(Z), u)[1:3]
        ll = -0.5 * n * np.log(2 * np.pi * sigma2) - np.log(np.diag(L)).sum() - 0.5 * n
        if not gradient:
            return ll
        # d ll / d eta_j = 1/2 tr(W dK/d eta_j), W = alpha alpha^T / sigma^2 - K^-1; beta and
        # sigma^2 are stationary points of the likelihood, so their own derivatives drop out.
        # The n x n steps work in place (same operations, same bits): this runs ~1000 times a fit.
        Kinv, info = _inverse_from_factor(L)
        if info != 0:
            return -np.inf, np.zeros_like(eta)
        W = np.outer(alpha, alpha)
        W /= sigma2
        W -= Kinv
        trace_w = np.trace(W)
        A = np.multiply(W, R, out=R)  # dK/dlog theta_k = -theta_k D2_k * R, elementwise
        AZ = A @ Z
        # sum_ij A_ij (z_ik - z_jk)^2 = 2 sum_i z_ik^2 (A 1)_i - 2 z_k^T A z_k for symmetric A
        quad = (Z**2 * A.sum(axis=1)[:, None]).sum(axis=0) - (Z * AZ).sum(axis=0)
        grad = np.r_[-theta * quad, 0.5 * nugget * trace_w]
        return ll, grad

    @staticmethod
    def _gls(L, H, u):
        """GLS trend given the Cholesky factor ``L`` of ``K``.

        Returns
        -------
        beta : ndarray, shape (p,)
        alpha : ndarray, shape (n,)
            ``K^-1 (u - H beta)``.
        sigma2 : float
            ``(u - H beta)^T K^-1 (u - H beta) / n``.
        Ht : ndarray, shape (n, p)
            ``L^-1 H``.
        """
        Ht = solve_triangular(L, H, lower=True, check_finite=False)
        ut = solve_triangular(L, u, lower=True, check_finite=False)
        beta = np.linalg.lstsq(Ht, ut, rcond=None)[0]
        rt = ut - Ht @ beta
        alpha = solve_triangular(L, rt, lower=True, trans="T", check_finite=False)
        return beta, alpha, float(rt @ rt) / len(u), Ht

    def _condition(self, Z, u):
        """Factorise ``K`` on the conditioning set and store what prediction needs."""
        self._L = _factor_with_nugget(_self_correlation(Z, self.theta_), self.nugget_)
        self._beta, self._alpha, self._sigma2, self._Ht = self._gls(self._L, self._design(Z), u)
        self._LM = cholesky(self._Ht.T @ self._Ht, lower=True, check_finite=False)
        self._Z_train = Z
        self.n_condition_ = len(u)
        self.sigma2_ = self._sigma2 * self._y_std**2
        self.beta_ = self._beta * self._y_std
        if self.beta_.size:
            self.beta_[0] += self._y_mean

    @limit_blas
    def log_marginal_likelihood(self, params, eval_gradient=False):
        """Concentrated log-likelihood on the hyperparameter-fit data.

        Parameters
        ----------
        params : array_like, shape (d + 1,)
            ``[log theta_1..d, log nugget]`` (theta on standardised inputs).
        eval_gradient : bool
            Also return the analytic gradient with respect to ``params``.

        Returns
        -------
        float, or (float, ndarray of shape (d + 1,))
            Log-likelihood in normalised-output units (differs from the one in y units by
            the constant ``-n log(y_std)``).
        """
        check_is_fitted(self)
        return self._concentrated(np.asarray(params, float), self._Z_hyp, self._u_hyp, eval_gradient)

    # --------------------------------------------------------------- prediction
    def _mean(self, Zs):
        """Mean (normalised) at standardised points ``Zs`` (m, d) and their correlations ``r`` (n, m)."""
        r = _correlation(self._Z_train, Zs, self.theta_)
        return self._design(Zs) @ self._beta + r.T @ self._alpha, r

    def _parts(self, Zs):
        """Mean (normalised) and the two variance pieces at standardised points ``Zs`` (m, d).

        Returns
        -------
        mean : ndarray, shape (m,)
        V : ndarray, shape (n, m)
            ``L^-1 r(x)``.
        W : ndarray, shape (p, m)
            ``L_M^-1 u(x)``, ``u = h(x) - H^T K^-1 r(x)``, ``L_M L_M^T = H^T K^-1 H``.
        """
        mean, r = self._mean(Zs)
        V = solve_triangular(self._L, r, lower=True, check_finite=False)
        U = self._design(Zs).T - self._Ht.T @ V
        W = solve_triangular(self._LM, U, lower=True, check_finite=False)
        return mean, V, W

    @limit_blas
    def predict(self, X, return_std=False, include_noise=False):
        """Predictive mean, and optionally the standard deviation (Eq. 19-20 corrected).

        Parameters
        ----------
        X : array_like, shape (m, d)
        return_std : bool
            Also return ``sigma^2 [1 - r^T K^-1 r + u^T (H^T K^-1 H)^-1 u]`` as a std.
        include_noise : bool
            Add the noise variance ``sigma^2 * nugget`` (a new observation, not the latent
            bias function).

        Returns
        -------
        mean : ndarray, shape (m,)
        std : ndarray, shape (m,), only if ``return_std``
        """
        check_is_fitted(self)
        Zs = self.scaler_.transform(check_array(X))
        means, stds = [], []
        for start in range(0, len(Zs), _CHUNK):
            chunk = Zs[start:start + _CHUNK]
            if not return_std:  # the mean needs no triangular solve against the training points
                means.append(self._mean(chunk)[0])
                continue
            mean, V, W = self._parts(chunk)
            means.append(mean)
            var = 1.0 - (V**2).sum(axis=0) + (W**2).sum(axis=0) + include_noise * self.nugget_
            stds.append(np.sqrt(np.clip(var * self._sigma2, 0.0, None)))
        mean = np.concatenate(means) * self._y_std + self._y_mean if means else np.empty(0)
        if not return_std:
            return mean
        return mean, (np.concatenate(stds) if stds else np.empty(0)) * self._y_std

    @limit_blas
    def predict_cov(self, X):
        """Joint predictive mean and covariance of the latent function (no nugget).

        Parameters
        ----------
        X : array_like, shape (m, d)

        Returns
        -------
        mean : ndarray, shape (m,)
        cov : ndarray, shape (m, m)
            ``sigma^2 [R** - r^T K^-1 r + U^T (H^T K^-1 H)^-1 U]``, including the
            trend-estimation term.
        """
        check_is_fitted(self)
        Zs = self.scaler_.transform(check_array(X))
        mean, V, W = self._parts(Zs)
        cov = _correlation(Zs, Zs, self.theta_) - V.T @ V + W.T @ W
        return mean * self._y_std + self._y_mean, cov * (self._sigma2 * self._y_std**2)

    @limit_blas
    def sample_functions(self, X, n_samples=1, random_state=None):
        """Joint draws of the latent bias function (no nugget) at the points ``X``.

        The covariance includes the trend-estimation term. It is factorised by Cholesky
        with a diagonal jitter of ``j * mean(diag(cov))``, ``j`` trying 1e-12, 1e-11, ...,
        1e-4 in turn until the factorisation succeeds (smooth GPs on dense grids are
        numerically singular); the added standard deviation is at most 1 % of the
        average predictive one.

        Parameters
        ----------
        X : array_like, shape (m, d)
        n_samples : int
        random_state : int, RandomState or None

        Returns
        -------
        ndarray, shape (n_samples, m)
        """
        mean, cov = self.predict_cov(X)
        Lc = _jittered_cholesky(cov)
        z = check_random_state(random_state).standard_normal((len(mean), n_samples))
        return (mean[:, None] + Lc @ z).T


def stratified_subset(groups, limit):
    """Deterministic subset: about ``limit`` rows, evenly spaced within each group, sorted.

    Parameters
    ----------
    groups : ndarray, shape (n,)
    limit : int or None

    Returns
    -------
    ndarray of int
    """
    n = len(groups)
    if limit is None or n <= limit:
        return np.arange(n)
    keep = []
    for grp in np.unique(groups):
        idx = np.flatnonzero(groups == grp)
        m = max(1, int(round(limit * len(idx) / n)))
        keep.append(idx[np.unique(np.linspace(0, len(idx) - 1, m).round().astype(int))])
    return np.sort(np.concatenate(keep))


def _jittered_cholesky(cov):
    """Lower Cholesky factor of ``cov + j mean(diag) I`` with the smallest working jitter.

    Parameters
    ----------
    cov : ndarray, shape (m, m)

    Returns
    -------
    ndarray, shape (m, m)
    """
    if cov.size == 0:
        return cov
    scale = max(float(np.mean(np.diag(cov))), np.finfo(float).tiny)
    for j in _JITTERS:
        try:
            return cholesky(cov + j * scale * np.eye(len(cov)), lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            continue
    raise np.linalg.LinAlgError("predictive covariance is not positive semi-definite even with "
                                f"a jitter of {_JITTERS[-1]:g} x its mean variance")
