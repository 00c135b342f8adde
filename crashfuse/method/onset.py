"""Corrections of a bias model from its own held-out errors, over the time since contact: the held-out
shrinkage (its mean scaled to what predicts a left-out test) and the onset correction (a GP on what is left
early in the pulse).

See ``docs/bias-model.md``, "Held-out shrinkage" and "Onset correction".
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin, clone
from sklearn.utils.validation import check_array, check_is_fitted, validate_data

from crashfuse.gp.replicates import ReplicateMeanGP
from crashfuse.gp.subsets import stratified_subset

__all__ = ["OnsetCorrectedBias", "ONSET_WINDOW", "SHRINK_WIDTH", "shrink_profile"]

# s: the correction is whole up to 15 ms after contact and fades out by 22 ms, where the onset
# transients locked in time have died out (docs/bias-model.md, "Onset correction").
ONSET_WINDOW = (0.015, 0.022)
ONSET_MAX_ROWS = 2500  # rows (stratified per test) of the base model's O(n^3) held-out residuals
# The correction GP learns per-bin means over the tests (each test's rows are one replicate, not many),
# in this many bins up to window[1] (1 ms for the state default).
ONSET_BINS = 22
# s: width of the Gaussian window over the time since contact in which the held-out shrinkage
# scales the bias mean - a few ms, the scale of a pulse's bumps (docs/bias-model.md, "Held-out shrinkage").
SHRINK_WIDTH = 0.005
SHRINK_STEP = 0.001  # s, spacing of the times the shrinkage factor is tabulated at


class OnsetCorrectedBias(RegressorMixin, BaseEstimator):
    """A bias model corrected by its own held-out errors over the time since contact.

    The base model's leave-one-test-out residuals on the training tests show where it predicts a
    left-out test and where not. Two corrections learn from them, over the nominal time since contact:

    - **Held-out shrinkage** (``shrink_width``): where the other tests' bias does not predict a test's
      (bumps of one or two tests carried to their neighbours), the base mean is scaled towards 0, the
      CAE model's pulse. Per time ``t`` the factor is the least-squares scale of the held-out predictions
      ``m`` onto the bias ``y`` in a Gaussian window about ``t``, ``sum w y m / sum w m^2`` clipped
      to [0, 1] (:func:`shrink_profile`): 1 where the held-out predictions are right, 0 where they
      are no better than 0.
    - **Onset correction** (``window``): features locked in time after contact (the onset transients
      of structure and instrumentation) move with the impact speed in displacement, so a GP over the
      branch coordinate interpolates them between tests out of phase. A zero-mean GP over the time
      since contact learns what the tests share of the held-out error left after the shrinkage before
      ``window[1]``: per-bin means over the tests, each with its standard error as noise
      (:class:`crashfuse.gp.replicates.ReplicateMeanGP`), so one test's correlated noise is shrunk, not
      followed. Its mean is added, whole up to ``window[0]`` and faded out by ``window[1]`` (cos^2).

    Both move the mean only: the latent band and the draws' spread about the mean stay the base
    model's. The test-to-test scatter adds what the shrinkage took off the mean and, while the onset
    correction acts, how far the training tests' held-out errors lie from it (:meth:`scatter_std`).

    Parameters
    ----------
    base : estimator
        The bias model (:class:`crashfuse.method.mixture.GMMGPBias`), cloned and fitted on all rows.
    time : callable
        Maps inputs ``X`` (m, d) to the nominal time since contact in s, shape (m,)
        (:func:`crashfuse.method.projection.nominal_time`); a function listed in
        :mod:`crashfuse.method.files`, or a ``functools.partial`` of one, so that a model file can store it.
    window : (float, float) or None
        Times (s) where the onset correction starts to fade and where it is gone; None: no onset correction.
    shrink_width : float or None
        Width (s, the std of the Gaussian window) of the held-out shrinkage; None: no shrinkage.
    max_rows : int
        At most this many rows (evenly spaced within each test) enter the residuals.

    Attributes
    ----------
    base_ : estimator
        The fitted base model.
    shrink_times_ : ndarray, shape (n_t,) or None
        Times since contact (s) the shrinkage factor is tabulated at (linear in between, the ends held
        beyond); None without shrinkage or residuals.
    shrink_ : ndarray, shape (n_t,) or None
        The shrinkage factor at ``shrink_times_``, in [0, 1].
    onset_gp_ : ReplicateMeanGP or None
        The correction GP over time (s), on per-bin means over the tests with their standard errors; None
        when fewer than two bins are reached by three tests or the residuals could not be computed (no correction).
    """

    def __init__(self, *, base=None, time=None, window=ONSET_WINDOW, shrink_width=None, max_rows=ONSET_MAX_ROWS):
        self.base = base
        self.time = time
        self.window = window
        self.shrink_width = shrink_width
        self.max_rows = max_rows

    def fit(self, X, y, groups, pooled_gp=None):
        """Fit the base model on every row, then the shrinkage and the onset GP on its held-out residuals.

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
        self.shrink_times_ = self.shrink_ = self.onset_gp_ = None
        rows = stratified_subset(groups, self.max_rows)
        t, y, groups = np.asarray(self.time(X[rows]), dtype=float), y[rows], groups[rows]
        early = t < self.window[1] if self.window is not None else np.zeros(len(t), bool)
        if self.shrink_width is None and len(np.unique(groups[early])) < 3:
            return self
        res = self.base_.grouped_residuals(X[rows], y, groups)
        if res is None:
            return self
        if self.shrink_width is not None:
            self.shrink_times_ = np.arange(0.0, t.max() + SHRINK_STEP, SHRINK_STEP)
            self.shrink_ = shrink_profile(self.shrink_times_, t, y, y - res, self.shrink_width)
            res = y - self._shrunk(t, y - res)
        if self.window is None:
            return self
        try:
            # The tests are the replicates: a GP on per-bin means over the tests, each with its standard
            # error, follows what the tests share and shrinks what one test's correlated noise shows.
            self.onset_gp_ = ReplicateMeanGP(self.window[1] / ONSET_BINS).fit(t[early], res[early], groups[early])
        except ValueError:  # fewer than two bins reached by three tests
            self.onset_gp_ = None
        return self

    @property
    def gps_(self):
        """The base model's GPs."""
        return self.base_.gps_

    def all_rows_gp(self):
        """The base model's :meth:`GMMGPBias.all_rows_gp`."""
        return self.base_.all_rows_gp()

    def _shrunk(self, t, mean):
        """The base mean ``mean`` (..., m) at times ``t`` (m,) in s, times the shrinkage factor there."""
        return np.interp(t, self.shrink_times_, self.shrink_) * mean

    def _shrinks(self):
        """Whether the mean is shrunk."""
        return getattr(self, "shrink_", None) is not None  # None: no shrinkage, or a model file from before it

    def _discount(self, X, base_mean):
        """What the shrinkage takes off the base mean ``base_mean`` (m,) at ``X`` (y units), shape (m,)."""
        return self._shrunk(np.asarray(self.time(X), dtype=float), base_mean) - base_mean

    def _mean_shift(self, X, base_mean):
        """What the corrections add to the base mean ``base_mean`` (m,) at ``X`` (y units), shape (m,)."""
        shift = self.correction(X)
        return shift + self._discount(X, base_mean) if self._shrinks() else shift

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
        """Leave-one-test-out residuals of base model and corrections at fixed hyperparameters (y units).

        The base model's (:meth:`GMMGPBias.held_out_residuals`), its held-out prediction shrunk as in
        :meth:`predict` (the factor is the fitted one); on the early rows the correction GP,
        conditioned on the other tests' residuals, predicts a left-out test's, faded as in
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
        if e is None:
            return None
        t = np.asarray(self.time(X), dtype=float)
        if self._shrinks():
            y = np.asarray(y, dtype=float)
            e = y - self._shrunk(t, y - e)
        if self.onset_gp_ is None:
            return e
        early = t < self.window[1]
        if len(np.unique(groups[early])) < 2:
            return e
        e_o = self.onset_gp_.grouped_residuals(t[early], e[early], groups[early])
        e[early] -= self._fade(t[early]) * (e[early] - e_o)
        return e

    def predict(self, X, return_std=False):
        """The base prediction, shrunk, plus the onset correction; ``std`` (if asked) is the base model's."""
        check_is_fitted(self)
        X = check_array(X)
        mean, std = self.base_.predict(X, return_std=True) if return_std else (self.base_.predict(X), None)
        mean = mean + self._mean_shift(X, mean)
        return (mean, std) if return_std else mean

    def sample_functions(self, X, n_samples=1, random_state=None):
        """The base model's joint draws, each shifted as its mean is (:meth:`predict`), shape (n_samples, m)."""
        check_is_fitted(self)
        X = check_array(X)
        base_mean = self.base_.predict(X) if self._shrinks() else None
        return self.base_.sample_functions(X, n_samples, random_state) + self._mean_shift(X, base_mean)

    def scatter_std(self, X):
        """Test-to-test scatter std (y units), shape (m,): the base model's and, in quadrature, what the
        shrinkage took off the mean (a new test may have the bump its neighbours had) and, early in the pulse,
        how far a new test's held-out error lies from the onset correction - the correction GP's predictive
        std of a new residual (its noise included), faded as the correction."""
        X = check_array(X)
        var = self.base_.scatter_std(X) ** 2
        if self._shrinks():
            var = var + self._discount(X, self.base_.predict(X)) ** 2
        if self.onset_gp_ is not None:
            var = var + self._faded(X, lambda t: self.onset_gp_.predict(t, return_std=True, include_noise=True)[1]) ** 2
        return np.sqrt(var)

    def held_out_std(self, X):
        """The base model's :meth:`GMMGPBias.held_out_std`."""
        return self.base_.held_out_std(X)

    def predict_responsibilities(self, X):
        """The base model's mixture responsibilities, shape (m, len(gps_))."""
        return self.base_.predict_responsibilities(X)


def shrink_profile(times, t, y, m, width):
    """The held-out shrinkage factor at ``times``: least-squares scale of held-out predictions onto the bias.

    At each time ``tau``, ``sum w y m / sum w m^2`` clipped to [0, 1], with Gaussian weights
    ``w = exp(-((t - tau) / width)^2 / 2)``; 1 where no row has weight (nothing to judge by).

    Parameters
    ----------
    times : ndarray, shape (n_t,)
        Where the factor is wanted (s).
    t : ndarray, shape (n,)
        Time since contact of each training row (s).
    y : ndarray, shape (n,)
        The bias of each row (y units).
    m : ndarray, shape (n,)
        Its leave-one-test-out prediction (y units).
    width : float
        Std of the window (s).

    Returns
    -------
    ndarray, shape (n_t,)
    """
    w = np.exp(-0.5 * ((times[:, None] - t[None, :]) / width) ** 2)
    num, den = w @ (y * m), w @ (m * m)
    safe = den > np.finfo(float).tiny
    return np.clip(np.divide(num, den, out=np.ones_like(num), where=safe), 0.0, 1.0)
