"""A zero-mean GP over one input fitted to what groups share: per-bin means over the groups, each with its
standard error as known noise.

Rows of one group (test) are not independent evidence: a test's noise and transients are correlated along
its record. Binned along the input (e.g. time since contact), each bin's mean over the groups has the
test-to-test standard error ``se^2 = s^2 / n_groups``; a GP with that noise shrinks the bin means towards 0
where the groups disagree and follows them where they agree. Pure numpy/scipy; deterministic (the
hyperparameters are searched from fixed starts).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize
from sklearn.base import BaseEstimator

__all__ = ["ReplicateMeanGP", "bin_means"]

LENGTH_BOUNDS = (0.5, 50.0)  # in bin widths: from one bin to far beyond the binned range
LENGTH_STARTS = (1.0, 3.0, 10.0)  # in bin widths


def bin_means(x, y, groups, width, min_groups):
    """Per-bin mean over the groups of each group's mean in the bin, with the spread between groups.

    Parameters
    ----------
    x, y : ndarray, shape (n,)
    groups : ndarray, shape (n,)
    width : float
        Bin width (``x`` units); bins start at 0.
    min_groups : int
        Bins with fewer groups are left out.

    Returns
    -------
    centres, means, spread2 : ndarray, shape (n_bins,)
        Bin centres, the mean over groups, and the variance between the groups' means (ddof 1).
    counts : ndarray of int, shape (n_bins,)
        Groups in each bin.
    """
    bins = np.floor(np.asarray(x, float) / width).astype(int)
    cells = {}
    for b, g, v in zip(bins, groups, y):
        cells.setdefault(b, {}).setdefault(g, []).append(v)
    keep = sorted(b for b, per in cells.items() if len(per) >= min_groups)
    per_bin = [np.array([np.mean(v) for v in cells[b].values()]) for b in keep]
    centres = (np.array(keep, float) + 0.5) * width
    means = np.array([m.mean() for m in per_bin])
    spread2 = np.array([m.var(ddof=1) for m in per_bin])
    return centres, means, spread2, np.array([len(m) for m in per_bin], int)


def _kernel(a, b, length, sf2):
    return sf2 * np.exp(-0.5 * ((a[:, None] - b[None, :]) / length) ** 2)


def _factor(centres, noise, length, sf2):
    """Cholesky factor (``cho_factor``) of the bin means' covariance: kernel plus each mean's known noise."""
    return cho_factor(_kernel(centres, centres, length, sf2) + np.diag(noise), lower=True, check_finite=False)


class ReplicateMeanGP(BaseEstimator):
    """Zero-mean GP, squared-exponential kernel, on the bin means of replicated groups.

    Parameters
    ----------
    bin_width : float
        Bin width along the input.
    min_groups : int
        Groups a bin needs (at least 3: a spread from two is no estimate).

    Attributes
    ----------
    centres_, means_ : ndarray, shape (n_bins,)
        The bins the GP is conditioned on.
    noise_ : ndarray, shape (n_bins,)
        Standard error squared of each bin mean (``spread2 / counts``).
    spread2_ : ndarray, shape (n_bins,)
        Variance between the groups' means per bin: how far a new group lies from the shared function.
    length_, sf2_ : float
        Fitted length scale (input units) and signal variance (output units squared).
    """

    _derived_attributes = ("_chol", "_alpha")  # a model file stores the bins and hyperparameters; refactorised on use

    def __init__(self, bin_width, min_groups=3):
        self.bin_width = bin_width
        self.min_groups = min_groups

    def fit(self, x, y, groups):
        """Bin, then maximise the marginal likelihood of the bin means over length scale and signal variance.

        Parameters
        ----------
        x, y : array_like, shape (n,)
        groups : array_like, shape (n,)

        Returns
        -------
        self

        Raises
        ------
        ValueError
            Fewer than two bins reach ``min_groups`` groups.
        """
        self.centres_, self.means_, self.spread2_, counts = bin_means(
            np.ravel(x), np.asarray(y, float), np.asarray(groups), self.bin_width, self.min_groups)
        if len(self.centres_) < 2:
            raise ValueError(f"ReplicateMeanGP needs two bins with {self.min_groups} groups, got {len(self.centres_)}")
        self.noise_ = self._noise(self.spread2_, counts)
        self.length_, self.sf2_ = self._maximise()
        self._condition()
        return self

    @staticmethod
    def _noise(spread2, counts):
        # A bin whose groups agree to the last bit would pin the GP; floor at a millionth of the typical error.
        se2 = spread2 / counts
        return np.maximum(se2, 1e-6 * max(float(np.median(se2)), np.finfo(float).tiny))

    def _nll(self, p):
        try:
            c = _factor(self.centres_, self.noise_, *np.exp(p))
        except np.linalg.LinAlgError:
            return 1e300
        return 0.5 * self.means_ @ cho_solve(c, self.means_) + np.log(np.diag(c[0])).sum()

    def _maximise(self):
        scale = max(float(np.mean(self.means_ ** 2)), float(np.median(self.noise_)))
        bounds = [np.log(np.multiply(LENGTH_BOUNDS, self.bin_width)), (np.log(scale * 1e-6), np.log(scale * 1e2))]
        fits = [minimize(self._nll, [np.log(ell * self.bin_width), np.log(scale)], method="L-BFGS-B", bounds=bounds)
                for ell in LENGTH_STARTS]
        best = min(fits, key=lambda r: r.fun)
        return tuple(float(v) for v in np.exp(best.x))

    def _condition(self):
        self._chol = _factor(self.centres_, self.noise_, self.length_, self.sf2_)
        self._alpha = cho_solve(self._chol, self.means_)

    def _conditioned(self):
        if "_alpha" not in self.__dict__:  # a model file holds the bins and hyperparameters only
            self._condition()

    def predict(self, x, return_std=False, include_noise=False):
        """Mean of the shared function at ``x`` (shape (m,) or (m, 1)); with ``return_std`` its std, and with
        ``include_noise`` the std of a new group's value there (the spread between groups added)."""
        self._conditioned()
        x = np.ravel(x)
        k = _kernel(x, self.centres_, self.length_, self.sf2_)
        mean = k @ self._alpha
        if not return_std:
            return mean
        var = self.sf2_ - np.einsum("ij,ji->i", k, cho_solve(self._chol, k.T))
        if include_noise:
            var = var + np.interp(x, self.centres_, self.spread2_)
        return mean, np.sqrt(np.maximum(var, 0.0))

    def grouped_residuals(self, x, y, groups):
        """``y`` minus each group's prediction from the bins of the other groups (hyperparameters fixed).

        Returns
        -------
        ndarray, shape (n,)
            A group whose others leave fewer than two bins is predicted as 0 (no correction without it).
        """
        x, y, groups = np.ravel(x), np.asarray(y, float), np.asarray(groups)
        out = np.empty_like(y)
        for g in np.unique(groups):
            own = groups == g
            c, m, s2, n = bin_means(x[~own], y[~own], groups[~own], self.bin_width, self.min_groups)
            if len(c) < 2:
                out[own] = y[own]
                continue
            alpha = cho_solve(_factor(c, self._noise(s2, n), self.length_, self.sf2_), m)
            out[own] = y[own] - _kernel(x[own], c, self.length_, self.sf2_) @ alpha
        return out
