"""The concentrated likelihood of universal kriging and its analytic gradient (paper Eq. 18).

For fixed hyperparameters ``eta = [log theta_1..d, log nugget]`` the trend coefficients ``beta`` (GLS) and the
process variance ``sigma^2`` have closed forms, so the likelihood is maximised over ``eta`` alone. Pure functions
on standardised inputs ``Z`` (n, d), normalised outputs ``u`` (n,) and the trend design ``H`` (n, p) of
:func:`crashfuse.gp.kernels.design`.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular

from crashfuse.gp.kernels import factor_with_nugget, inverse_from_factor, self_correlation

__all__ = ["FAILED", "gls", "concentrated_log_likelihood", "negative_log_likelihood"]

FAILED = 1e300  # objective value where K is not numerically positive definite


def gls(L, H, u):
    """GLS trend given the Cholesky factor ``L`` of ``K``.

    Parameters
    ----------
    L : ndarray, shape (n, n)
        Lower Cholesky factor of ``K = R + nugget I``.
    H : ndarray, shape (n, p)
    u : ndarray, shape (n,)

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


def concentrated_log_likelihood(eta, Z, u, H, gradient=False):
    """Concentrated log-likelihood (beta GLS, sigma^2 = r^T K^-1 r / n) and gradient.

    Parameters
    ----------
    eta : ndarray, shape (d + 1,)
        ``[log theta_1..d, log nugget]``.
    Z : ndarray, shape (n, d)
        Standardised inputs.
    u : ndarray, shape (n,)
        (Normalised) outputs.
    H : ndarray, shape (n, p)
        Trend design matrix at ``Z``.
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
    R = self_correlation(Z, theta)
    try:
        L = factor_with_nugget(R.copy(), nugget)  # R is needed for the gradient
    except np.linalg.LinAlgError:
        return (-np.inf, np.zeros_like(eta)) if gradient else -np.inf
    alpha, sigma2 = gls(L, H, u)[1:3]
    ll = -0.5 * n * np.log(2 * np.pi * sigma2) - np.log(np.diag(L)).sum() - 0.5 * n
    if not gradient:
        return ll
    # d ll / d eta_j = 1/2 tr(W dK/d eta_j), W = alpha alpha^T / sigma^2 - K^-1; beta and
    # sigma^2 are stationary points of the likelihood, so their own derivatives drop out.
    # The n x n steps work in place (same operations, same bits): this runs ~1000 times a fit.
    Kinv, info = inverse_from_factor(L)
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


def negative_log_likelihood(eta, Z, u, H):
    """Negative concentrated log-likelihood and its gradient, the objective of the optimiser.

    Parameters
    ----------
    eta, Z, u, H
        As in :func:`concentrated_log_likelihood`.

    Returns
    -------
    f : float
        ``-ll``, or :data:`FAILED` where ``K`` is not numerically positive definite.
    grad : ndarray, shape (d + 1,)
        ``-d ll / d eta`` (zeros where the likelihood failed).
    """
    ll, grad = concentrated_log_likelihood(eta, Z, u, H, gradient=True)
    if not np.isfinite(ll):
        return FAILED, np.zeros_like(eta)
    return -ll, -grad
