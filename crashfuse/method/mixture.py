"""The paper's bias model: a Gaussian mixture over the inputs and one kriging GP per cluster (Eq. 16-22).

Inputs ``X`` have shape (n, d) in SI (e.g. ``[s m, v0 m/s, w_f kg, w_r kg]``); the bias ``y``
has shape (n,) in m/s^2 (or relative to the CAE deceleration). See ``docs/bias-model.md``.
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.mixture import GaussianMixture
from sklearn.preprocessing import StandardScaler
from sklearn.utils import check_random_state
from sklearn.utils.validation import check_array, check_is_fitted, validate_data

from crashfuse.errors import InputError
from crashfuse.gp.kriging import SEED_MAX, KrigingGP, data_digest
from crashfuse.gp.optimise import FREE_NUGGET
from crashfuse.gp.threads import controller, limit_blas

__all__ = ["GMMGPBias", "TooFewPointsError", "THETA_MAX_CANDIDATES", "MIN_CLUSTER_TESTS"]

THETA_MAX_CANDIDATES = (1.0, 10.0, 100.0, 1000.0)  # theta upper bounds GMMGPBias chooses from by grouped CV
# A pooled model's cluster GP is judged by leaving its tests out one at a time: with fewer than three
# the judgement (and the GP's own theta bound and band calibration) is impossible.
MIN_CLUSTER_TESTS = 3
# Rows one GP conditions on: every row of up to 20 tests at the default 200 points per test and branch
# (the exact GP); a larger test library keeps an even share of each test (docs/bias-model.md, "Speed").
MAX_CONDITION_POINTS = 4000


class TooFewPointsError(ValueError):
    """Fewer bias points than :class:`GMMGPBias` needs for its clusters and their GP parameters."""



class GMMGPBias(RegressorMixin, BaseEstimator):
    """The paper's bias model: a Gaussian mixture over the inputs and one KrigingGP per cluster.

    Parameters
    ----------
    n_clusters : int
        Mixture components K.
    cluster_inputs : sequence of int or None
        Columns of ``X`` the mixture sees (default all).
    assignment : {'select', 'blend'}
        ``'select'``: the GP of the most responsible cluster (paper section 3.2).
        ``'blend'``: responsibility-weighted mean of the cluster GPs (paper introduction).
    trend, theta_bounds, nugget_bounds, n_restarts, theta_max_candidates, calibrate_variance, estimate_scatter
        Passed to every cluster's :class:`KrigingGP`. The last three act only when ``fit`` gets
        ``groups``; their defaults here (choose the theta bound among ``THETA_MAX_CANDIDATES``,
        calibrate the band by grouped leave-one-test-out, estimate the test-to-test scatter by
        grouped refits) are the bias model's, see
        ``docs/bias-model.md``.
    max_fit_points, max_condition_points, normalize_y, blas_threads
        Passed to every cluster's :class:`KrigingGP` (``max_condition_points`` default
        :data:`MAX_CONDITION_POINTS`, not the GP's all; ``blas_threads`` also limits the
        mixture, the OpenMP threads of its k-means initialisation, and the prediction methods
        here). ``max_*`` apply per cluster.
    n_init : int
        GaussianMixture initialisations.
    reg_covar : float
        Covariance floor on the standardised inputs (v0 and the weights are constant within
        a test, so a one-test cluster has zero variance there).
    min_cluster_points : int or None
        Clusters with fewer hard-assigned points are merged into the cluster whose mixture
        mean is nearest (standardised inputs), smallest first. ``None``: three times the
        number of GP parameters (trend + d theta + nugget + sigma^2).
    pooled : bool
        With more than one cluster: first fit one GP on every point (the K = 1 model, this
        model's trend), then the cluster GPs on its residual without a trend, and predict their
        sum. Where a cluster's few tests say nothing the residual reverts to 0, so the
        prediction to the pooled GP's, not to the cluster's trend; the test-to-test scatter
        is the pooled GP's (the residual GPs estimate none). ``False``: the paper's clusters, each
        GP on its own points' bias.
    min_cluster_tests : int
        With ``pooled`` and ``groups``: a cluster GP speaks only if its points come from at least
        this many tests and, each of them left out in turn, it predicts their residual better
        than 0 (the pooled model) does; otherwise its residual is 0. What it says is shrunk
        towards 0 by its own uncertainty against the variance it predicts out of sample
        (``residual_var_``), so its band cannot outgrow that variance and its mean defers to the
        pooled model where it is unsure.
    random_state : int, RandomState or None
        Seeds the mixture and the GPs.

    Attributes
    ----------
    scaler_ : StandardScaler
        Standardisation of the clustering inputs.
    gmm_ : GaussianMixture
    pooled_gp_ : KrigingGP or None
        The GP on every point (``pooled`` with more than one cluster), else None.
    gps_ : list of KrigingGP
        One per surviving cluster (on the pooled GP's residual when ``pooled_gp_`` is set).
    component_to_gp_ : ndarray of int, shape (n_clusters,)
        Which GP each mixture component's points and responsibility go to.
    n_points_per_cluster_ : ndarray of int, shape (len(gps_),)
    labels_ : ndarray of int, shape (n,)
        GP index of each training point.
    residual_var_ : ndarray, shape (len(gps_),) or None
        With a pooled GP and groups: per cluster GP, the variance of its points' residual that it
        predicts for a left-out test (y units squared), the prior variance its prediction is shrunk
        with; 0 for a GP that does not speak. None otherwise (the cluster GPs are used as fitted).
    """

    def __init__(self, *, n_clusters=1, cluster_inputs=None, assignment="select", trend="constant",
                 theta_bounds=(1e-5, 1e3), nugget_bounds=(FREE_NUGGET, 10.0), n_restarts=2,
                 max_fit_points=300, max_condition_points=MAX_CONDITION_POINTS, normalize_y=True, n_init=5,
                 reg_covar=1e-3, min_cluster_points=None, blas_threads=1, random_state=None,
                 theta_max_candidates=THETA_MAX_CANDIDATES, calibrate_variance=True, estimate_scatter=True,
                 pooled=False, min_cluster_tests=MIN_CLUSTER_TESTS):
        self.pooled = pooled
        self.min_cluster_tests = min_cluster_tests
        self.theta_max_candidates = theta_max_candidates
        self.calibrate_variance = calibrate_variance
        self.estimate_scatter = estimate_scatter
        self.n_clusters = n_clusters
        self.cluster_inputs = cluster_inputs
        self.assignment = assignment
        self.trend = trend
        self.theta_bounds = theta_bounds
        self.nugget_bounds = nugget_bounds
        self.n_restarts = n_restarts
        self.max_fit_points = max_fit_points
        self.max_condition_points = max_condition_points
        self.normalize_y = normalize_y
        self.n_init = n_init
        self.reg_covar = reg_covar
        self.min_cluster_points = min_cluster_points
        self.blas_threads = blas_threads
        self.random_state = random_state

    def _gp(self, seed, trend=None, estimate_scatter=None):
        """An unfitted GP with this model's settings (``trend`` and ``estimate_scatter`` overridable)."""
        return KrigingGP(trend=self.trend if trend is None else trend, theta_bounds=self.theta_bounds,
                         nugget_bounds=self.nugget_bounds, n_restarts=self.n_restarts,
                         max_fit_points=self.max_fit_points,
                         max_condition_points=self.max_condition_points,
                         normalize_y=self.normalize_y, blas_threads=self.blas_threads,
                         random_state=seed, theta_max_candidates=self.theta_max_candidates,
                         calibrate_variance=self.calibrate_variance,
                         estimate_scatter=self.estimate_scatter if estimate_scatter is None else estimate_scatter)

    def _min_points(self, d):
        """Smallest cluster that keeps its own GP."""
        if self.min_cluster_points is not None:
            return int(self.min_cluster_points)
        p = (self.trend != "zero") + (d if self.trend == "linear" else 0)
        return 3 * (p + d + 2)

    @limit_blas
    def fit(self, X, y, groups=None, pooled_gp=None):
        """Fit scaler and mixture on ``X``, then one KrigingGP per (merged) cluster.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
            Bias, m/s^2.
        groups : array_like, shape (n,), optional
            Test of each row, passed to the cluster GPs (:meth:`KrigingGP.fit`).
        pooled_gp : KrigingGP, optional
            The pooled GP already fitted, e.g. :meth:`all_rows_gp` of another K's model of the same
            rows and seed: the same fit, so it is taken as it is (the result is identical, the cost
            of the pooled GP saved). Used only where this model pools.

        Returns
        -------
        self

        Raises
        ------
        ValueError
            ``pooled_gp`` was fitted on other rows, with other settings or another seed.
        """
        if self.assignment not in ("select", "blend"):
            raise ValueError(f"assignment must be 'select' or 'blend', got {self.assignment!r}")
        X, y = validate_data(self, X, y, y_numeric=True)
        need = self._min_points(X.shape[1])
        if len(y) < max(need, self.n_clusters):
            raise TooFewPointsError(f"GMMGPBias needs at least {max(need, self.n_clusters)} bias points "
                                    f"(min_cluster_points={need}, n_clusters={self.n_clusters}), got {len(y)}")
        rng = check_random_state(self.random_state)
        C = self._cluster_view(X, fit=True)
        # The mixture keeps only the labels of its k-means start, so its OpenMP threads change
        # nothing but the cost: on the shared 2-core machine they spend 5-10x the CPU of one
        # thread (docs/decisions.md, section 12).
        with controller().limit(limits=self.blas_threads, user_api="openmp"):
            self.gmm_ = GaussianMixture(self.n_clusters, covariance_type="full", n_init=self.n_init,
                                        reg_covar=self.reg_covar,
                                        random_state=rng.randint(SEED_MAX)).fit(C)
        self.component_to_gp_ = self._merge(self.gmm_.predict(C), need)
        self.labels_ = self.component_to_gp_[self.gmm_.predict(C)]
        n_gps = self.component_to_gp_.max() + 1
        self.n_points_per_cluster_ = np.bincount(self.labels_, minlength=n_gps)
        groups = None if groups is None else np.asarray(groups)
        self.pooled_gp_ = None
        if self.pooled and n_gps > 1:
            self.pooled_gp_ = self._pooled_fit(self._gp(rng.randint(SEED_MAX)), X, y, groups, pooled_gp)
            y = y - self.pooled_gp_.predict(X)
        residual = {"trend": "zero", "estimate_scatter": False} if self.pooled_gp_ is not None else {}
        self.gps_ = [self._gp(rng.randint(SEED_MAX), **residual).fit(
            X[self.labels_ == g], y[self.labels_ == g], None if groups is None else groups[self.labels_ == g])
            for g in range(n_gps)]
        self.residual_var_ = None
        if self.pooled_gp_ is not None and groups is not None:
            self.residual_var_ = np.array([self._residual_prior(gp, groups[self.labels_ == g])
                                           for g, gp in enumerate(self.gps_)])
        return self

    @staticmethod
    def _pooled_fit(gp, X, y, groups, fitted):
        """``gp`` fitted on the rows, or ``fitted`` where it is that same fit (ValueError where it is not)."""
        if fitted is None:
            return gp.fit(X, y, groups)
        if fitted.get_params() != gp.get_params() or getattr(fitted, "data_digest_", None) != data_digest(X, y, groups):
            raise ValueError("pooled_gp is not this model's pooled GP: fitted on other rows, settings or seed")
        return fitted

    def all_rows_gp(self):
        """The GP on every training row with this model's settings and its pooled GP's seed, or None.

        The pooled GP, or the only GP of a model with one cluster: the same fit another K's model of
        the same rows and ``random_state`` makes, which it can take as ``pooled_gp``.
        """
        check_is_fitted(self)
        if self.pooled_gp_ is not None:
            return self.pooled_gp_
        return self.gps_[0] if len(self.gps_) == 1 else None

    def _residual_prior(self, gp, groups):
        """Prior variance of one cluster GP (y units squared): the part of its residual its tests show it predicts.

        ``mean(r^2) - mean(e^2)``, with ``r`` the pooled residual it was fitted on and ``e`` its
        leave-one-test-out residuals (closed form at its hyperparameters, on its hyperparameter-fit
        subset); 0 - the GP does not speak - when that is not positive or its points come from
        fewer than ``min_cluster_tests`` tests. On noise the GP predicts a left-out test no better
        than 0 does, so its prior variance, hence its residual, is about 0.
        """
        if len(np.unique(groups)) < max(self.min_cluster_tests, 2):
            return 0.0
        e = gp.grouped_cv_residuals()
        if e is None:
            return 0.0
        return max(0.0, float(np.mean(gp.u_fit_**2) - np.mean(e**2))) * gp.y_std_**2

    def _shrink(self, g):
        """Shrinkage of cluster GP ``g``: a function of its latent variance (y units squared), or None."""
        if self.residual_var_ is None:
            return None
        tau2 = self.residual_var_[g]
        return lambda var: tau2 / (tau2 + var) if tau2 > 0 else np.zeros_like(var)

    def _cluster_predict(self, g, X, return_std=False):
        """Cluster GP ``g``'s mean (and latent std) at ``X``, shrunk towards 0 with a pooled GP.

        With the prior variance ``tau^2`` of :attr:`residual_var_`, the GP's ``N(mu, s^2)`` becomes
        ``N(w mu, w s^2)`` with ``w = tau^2 / (tau^2 + s^2)``: the precision-weighted combination
        with ``N(0, tau^2)``. Where the GP is sure (``s^2 << tau^2``) nothing changes; where its
        tests say nothing the residual goes to 0 and its variance stays below ``tau^2``.
        """
        gp, shrink = self.gps_[g], self._shrink(g)
        if shrink is None:
            return gp.predict(X, return_std=return_std)
        if self.residual_var_[g] == 0:  # it does not speak: nothing to predict (its std costs O(n^2) a point)
            zeros = np.zeros(len(X))
            return (zeros, zeros) if return_std else zeros
        mu, sd = gp.predict(X, return_std=True)
        w = shrink(sd**2)
        return (w * mu, np.sqrt(w) * sd) if return_std else w * mu

    def _cluster_view(self, X, fit=False):
        """Standardised clustering columns of ``X``, shape (n, d_cluster)."""
        cols = list(range(X.shape[1])) if self.cluster_inputs is None else list(self.cluster_inputs)
        if fit:
            self.scaler_ = StandardScaler().fit(X[:, cols])
        return self.scaler_.transform(X[:, cols])

    def _merge(self, labels, need):
        """Map mixture components to GPs, merging clusters smaller than ``need`` points.

        Parameters
        ----------
        labels : ndarray of int, shape (n,)
            Hard mixture assignment of the training points.
        need : int

        Returns
        -------
        ndarray of int, shape (n_clusters,)
            GP index (0..n_gps-1, in component order) of each component.
        """
        owner = np.arange(self.n_clusters)
        means = self.gmm_.means_
        while True:
            counts = np.bincount(owner[labels], minlength=self.n_clusters)
            roots = np.flatnonzero(owner == np.arange(self.n_clusters))  # components owning a GP
            small = roots[counts[roots] < need]  # includes components with no points at all
            if len(small) == 0 or len(roots) == 1:
                break
            c = small[np.argmin(counts[small])]
            others = roots[roots != c]
            owner[owner == c] = others[np.argmin(np.linalg.norm(means[others] - means[c], axis=1))]
        return np.unique(owner, return_inverse=True)[1]

    def predict_responsibilities(self, X):
        """Mixture responsibilities summed per GP (merged components add up).

        Parameters
        ----------
        X : array_like, shape (m, d)

        Returns
        -------
        ndarray, shape (m, len(gps_))
            Rows sum to one.
        """
        check_is_fitted(self)
        X = validate_data(self, X, reset=False)
        resp = self.gmm_.predict_proba(self._cluster_view(X))
        out = np.zeros((len(X), len(self.gps_)))
        np.add.at(out.T, self.component_to_gp_, resp.T)
        return out

    def _weights(self, X):
        """Per-GP weights of the assignment rule, shape (m, len(gps_))."""
        resp = self.predict_responsibilities(X)
        if self.assignment == "blend":
            return resp
        return np.eye(len(self.gps_))[np.argmax(resp, axis=1)]

    @limit_blas
    def predict(self, X, return_std=False):
        """Bias prediction by the assignment rule.

        Parameters
        ----------
        X : array_like, shape (m, d)
        return_std : bool
            Latent-function std: the selected GP's (``select``) or the mixture's
            ``sqrt(sum_k w_k (s_k^2 + mu_k^2) - mu^2)`` (``blend``).

        Returns
        -------
        mean : ndarray, shape (m,)
        std : ndarray, shape (m,), only if ``return_std``
            With a pooled GP, its variance is added (the two GPs are independent).
        """
        X = check_array(X)
        w = self._weights(X)
        pooled = self._pooled(X, return_std)
        mean, second = np.zeros(len(X)), np.zeros(len(X))
        for g in range(len(self.gps_)):
            use = w[:, g] > 0
            if not use.any():
                continue
            if not return_std:
                mean[use] += w[use, g] * self._cluster_predict(g, X[use])
                continue
            mu, sd = self._cluster_predict(g, X[use], return_std=True)
            mean[use] += w[use, g] * mu
            second[use] += w[use, g] * (sd**2 + mu**2)
        if not return_std:
            return mean + pooled
        return mean + pooled[0], np.sqrt(np.clip(second - mean**2, 0.0, None) + pooled[1] ** 2)

    def _pooled(self, X, return_std=False):
        """The pooled GP's mean (and std) at ``X``; zeros without one."""
        if self.pooled_gp_ is None:
            return (np.zeros(len(X)), np.zeros(len(X))) if return_std else np.zeros(len(X))
        return self.pooled_gp_.predict(X, return_std=return_std)

    def grouped_residuals(self, X, y, groups):
        """Leave-one-test-out residuals of the bias model at fixed hyperparameters (y units).

        The pooled GP's when there is one (the cluster GPs on its residual are not refitted), else
        each GP's (:meth:`KrigingGP.grouped_residuals`) on the rows it is selected for.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
        groups : array_like, shape (n,)

        Returns
        -------
        ndarray, shape (n,) or None
            None where a GP's rows come from a single test or its matrices are singular.
        """
        X, y, groups = check_array(X), np.asarray(y, dtype=float), np.asarray(groups)
        if self.pooled_gp_ is not None:
            return self.pooled_gp_.grouped_residuals(X, y, groups)
        pick = np.argmax(self.predict_responsibilities(X), axis=1)
        out = np.zeros(len(y))
        for g, gp in enumerate(self.gps_):
            rows = pick == g
            if not rows.any():
                continue
            res = gp.grouped_residuals(X[rows], y[rows], groups[rows]) if len(set(groups[rows])) > 1 else None
            if res is None:
                return None
            out[rows] = res
        return out

    def held_out_residuals(self, X, y, groups):
        """Leave-one-test-out residuals of the whole model at fixed hyperparameters (y units).

        As :meth:`grouped_residuals`, but with a pooled GP its cluster GPs count too: each cluster GP
        that speaks (``residual_var_ > 0``) predicts a left-out test's pooled residual from its other
        tests, and that prediction is taken off the pooled GP's held-out residual. The cluster GPs'
        targets are the pooled GP's in-sample residuals (first order: the pooled GP refitted
        without the test would move them a little).

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
        groups : array_like, shape (n,)

        Returns
        -------
        ndarray, shape (n,) or None
            None where a GP's rows come from a single test or its matrices are singular.
        """
        e = self.grouped_residuals(X, y, groups)
        if e is None or self.pooled_gp_ is None:
            return e
        X, groups = check_array(X), np.asarray(groups)
        r = np.asarray(y, dtype=float) - self.pooled_gp_.predict(X)
        pick = np.argmax(self.predict_responsibilities(X), axis=1)
        for g, gp in enumerate(self.gps_):
            rows = pick == g
            if self.residual_var_[g] <= 0 or len(set(groups[rows])) < 2:
                continue  # a cluster GP that does not speak predicts 0
            e_g = gp.grouped_residuals(X[rows], r[rows], groups[rows])
            if e_g is None:
                return None
            e[rows] -= r[rows] - e_g
        return e

    def scatter_std(self, X):
        """Test-to-test scatter std at ``X`` (y units): what a new test adds to the latent band.

        Each GP's scatter near ``X`` (:meth:`KrigingGP.scatter_var_at`): ``select``: the selected GP's;
        ``blend``: ``sqrt(sum_k w_k s_k^2)``; with a pooled GP, the pooled GP's.

        Parameters
        ----------
        X : array_like, shape (m, d)

        Returns
        -------
        ndarray, shape (m,)
        """
        X = check_array(X)
        if self.pooled_gp_ is None and not all(hasattr(gp, "scatter_var_") for gp in self.gps_):
            raise InputError("this bias model was fitted before the test-to-test scatter existed: refit it, or "
                             "ask for the latent band (band 'latent')", field="band")
        return self._combined_std(X, lambda gp: gp.scatter_var_at(X))

    def held_out_std(self, X):
        """The std a new test's errors need at ``X`` (y units), shape (m,): a bound on the band.

        Each GP's :meth:`KrigingGP.held_out_var_at` (the 95 % level of its refits' held-out errors near
        ``X``), combined as :meth:`scatter_std` combines the scatter; ``inf`` for a GP without them.
        """
        X = check_array(X)
        return self._combined_std(X, lambda gp: gp.held_out_var_at(X))

    def _combined_std(self, X, var_at):
        """``sqrt`` of the GPs' variances ``var_at(gp)`` (m,) at ``X``: the pooled GP's, else weighted by
        :meth:`_weights` (a GP of no weight adds nothing, even an infinite variance)."""
        if self.pooled_gp_ is not None:
            return np.sqrt(var_at(self.pooled_gp_))
        w, var = self._weights(X), np.stack([var_at(gp) for gp in self.gps_], axis=1)
        return np.sqrt(np.sum(np.where(w > 0, w * var, 0.0), axis=1))

    @limit_blas
    def sample_functions(self, X, n_samples=1, random_state=None):
        """Joint draws of the bias function at ``X``, combined by the assignment rule.

        Each GP is drawn jointly (no nugget) on the points where its weight is non-zero;
        ``select`` takes the selected GP's draw at each point, ``blend`` the
        responsibility-weighted sum of the independent per-GP draws (whose spread is
        ``sqrt(sum_k w_k^2 s_k^2)``, narrower than the mixture std of ``predict``). A pooled
        GP's joint draw is added.

        Parameters
        ----------
        X : array_like, shape (m, d)
        n_samples : int
        random_state : int, RandomState or None

        Returns
        -------
        ndarray, shape (n_samples, m)
        """
        X = check_array(X)
        w = self._weights(X)
        rng = check_random_state(random_state)
        out = np.zeros((n_samples, len(X)))
        for g in range(len(self.gps_)):
            use = w[:, g] > 0
            seed = rng.randint(SEED_MAX)  # drawn for every GP so seeds don't depend on X
            if use.any():
                out[:, use] += w[use, g] * self._cluster_draws(g, X[use], n_samples, seed)
        if self.pooled_gp_ is not None:
            out += self.pooled_gp_.sample_functions(X, n_samples, rng.randint(SEED_MAX))
        return out

    def _cluster_draws(self, g, X, n_samples, seed):
        """Joint draws of cluster GP ``g`` at ``X``, shape (n_samples, m), shrunk as in :meth:`_cluster_predict`.

        A draw ``f`` becomes ``w mu + sqrt(w) (f - mu)``: mean ``w mu`` and pointwise variance ``w s^2``.
        """
        gp, shrink = self.gps_[g], self._shrink(g)
        if shrink is not None and self.residual_var_[g] == 0:
            return np.zeros((n_samples, len(X)))
        draws = gp.sample_functions(X, n_samples, seed)
        if shrink is None:
            return draws
        mu, sd = gp.predict(X, return_std=True)
        w = shrink(sd**2)
        return w * mu + np.sqrt(w) * (draws - mu)
