"""The kriging model's building blocks on standardised inputs: the Gaussian correlation, the trend basis, and the
Cholesky factor and inverse of the correlation matrix with its nugget (paper Eq. 16-17).

Pure functions on arrays. ``Z`` are inputs standardised to zero mean and unit variance per column, shape (n, d);
``theta`` (d,) are the correlation parameters on them. The routines marked bit-identical give exactly the bits of
the plain NumPy/SciPy expressions they stand for: the likelihood optimiser's path depends on every bit.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cholesky, lapack
from scipy.spatial.distance import cdist, pdist, squareform

__all__ = ["TRENDS", "correlation", "self_correlation", "factor_with_nugget", "inverse_from_factor",
           "independent_columns", "design"]

TRENDS = ("zero", "constant", "linear")


def correlation(A, B, theta):
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


def self_correlation(A, theta):
    """``correlation(A, A, theta)``, bit for bit, with one exponential per pair instead of two.

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


def factor_with_nugget(R, nugget):
    """Lower Cholesky factor of ``R + nugget I`` for an exactly symmetric ``R``, computed in ``R``'s memory.

    ``R.T`` is Fortran-ordered, so LAPACK factorises it in place instead of copying it first; being
    symmetric it is the same matrix, and the factor is the one
    ``cholesky(R + nugget * np.eye(n), lower=True)`` returns, bit for bit.

    Parameters
    ----------
    R : ndarray, shape (n, n)
        Correlation matrix, overwritten.
    nugget : float
        Noise-to-signal variance ratio added to the diagonal.

    Returns
    -------
    ndarray, shape (n, n)

    Raises
    ------
    numpy.linalg.LinAlgError
        ``R + nugget I`` is not numerically positive definite.
    """
    R.flat[::len(R) + 1] += nugget
    return cholesky(R.T, lower=True, overwrite_a=True, check_finite=False)


def inverse_from_factor(L):
    """``K^-1`` from the lower Cholesky factor ``L`` of ``K`` (LAPACK ``dpotri``), overwriting ``L``.

    ``dpotri`` fills the lower triangle; the upper one is zero (``cholesky`` cleans it), so adding
    the transpose and halving the doubled diagonal mirrors it exactly (sums with 0 and the halving
    are exact), in one pass instead of two ``tril`` copies.

    Returns
    -------
    Kinv : ndarray, shape (n, n)
        C-ordered (the transposed view of LAPACK's Fortran-ordered result: the same symmetric
        matrix), so products with it are summed in the same order as with a plain inverse.
    info : int
        LAPACK's status; non-zero means ``K`` is singular.
    """
    Kinv, info = lapack.dpotri(L, lower=1, overwrite_c=1)
    Kinv += Kinv.T
    Kinv.flat[::len(Kinv) + 1] *= 0.5
    return Kinv.T, info


def independent_columns(Z, tol=1e-8):
    """Indices of a maximal linearly independent set of ``[1, Z]`` columns (greedy, in order).

    Parameters
    ----------
    Z : ndarray, shape (n, d)
        Standardised inputs.
    tol : float
        Relative singular-value threshold below which a column counts as dependent.

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


def design(Z, trend, columns):
    """Trend design matrix ``H`` on standardised inputs (paper Eq. 16's ``h(x)``).

    Parameters
    ----------
    Z : ndarray, shape (n, d)
    trend : {'zero', 'constant', 'linear'}
    columns : list of int
        Columns of ``Z`` in a linear trend (empty for the other trends).

    Returns
    -------
    ndarray, shape (n, p)
        ``p = 0`` for no trend, else the intercept column followed by ``Z[:, columns]``.
    """
    if trend == "zero":
        return np.empty((len(Z), 0))
    return np.column_stack([np.ones(len(Z)), Z[:, columns]])
