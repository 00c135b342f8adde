"""Universal kriging as a scikit-learn estimator: a Gaussian process with a GLS trend (paper Eq. 16-20).

:class:`KrigingGP` holds the settings and the fitted state and composes the jobs of the other ``gp`` modules:
the correlation and trend basis (:mod:`~crashfuse.gp.kernels`), the concentrated likelihood
(:mod:`~crashfuse.gp.likelihood`), its maximisation and the theta bound chosen by grouped CV
(:mod:`~crashfuse.gp.optimise`), the row subsets (:mod:`~crashfuse.gp.subsets`), conditioning and prediction
(:mod:`~crashfuse.gp.posterior`), leave-one-group-out residuals, band calibration and test-to-test scatter
(:mod:`~crashfuse.gp.grouped`) and joint draws (:mod:`~crashfuse.gp.sampling`).

Inputs ``X`` have shape (n, d) in whatever SI units the caller uses (e.g. ``[s m, v0 m/s, w_f kg, w_r kg]``);
the target ``y`` has shape (n,). The estimator standardises its inputs (``Z``) and outputs (``u``) internally,
so nothing here depends on units. The equations as implemented, and the paper's slips fixed, are in
``docs/bias-model.md``.
"""

from __future__ import annotations

import hashlib

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.preprocessing import StandardScaler
from sklearn.utils import check_random_state
from sklearn.utils.validation import check_is_fitted, validate_data

from crashfuse.gp.grouped import grouped_cv_log_density, grouped_residuals, scatter_needs, variance_factor
from crashfuse.gp.kernels import (TRENDS, correlation, design, factor_with_nugget, independent_columns,
                                  self_correlation)
from crashfuse.gp.likelihood import concentrated_log_likelihood
from crashfuse.gp.optimise import FREE_NUGGET, choose_theta_bound, log_bounds
from crashfuse.gp.posterior import condition, latent_variance, predictive_mean, variance_parts
from crashfuse.gp.sampling import joint_draws
from crashfuse.gp.subsets import condition_subset, random_subset, stratified_subset
from crashfuse.gp.threads import blas_threads, limit_blas

__all__ = ["KrigingGP", "SEED_MAX", "data_digest"]

SEED_MAX = 2**31 - 1  # exclusive upper bound of the integer seeds handed to sub-estimators
_CHUNK = 2048  # prediction points per block: bounds the (n_train, chunk) work arrays


def data_digest(X, y, groups=None) -> str:
    """A fingerprint of training rows ``(X, y, groups)``: two fits with equal settings and seed on rows
    with equal digests are the same fit."""
    h = hashlib.blake2b(digest_size=16)
    for a in (X, y):
        h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    if groups is not None:
        h.update("\0".join(map(str, groups)).encode())
    return h.hexdigest()


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
    theta_bounds : (float or tuple of d floats, float)
        Bounds on every ``theta_i`` (the lower one for all inputs, or one per input) for inputs
        standardised to unit variance; the
        correlation length ``1/sqrt(theta)`` spans 1/30 to 300 standard deviations by
        default. The low end lets the fit switch off an input: with a few tests per cluster
        the test-level inputs (v0, weights) are confounded, and a floor of 1e-3 gives
        held-out errors up to 90x larger on ``benchmarks/bench_bias.py`` data (docs/decisions.md, section 3).
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
        About this many points (the fit subset's, topped up evenly within each group when ``fit``
        gets groups, else at random) are conditioned on (subset of data); ``None`` uses all.
    normalize_y : bool
        Standardise ``y`` before fitting (numerical only: the profiled likelihood is
        affine-equivariant in ``y``).
    blas_threads : int or None
        BLAS threads inside ``fit``, ``predict`` and draws (``None``: the library default).
        One thread, because threaded BLAS on these few-hundred-point matrices runs 2-10x
        slower on the shared 2-core machine (``benchmarks/bench_bias.py``, docs/decisions.md,
        section 12); parallelise folds across processes instead.
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
    data_digest_ : str
        :func:`data_digest` of the training rows.
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
        (:func:`crashfuse.gp.grouped.scatter_needs`). What a new group (test) scatters about the latent function beyond
        the function's uncertainty, white noise included; the latent draws leave it out. Pooled over
        the tests; :meth:`scatter_var_at` gives it near a point.
    scatter_need_, scatter_Z_, scatter_tests_ : ndarray, ndarray, int
        The held-out needs (normalised units, shape (n_needs,)), their standardised inputs
        (n_needs, d) and the number of tests they come from (only with the scatter estimated).
    held_out_spread_ : ndarray, shape (n_needs,)
        ``(e / 1.96)^2`` of the same held-out points (normalised units): the need with the latent
        variance added back (:meth:`held_out_var_at`).
    cv_scores_ : dict of float to float
        Grouped leave-one-group-out log density per candidate bound (empty without groups).
    n_features_in_ : int
        Number of inputs ``d`` seen in ``fit``.
    y_mean_, y_std_ : float
        Output normalisation ``u = (y - y_mean_) / y_std_`` (``y_mean_`` is 0 for the zero trend,
        ``y_std_`` 1 without ``normalize_y``).
    Z_fit_ : ndarray, shape (n_fit_, d)
        Standardised inputs of the hyperparameter-fit subset (the likelihood's data).
    u_fit_ : ndarray, shape (n_fit_,)
        Normalised outputs of that subset.
    groups_fit_ : ndarray, shape (n_fit_,) or None
        Their groups (None without ``groups``).
    Z_condition_ : ndarray, shape (n_condition_, d)
        Standardised inputs conditioned on.
    L_ : ndarray, shape (n_condition_, n_condition_)
        Lower Cholesky factor of ``K = R + nugget I`` on the conditioning set. Not saved with the
        model (:mod:`crashfuse.io.persist`): a loaded model refactorises on first use.
    alpha_ : ndarray, shape (n_condition_,)
        ``K^-1 (u - H beta)`` (normalised units).
    Ht_ : ndarray, shape (n_condition_, p)
        ``L^-1 H``.
    LM_ : ndarray, shape (p, p)
        Lower Cholesky factor of ``H^T K^-1 H``.
    beta_norm_ : ndarray, shape (p,)
        Trend coefficients in normalised units.
    sigma2_norm_ : float
        Process variance in normalised units, calibrated (``sigma2_ = sigma2_norm_ * y_std_**2``).
    """


    # n^2 floats, 32 MB at 2000 points: refactorising (~0.1 s) is cheaper than writing and reading it
    _derived_attributes = ("L_",)

    def __init__(self, *, trend="constant", theta_bounds=(1e-5, 1e3), nugget_bounds=(FREE_NUGGET, 10.0),
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
        X, y = self._validate_training_data(X, y)
        if groups is not None and len(groups) != len(y):
            raise ValueError(f"groups has {len(groups)} entries for {len(y)} rows")
        self.data_digest_ = data_digest(X, y, groups)
        Z = self.scaler_.transform(X)
        centre = self.normalize_y and self.trend != "zero"  # a zero-mean prior must stay zero in y units
        self.y_mean_, self.y_std_ = (y.mean() if centre else 0.0), (y.std() if self.normalize_y else 1.0)
        u = (y - self.y_mean_) / self.y_std_
        rng = check_random_state(self.random_state)
        if groups is None:
            i_fit = random_subset(len(u), self.max_fit_points, rng)
        else:
            groups = np.asarray(groups)
            i_fit = stratified_subset(groups, self.max_fit_points)
        self.Z_fit_, self.u_fit_ = Z[i_fit], u[i_fit]
        self.groups_fit_ = None if groups is None else groups[i_fit]
        self.n_fit_ = len(i_fit)
        eta, self.theta_max_, self.log_marginal_likelihood_value_, self.cv_scores_ = choose_theta_bound(
            self.Z_fit_, self.u_fit_, self._design(self.Z_fit_), self.groups_fit_, rng,
            theta_bounds=self.theta_bounds, nugget_bounds=self.nugget_bounds,
            candidates=self.theta_max_candidates, n_restarts=self.n_restarts)
        self.theta_, self.nugget_ = np.exp(eta[:-1]), float(np.exp(eta[-1]))
        i_cond = condition_subset(len(u), i_fit, self.max_condition_points, rng, groups)
        self._condition(Z[i_cond], u[i_cond])
        self._calibrate(u[i_cond], None if groups is None else groups[i_cond])
        return self

    def _validate_training_data(self, X, y):
        """Validate settings and data; fit the scaler and choose the trend columns.

        Returns
        -------
        X : ndarray, shape (n, d)
        y : ndarray, shape (n,)
        """
        if self.trend not in TRENDS:
            raise ValueError(f"trend must be one of {TRENDS}, got {self.trend!r}")
        X, y = validate_data(self, X, y, y_numeric=True)
        self.scaler_ = StandardScaler().fit(X)
        Z = self.scaler_.transform(X)
        self.trend_columns_ = independent_columns(Z) if self.trend == "linear" else []
        n_par = (self.trend != "zero") + len(self.trend_columns_)
        if len(y) < n_par + 2:
            raise ValueError(f"KrigingGP needs at least {n_par + 2} points for a {self.trend} "
                             f"trend in {X.shape[1]}-D, got {len(y)} sample(s)")
        if np.ptp(y) == 0:
            raise ValueError(f"KrigingGP: all {len(y)} outputs equal {y[0]!r}; a constant has no "
                             "process variance to fit")
        return X, y

    def _design(self, Z):
        """Trend design matrix ``H``, shape (n, p), at standardised inputs ``Z`` (n, d)."""
        return design(Z, self.trend, self.trend_columns_)

    def _eta(self):
        """The fitted ``[log theta_1..d, log nugget]``, shape (d + 1,)."""
        return np.log(np.r_[self.theta_, self.nugget_])

    def _condition(self, Z, u):
        """Condition on ``(Z, u)`` at the fitted hyperparameters and store what prediction needs."""
        self.L_, self.beta_norm_, self.alpha_, self.sigma2_norm_, self.Ht_, self.LM_ = condition(
            Z, u, self._design(Z), self.theta_, self.nugget_)
        self.Z_condition_ = Z
        self.n_condition_ = len(u)
        self.sigma2_ = self.sigma2_norm_ * self.y_std_**2
        self.beta_ = self.beta_norm_ * self.y_std_
        if self.beta_.size:
            self.beta_[0] += self.y_mean_

    def __getattr__(self, name):
        # Only reached when normal lookup fails: a loaded model rebuilds its factor once.
        if name == "L_" and "Z_condition_" in self.__dict__:
            with blas_threads(self.blas_threads):  # as in fit: the same factor, bit for bit
                self.L_ = factor_with_nugget(self_correlation(self.Z_condition_, self.theta_), self.nugget_)
            return self.L_
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def _calibrate(self, u_cond, g_cond):
        """Scale ``sigma^2`` so the 95 % band holds 95 % of the grouped leave-one-out residuals (if asked),
        then estimate the test-to-test scatter from grouped refits on the conditioning set."""
        self.variance_factor_, self.scatter_var_ = 1.0, 0.0
        if not self.calibrate_variance or self.groups_fit_ is None or len(np.unique(self.groups_fit_)) < 3:
            return
        eta = self._eta()
        hyp = (self.Z_fit_, self.u_fit_, self._design(self.Z_fit_), self.groups_fit_)
        self.variance_factor_ = variance_factor(eta, *hyp)
        self.sigma2_norm_ *= self.variance_factor_
        self.sigma2_ *= self.variance_factor_
        if not self.estimate_scatter:
            return
        bounds = log_bounds(self.n_features_in_, self.theta_bounds, self.theta_max_, self.nugget_bounds)
        cond = (self.Z_condition_, u_cond, self._design(self.Z_condition_), g_cond)
        need, rows, spread = scatter_needs(eta, bounds, hyp, cond)
        if need.size:
            self.scatter_var_ = max(0.0, float(np.quantile(need, 0.95))) * self.y_std_**2
            self.scatter_need_, self.scatter_Z_, self.held_out_spread_ = need, self.Z_condition_[rows], spread
            self.scatter_tests_ = len(np.unique(g_cond[rows]))

    def scatter_var_at(self, X):
        """Test-to-test scatter at ``X`` (y units)^2: the held-out needs' 95 % quantile near ``X``.

        Each conditioning point's need (:func:`crashfuse.gp.grouped.scatter_needs`) is weighted by the
        GP's own correlation with ``X``, scaled so that one test's points, all at ``X``, weigh 1. Where
        the points near ``X`` weigh less than that, the rest of the weight is spread evenly over all
        needs: far from the tests the scatter is about the pooled ``scatter_var_``. A model fitted before
        the needs were kept has the pooled value everywhere.

        Parameters
        ----------
        X : array_like, shape (m, d)

        Returns
        -------
        ndarray, shape (m,)
        """
        if "scatter_need_" not in self.__dict__:
            return np.full(len(X), self.scatter_var_)
        return np.maximum(0.0, self._near_quantile(self.scatter_need_, X)) * self.y_std_**2

    def held_out_var_at(self, X):
        """The variance a new test's errors need near ``X`` (y units)^2: ``(e / 1.96)^2``'s 95 % quantile.

        ``e`` are the errors of the refits without each test (``held_out_spread_``), weighted near ``X``
        as :meth:`scatter_var_at` weighs the needs: the whole band (latent and scatter) that holds 95 %
        of a left-out test's points there. ``inf`` where the refits were not made (no scatter estimated,
        or a model fitted before they were kept).

        Parameters
        ----------
        X : array_like, shape (m, d)

        Returns
        -------
        ndarray, shape (m,)
        """
        if "held_out_spread_" not in self.__dict__:
            return np.full(len(X), np.inf)
        return self._near_quantile(self.held_out_spread_, X) * self.y_std_**2

    def _near_quantile(self, values, X):
        """The 95 % quantile of ``values`` (one per held-out point) weighted near ``X``, shape (m,)."""
        k = correlation(self._standardised(X), self.scatter_Z_, self.theta_)  # (m, needs)
        k /= len(values) / self.scatter_tests_
        w = k + np.maximum(0.0, 1.0 - k.sum(axis=1, keepdims=True)) / len(values)
        order = np.argsort(values)
        cw = np.cumsum(w[:, order], axis=1)
        cw /= cw[:, -1:]
        idx = np.minimum((cw < 0.95).sum(axis=1), len(order) - 1)
        return values[order][idx]

    # ------------------------------------------------------- fitted-model scores
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
        return concentrated_log_likelihood(np.asarray(params, float), self.Z_fit_, self.u_fit_,
                                           self._design(self.Z_fit_), eval_gradient)

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
        groups : array_like, shape (n_fit_,), optional
            Group of each hyperparameter-fit point; default the groups given to ``fit``.

        Returns
        -------
        float
            Mean log density per point (higher is better).
        """
        check_is_fitted(self)
        g = self.groups_fit_ if groups is None else np.asarray(groups)
        if g is None:
            raise ValueError("grouped_cv_log_density needs groups (pass them to fit or here)")
        return grouped_cv_log_density(self._eta(), self.Z_fit_, self.u_fit_, self._design(self.Z_fit_), g)

    @limit_blas
    def grouped_cv_residuals(self):
        """Leave-one-group-out residuals on the hyperparameter-fit subset at the fitted hyperparameters.

        The residuals :meth:`grouped_cv_log_density` scores, in normalised-output units (compare them with
        ``u_fit_``, the outputs themselves).

        Returns
        -------
        ndarray, shape (n_fit_,) or None
            None without at least two groups, or where a matrix is numerically singular.
        """
        check_is_fitted(self)
        if self.groups_fit_ is None or len(np.unique(self.groups_fit_)) < 2:
            return None
        res = grouped_residuals(self._eta(), self.Z_fit_, self.u_fit_, self._design(self.Z_fit_), self.groups_fit_)
        return None if res is None else res[0]

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
        X, y, groups = validate_data(self, X, reset=False), np.asarray(y, dtype=float), np.asarray(groups)
        if len(np.unique(groups)) < 2:
            raise ValueError("grouped_residuals needs at least two groups")
        u = (y - self.y_mean_) / self.y_std_
        Z = self.scaler_.transform(X)
        res = grouped_residuals(self._eta(), Z, u, self._design(Z), groups)
        return None if res is None else res[0] * self.y_std_

    # --------------------------------------------------------------- prediction
    def _standardised(self, X):
        """Validated ``X`` (its feature count that of ``fit``), standardised, shape (m, d)."""
        check_is_fitted(self)
        return self.scaler_.transform(validate_data(self, X, reset=False))

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

        Raises
        ------
        ValueError
            ``X`` has another number of columns than in ``fit``.
        """
        Zs = self._standardised(X)
        means, stds = [], []
        for start in range(0, len(Zs), _CHUNK):
            chunk = Zs[start:start + _CHUNK]
            Hs = self._design(chunk)
            mean, r = predictive_mean(self.Z_condition_, chunk, Hs, self.theta_, self.beta_norm_, self.alpha_)
            means.append(mean)
            if not return_std:  # the mean needs no triangular solve against the training points
                continue
            V, W = variance_parts(r, Hs, self.L_, self.Ht_, self.LM_)
            var = latent_variance(V, W) + include_noise * self.nugget_
            stds.append(np.sqrt(np.clip(var * self.sigma2_norm_, 0.0, None)))
        mean = np.concatenate(means) * self.y_std_ + self.y_mean_ if means else np.empty(0)
        if not return_std:
            return mean
        return mean, (np.concatenate(stds) if stds else np.empty(0)) * self.y_std_

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

        Raises
        ------
        ValueError
            ``X`` has another number of columns than in ``fit``.
        """
        Zs = self._standardised(X)
        Hs = self._design(Zs)
        mean, r = predictive_mean(self.Z_condition_, Zs, Hs, self.theta_, self.beta_norm_, self.alpha_)
        V, W = variance_parts(r, Hs, self.L_, self.Ht_, self.LM_)
        cov = correlation(Zs, Zs, self.theta_) - V.T @ V + W.T @ W
        return mean * self.y_std_ + self.y_mean_, cov * (self.sigma2_norm_ * self.y_std_**2)

    @limit_blas
    def sample_functions(self, X, n_samples=1, random_state=None):
        """Joint draws of the latent bias function (no nugget) at the points ``X``.

        The covariance includes the trend-estimation term; it is factorised with the smallest
        diagonal jitter that works (:func:`crashfuse.gp.sampling.jittered_cholesky`).

        Parameters
        ----------
        X : array_like, shape (m, d)
        n_samples : int
        random_state : int, RandomState or None

        Returns
        -------
        ndarray, shape (n_samples, m)

        Raises
        ------
        ValueError
            ``X`` has another number of columns than in ``fit``.
        """
        mean, cov = self.predict_cov(X)
        return joint_draws(mean, cov, n_samples, random_state)
