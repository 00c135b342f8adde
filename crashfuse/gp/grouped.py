"""Leave-one-group-out (leave-one-test-out) kriging: held-out residuals, their log density, and the band calibration.

A group is the test a row came from. At fixed hyperparameters every group's held-out prediction has a closed form
(:func:`grouped_residuals`); it scores the candidate theta bounds (:func:`grouped_cv_log_density`) and calibrates
the 95 % band (:func:`variance_factor`). The test-to-test scatter needs the hyperparameters refitted without each
group (:func:`scatter_needs`). Pure functions on standardised inputs ``Z`` (n, d), normalised outputs ``u`` (n,),
the trend design ``H`` (n, p) and ``eta = [log theta_1..d, log nugget]``; docs/bias-model.md has the equations.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from crashfuse.gp.kernels import factor_with_nugget, inverse_from_factor, self_correlation
from crashfuse.gp.likelihood import gls, negative_log_likelihood
from crashfuse.gp.posterior import condition, latent_variance, predictive_mean, variance_parts
from crashfuse.gp.subsets import stratified_subset

__all__ = ["Z95", "grouped_residuals", "grouped_cv_log_density", "variance_factor", "scatter_needs"]

Z95 = 1.959963984540054  # two-sided 95 % normal quantile
# The scatter refits (one per left-out test) stop at a relative likelihood change of 1e-6, not
# scipy's 2e-9: they only size the test band. The main fit keeps scipy's default, where a
# looser tolerance can end in another local optimum (docs/decisions.md).
SCATTER_LBFGS = {"ftol": 1e-6}
# A test library of dozens of tests: at most this many refits, each leaving out one block of tests
# (the tests dealt in turn in sorted order), conditioned on at most this many rows of the others
# (evenly spaced within each test). Up to 12 tests of 200 rows: one test per refit, every row - the
# exact leave-one-test-out path (docs/bias-model.md, "Speed").
SCATTER_MAX_FOLDS = 12
SCATTER_MAX_ROWS = 2500


def grouped_residuals(eta, Z, u, H, groups):
    """Leave-one-group-out residuals and their predictive variances (normalised units).

    Each group is predicted from the others with ``theta``, the nugget and ``sigma^2`` fixed and the trend
    re-estimated: with ``P = K^-1 - K^-1 H (H^T K^-1 H)^-1 H^T K^-1`` the held-out residuals are
    ``P_II^-1 (P u)_I`` with covariance ``sigma^2 P_II^-1``.

    Parameters
    ----------
    eta : ndarray, shape (d + 1,)
    Z : ndarray, shape (n, d)
    u : ndarray, shape (n,)
    H : ndarray, shape (n, p)
    groups : ndarray, shape (n,)

    Returns
    -------
    (e, var) : two ndarrays of shape (n,), or None where ``K`` or a block is singular.
    """
    try:
        L = factor_with_nugget(self_correlation(Z, np.exp(eta[:-1])), np.exp(eta[-1]))
    except np.linalg.LinAlgError:
        return None
    _, alpha, sigma2, _ = gls(L, H, u)  # alpha = P u
    Kinv = inverse_from_factor(L)[0]
    KiH = Kinv @ H
    try:
        P = Kinv - KiH @ np.linalg.solve(H.T @ KiH, KiH.T)
    except np.linalg.LinAlgError:
        # trend columns collinear on these rows (a label's tests a subset left out): the projection onto
        # their span is still defined
        P = Kinv - KiH @ np.linalg.pinv(H.T @ KiH) @ KiH.T
    e, var = np.empty(len(u)), np.empty(len(u))
    for grp in np.unique(groups):
        idx = np.flatnonzero(groups == grp)
        try:
            C = np.linalg.inv(P[np.ix_(idx, idx)])
        except np.linalg.LinAlgError:
            return None
        e[idx], var[idx] = C @ alpha[idx], np.diag(C) * sigma2
    return None if np.any(var <= 0) else (e, var)


def grouped_cv_log_density(eta, Z, u, H, groups):
    """Mean leave-one-group-out marginal log density per point (higher is better); ``-inf`` if singular.

    Parameters
    ----------
    eta, Z, u, H, groups
        As in :func:`grouped_residuals`.

    Returns
    -------
    float
    """
    res = grouped_residuals(eta, Z, u, H, groups)
    if res is None:
        return -np.inf
    e, var = res
    return float(np.mean(-0.5 * (np.log(2 * np.pi * var) + e**2 / var)))


def variance_factor(eta, Z, u, H, groups):
    """``(q95 / 1.96)^2``, at least 1, of the standardised grouped residuals ``|e| / sd``.

    Multiplying ``sigma^2`` by it puts 95 % of the held-out errors inside the 95 % band. 1 with fewer than
    three groups or singular matrices.

    Parameters
    ----------
    eta, Z, u, H, groups
        As in :func:`grouped_residuals`.

    Returns
    -------
    float
    """
    if len(np.unique(groups)) < 3:
        return 1.0
    res = grouped_residuals(eta, Z, u, H, groups)
    if res is None:
        return 1.0
    return max(1.0, (float(np.quantile(np.abs(res[0]) / np.sqrt(res[1]), 0.95)) / Z95) ** 2)


def scatter_needs(eta, bounds, hyp, cond, max_folds=SCATTER_MAX_FOLDS, max_rows=SCATTER_MAX_ROWS):
    """Variance each conditioning point needs beyond the latent band when its group (test) is left out.

    For each group (past ``max_folds`` groups: each block of groups) the GP is refitted without it - likelihood re-optimised from ``eta`` under ``bounds``,
    variance factor recomputed, conditioned on the other groups' points - and predicts the group's points:
    ``need = (e / 1.96)^2 - latent variance`` (normalised units). The closed-form leave-one-group-out at fixed
    hyperparameters is far more optimistic (state folds of the paper campaign: scatter 0.00-0.06 vs 0.05-0.11
    relative; docs/decisions.md, section 6); a refit whose factorisation fails is left out.

    Parameters
    ----------
    eta : ndarray, shape (d + 1,)
        The fitted ``[log theta, log nugget]``, the refits' start.
    bounds : ndarray, shape (d + 1, 2)
        Bounds on ``eta`` (:func:`crashfuse.gp.optimise.log_bounds` at the chosen theta bound).
    hyp : tuple (Z, u, H, groups)
        The hyperparameter-fit subset: inputs (n_hyp, d), outputs (n_hyp,), design (n_hyp, p), groups (n_hyp,).
    cond : tuple (Z, u, H, groups)
        The conditioning set, likewise; its groups are the ones left out in turn.
    max_folds : int or None
        Refits at most (None: one per group). With more groups, group ``i`` of the sorted groups is
        left out in block ``i mod max_folds``: every group still gets held-out needs, from
        ``max_folds`` refits (one per test over dozens of tests grows like ``n^4``).
    max_rows : int or None
        Rows of the other groups each refit conditions on at most (None: all).

    Returns
    -------
    needs : ndarray, shape (n_needs,)
    rows : ndarray of int, shape (n_needs,)
        The conditioning row of each need.
    spreads : ndarray, shape (n_needs,)
        ``(e / 1.96)^2``: the whole variance each held-out point needs inside a 95 % band, latent and
        scatter together (the need with the latent variance added back).
    """
    Z_hyp, u_hyp, H_hyp, g_hyp = hyp
    Z, u, H, groups = cond
    needs, rows, spreads = [], [], []
    names = np.unique(groups)
    blocks = np.arange(len(names)) % (len(names) if max_folds is None else max_folds)
    for block in np.unique(blocks):
        left = names[blocks == block]
        keep, out = ~np.isin(g_hyp, left), np.isin(groups, left)
        e = minimize(negative_log_likelihood, eta, args=(Z_hyp[keep], u_hyp[keep], H_hyp[keep]), jac=True,
                     method="L-BFGS-B", bounds=bounds, options=SCATTER_LBFGS).x
        theta = np.exp(e[:-1])
        rest = np.flatnonzero(~out)
        rest = rest[stratified_subset(groups[rest], max_rows)]
        try:
            L, beta, alpha, sigma2, Ht, LM = condition(Z[rest], u[rest], H[rest], theta, float(np.exp(e[-1])))
        except np.linalg.LinAlgError:
            continue
        mean, r = predictive_mean(Z[rest], Z[out], H[out], theta, beta, alpha)
        V, W = variance_parts(r, H[out], L, Ht, LM)
        var = latent_variance(V, W) * sigma2 * variance_factor(e, Z_hyp[keep], u_hyp[keep], H_hyp[keep], g_hyp[keep])
        spreads.append((u[out] - mean) ** 2 / Z95**2)
        needs.append(spreads[-1] - var)
        rows.append(np.flatnonzero(out))
    if not needs:
        return np.empty(0), np.empty(0, int), np.empty(0)
    return np.concatenate(needs), np.concatenate(rows), np.concatenate(spreads)
