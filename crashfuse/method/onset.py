"""The onset correction: a GP over the time since contact on a bias model's held-out residuals.

See ``docs/bias-model.md``, "Onset correction".
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin, clone
from sklearn.utils.validation import check_array, check_is_fitted, validate_data

from crashfuse.gp.kriging import KrigingGP
from crashfuse.gp.subsets import stratified_subset

__all__ = ["OnsetCorrectedBias", "ONSET_WINDOW"]

# s: the correction is whole up to 15 ms after contact and fades out by 22 ms, where the onset
# transients locked in time have died out (docs/bias-model.md, "Onset correction").
ONSET_WINDOW = (0.015, 0.022)
ONSET_MAX_ROWS = 2500  # rows (stratified per test) of the base model's O(n^3) held-out residuals
# Early rows (stratified per test) in the correction GP's likelihood; it conditions on every early row.
# Above every fold of the `paper` campaign (899 rows), below a 44-test library's 1234 (5 s a fit with all).
ONSET_FIT_ROWS = 1000


class OnsetCorrectedBias(RegressorMixin, BaseEstimator):
    """A bias model plus a correction of its held-out error early in the pulse, over time since contact.

    Features locked in time after contact (the onset transients of structure and instrumentation)
    move with the impact speed in displacement, so a GP over the branch coordinate interpolates
    them between tests out of phase. The base model's leave-one-test-out residuals expose that
    error; a zero-mean GP over the nominal time since contact learns it from the rows earlier
    than ``window[1]`` and its mean is added to the base model's, whole up to ``window[0]`` and
    faded out by ``window[1]`` (cos^2). The correction is a point estimate: the latent band and
    the draws' spread stay the base model's; the test-to-test scatter adds, while the correction
    acts, how far the training tests' held-out errors lie from it (:meth:`scatter_std`).

    Parameters
    ----------
    base : estimator
        The bias model (:class:`crashfuse.method.mixture.GMMGPBias`), cloned and fitted on all rows.
    time : callable
        Maps inputs ``X`` (m, d) to the nominal time since contact in s, shape (m,)
        (:func:`crashfuse.method.projection.nominal_time`); a function listed in
        :mod:`crashfuse.method.files`, or a ``functools.partial`` of one, so that a model file can store it.
    window : (float, float)
        Times (s) where the correction starts to fade and where it is gone.
    max_rows : int
        At most this many rows (evenly spaced within each test) enter the residuals.
    blas_threads : int or None
        BLAS threads of the correction GP.
    random_state : int, RandomState or None
        Seeds the correction GP.

    Attributes
    ----------
    base_ : estimator
        The fitted base model.
    onset_gp_ : KrigingGP or None
        The correction GP over time (s); None when fewer than three tests reach the window or
        the residuals could not be computed (no correction).
    """

    def __init__(self, *, base=None, time=None, window=ONSET_WINDOW, max_rows=ONSET_MAX_ROWS, blas_threads=1,
                 random_state=None):
        self.base = base
        self.time = time
        self.window = window
        self.max_rows = max_rows
        self.blas_threads = blas_threads
        self.random_state = random_state

    def fit(self, X, y, groups, pooled_gp=None):
        """Fit the base model on every row, then the correction GP on its held-out residuals.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
        groups : array_like, shape (n,)
            Test of each row.
        pooled_gp : KrigingGP, optional
            Passed to the base model's ``fit`` (:meth:`GMMGPBias.fit`).

        Returns
        -------
        self
        """
        X, y = validate_data(self, X, y, y_numeric=True)
        groups = np.asarray(groups)
        self.base_ = clone(self.base).fit(X, y, groups, pooled_gp=pooled_gp)
        self.onset_gp_ = None
        rows = stratified_subset(groups, self.max_rows)
        t = np.asarray(self.time(X[rows]), dtype=float)
        early = t < self.window[1]
        if len(np.unique(groups[rows][early])) < 3:
            return self
        res = self.base_.grouped_residuals(X[rows], y[rows], groups[rows])
        if res is not None:
            # Up to ONSET_FIT_ROWS early rows enter the likelihood, not 300: on a 300-row subset some
            # seeds' restarts stop in a flat optimum (no correction).
            gp = KrigingGP(trend="zero", max_fit_points=ONSET_FIT_ROWS, estimate_scatter=False,
                           blas_threads=self.blas_threads, random_state=self.random_state)
            self.onset_gp_ = gp.fit(t[early, None], res[early], groups[rows][early])
        return self

    @property
    def gps_(self):
        """The base model's GPs."""
        return self.base_.gps_

    def all_rows_gp(self):
        """The base model's :meth:`GMMGPBias.all_rows_gp`."""
        return self.base_.all_rows_gp()

    def correction(self, X):
        """The onset correction at ``X`` (y units), shape (m,): 0 from ``window[1]`` on."""
        check_is_fitted(self)
        X = check_array(X)
        if self.onset_gp_ is None:
            return np.zeros(len(X))
        return self._faded(X, self.onset_gp_.predict)

    def _faded(self, X, of_time):
        """``fade(t) * of_time(t)`` at ``X``, shape (m,); ``of_time`` maps times (k, 1) in s to (k,)."""
        t = np.asarray(self.time(X), dtype=float)
        fade = self._fade(t)
        out = np.zeros(len(t))
        on = fade > 0
        if on.any():
            out[on] = fade[on] * of_time(t[on, None])
        return out

    def _fade(self, t):
        """Weight of the correction at time since contact ``t`` (s): 1 up to ``window[0]``, cos^2 to 0 at ``window[1]``."""
        return np.cos(0.5 * np.pi * np.clip((t - self.window[0]) / (self.window[1] - self.window[0]), 0.0, 1.0)) ** 2

    def held_out_residuals(self, X, y, groups):
        """Leave-one-test-out residuals of base model and correction at fixed hyperparameters (y units).

        The base model's (:meth:`GMMGPBias.held_out_residuals`); on the early rows the correction GP,
        conditioned on the other tests' base residuals, predicts a left-out test's, faded as in
        :meth:`correction`.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
        groups : array_like, shape (n,)

        Returns
        -------
        ndarray, shape (n,) or None
            None where the base model's residuals are (a GP's rows from one test, a singular matrix).
        """
        check_is_fitted(self)
        X, groups = check_array(X), np.asarray(groups)
        e = self.base_.held_out_residuals(X, y, groups)
        if e is None or self.onset_gp_ is None:
            return e
        t = np.asarray(self.time(X), dtype=float)
        early = t < self.window[1]
        if len(np.unique(groups[early])) < 2:
            return e
        e_o = self.onset_gp_.grouped_residuals(t[early, None], e[early], groups[early])
        if e_o is None:
            return None
        e[early] -= self._fade(t[early]) * (e[early] - e_o)
        return e

    def predict(self, X, return_std=False):
        """Base prediction plus the correction; ``std`` (if asked) is the base model's."""
        check_is_fitted(self)
        if not return_std:
            return self.base_.predict(X) + self.correction(X)
        mean, std = self.base_.predict(X, return_std=True)
        return mean + self.correction(X), std

    def sample_functions(self, X, n_samples=1, random_state=None):
        """The base model's joint draws, each plus the correction, shape (n_samples, m)."""
        check_is_fitted(self)
        return self.base_.sample_functions(X, n_samples, random_state) + self.correction(X)

    def scatter_std(self, X):
        """Test-to-test scatter std (y units), shape (m,): the base model's, and early in the pulse, in
        quadrature, how far a new test's held-out error lies from the correction - the correction GP's
        predictive std of a new residual (its noise included), faded as the correction."""
        base = self.base_.scatter_std(X)
        if self.onset_gp_ is None:
            return base
        sd = self._faded(check_array(X), lambda t: self.onset_gp_.predict(t, return_std=True, include_noise=True)[1])
        return np.sqrt(base**2 + sd**2)

    def predict_responsibilities(self, X):
        """The base model's mixture responsibilities, shape (m, len(gps_))."""
        return self.base_.predict_responsibilities(X)
