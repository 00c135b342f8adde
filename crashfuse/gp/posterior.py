"""Conditioning kriging on data and its predictive equations (paper Eq. 19-20, with the trend-estimation term).

Pure functions on standardised inputs, normalised outputs and the trend design of
:func:`crashfuse.gp.kernels.design`. :func:`condition` factorises the correlation matrix of the conditioning set
and fits the GLS trend; :func:`predictive_mean` and :func:`variance_parts` then give, at new points, the mean and
the two pieces of the variance ``sigma^2 [1 - r^T K^-1 r + u^T (H^T K^-1 H)^-1 u]``.
"""

from __future__ import annotations

from scipy.linalg import cholesky, solve_triangular

from crashfuse.gp.kernels import correlation, factor_with_nugget, self_correlation
from crashfuse.gp.likelihood import gls

__all__ = ["condition", "predictive_mean", "variance_parts", "latent_variance"]


def condition(Z, u, H, theta, nugget):
    """Factorise ``K`` on the conditioning set and fit the GLS trend.

    Parameters
    ----------
    Z : ndarray, shape (n, d)
        Standardised conditioning inputs.
    u : ndarray, shape (n,)
        Normalised outputs.
    H : ndarray, shape (n, p)
        Trend design matrix at ``Z``.
    theta : ndarray, shape (d,)
    nugget : float

    Returns
    -------
    L : ndarray, shape (n, n)
        Lower Cholesky factor of ``K = R + nugget I``.
    beta : ndarray, shape (p,)
        GLS trend coefficients (normalised units).
    alpha : ndarray, shape (n,)
        ``K^-1 (u - H beta)``.
    sigma2 : float
        Process variance (normalised units).
    Ht : ndarray, shape (n, p)
        ``L^-1 H``.
    LM : ndarray, shape (p, p)
        Lower Cholesky factor of ``H^T K^-1 H``.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``K`` or ``H^T K^-1 H`` is not numerically positive definite.
    """
    L = factor_with_nugget(self_correlation(Z, theta), nugget)
    beta, alpha, sigma2, Ht = gls(L, H, u)
    LM = cholesky(Ht.T @ Ht, lower=True, check_finite=False)
    return L, beta, alpha, sigma2, Ht, LM


def predictive_mean(Z, Zs, Hs, theta, beta, alpha):
    """Predictive mean (normalised units) at standardised points ``Zs`` and their correlations with ``Z``.

    Parameters
    ----------
    Z : ndarray, shape (n, d)
        Conditioning inputs.
    Zs : ndarray, shape (m, d)
    Hs : ndarray, shape (m, p)
        Trend design matrix at ``Zs``.
    theta : ndarray, shape (d,)
    beta, alpha
        From :func:`condition`.

    Returns
    -------
    mean : ndarray, shape (m,)
    r : ndarray, shape (n, m)
    """
    r = correlation(Z, Zs, theta)
    return Hs @ beta + r.T @ alpha, r


def variance_parts(r, Hs, L, Ht, LM):
    """The two pieces of the predictive variance at points with correlations ``r`` to the conditioning set.

    Parameters
    ----------
    r : ndarray, shape (n, m)
        From :func:`predictive_mean`.
    Hs : ndarray, shape (m, p)
    L, Ht, LM
        From :func:`condition`.

    Returns
    -------
    V : ndarray, shape (n, m)
        ``L^-1 r(x)``.
    W : ndarray, shape (p, m)
        ``L_M^-1 u(x)``, ``u = h(x) - H^T K^-1 r(x)``, ``L_M L_M^T = H^T K^-1 H``.
    """
    V = solve_triangular(L, r, lower=True, check_finite=False)
    U = Hs.T - Ht.T @ V
    W = solve_triangular(LM, U, lower=True, check_finite=False)
    return V, W


def latent_variance(V, W):
    """``1 - r^T K^-1 r + u^T (H^T K^-1 H)^-1 u`` per point, in units of ``sigma^2``, shape (m,)."""
    return 1.0 - (V**2).sum(axis=0) + (W**2).sum(axis=0)
