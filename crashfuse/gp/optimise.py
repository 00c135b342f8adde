"""Maximum-likelihood hyperparameters of kriging: L-BFGS-B restarts, bounds, and the theta bound chosen by grouped CV.

The search is over ``eta = [log theta_1..d, log nugget]`` with the analytic gradient of
:func:`crashfuse.gp.likelihood.concentrated_log_likelihood`, from a fixed start (theta = 1, nugget = 1e-3) and
seeded log-uniform restarts. With groups, the upper bound on theta is chosen among candidates by the grouped
leave-one-out log density (:func:`choose_theta_bound`): the likelihood alone lets a few groups (tests) each
become their own function, and held-out groups then fall back on the trend. Pure functions on standardised inputs
``Z`` (n, d), normalised outputs ``u`` (n,) and the trend design ``H`` (n, p).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from crashfuse.gp.grouped import grouped_cv_log_density
from crashfuse.gp.likelihood import FAILED, negative_log_likelihood

__all__ = ["log_bounds", "maximise_likelihood", "warm_maximise", "choose_theta_bound"]


def log_bounds(d, theta_bounds, theta_max, nugget_bounds):
    """Bounds on ``[log theta_1..d, log nugget]``.

    Parameters
    ----------
    d : int
        Number of inputs.
    theta_bounds : (float or sequence of d floats, float)
        Only the lower bound (one for every input, or one per input) is used; ``theta_max`` is the upper one.
    theta_max : float
    nugget_bounds : (float, float)

    Returns
    -------
    ndarray, shape (d + 1, 2)
    """
    lo = np.r_[np.full(d, np.log(theta_bounds[0])), np.log(nugget_bounds[0])]
    hi = np.r_[np.full(d, np.log(theta_max)), np.log(nugget_bounds[1])]
    return np.column_stack([lo, hi])


# The GPs' own lower bound on the nugget (KrigingGP and GMMGPBias defaults); a floor above it is also searched from it.
FREE_NUGGET = 1e-8


def _fixed_start(bounds):
    """theta = 1, nugget = 1e-3, clipped into ``bounds``."""
    return np.clip(np.r_[np.zeros(len(bounds) - 1), np.log(1e-3)], bounds[:, 0], bounds[:, 1])


def _lbfgs(x0, Z, u, H, bounds):
    return minimize(negative_log_likelihood, x0, args=(Z, u, H), jac=True, method="L-BFGS-B", bounds=bounds)


def maximise_likelihood(Z, u, H, bounds, rng, n_restarts):
    """Best ``eta`` over the fixed start and ``n_restarts`` random ones.

    Under a nugget floor above ``FREE_NUGGET`` also from the fixed start's optimum without the floor,
    clipped to it: where the data want less noise than the floor allows, the floored optimum lies near
    that one, on the floor, and the fixed start (clipped to the floor) can fall into another basin
    (docs/decisions.md, section 76).

    Parameters
    ----------
    Z, u, H
        Hyperparameter-fit data.
    bounds : ndarray, shape (d + 1, 2)
    rng : numpy.random.RandomState
        Draws the restarts, uniformly within ``bounds``.
    n_restarts : int

    Returns
    -------
    eta : ndarray, shape (d + 1,)
    ll : float
        Concentrated log-likelihood at ``eta``.

    Raises
    ------
    ValueError
        The likelihood could not be evaluated at any start.
    """
    starts = [_fixed_start(bounds)] + [rng.uniform(bounds[:, 0], bounds[:, 1]) for _ in range(n_restarts)]
    if bounds[-1, 0] > np.log(FREE_NUGGET):
        free = bounds.copy()
        free[-1, 0] = np.log(FREE_NUGGET)
        starts.append(np.clip(_lbfgs(_fixed_start(free), Z, u, H, free).x, bounds[:, 0], bounds[:, 1]))
    best_eta, best_f = None, np.inf
    for x0 in starts:
        res = _lbfgs(x0, Z, u, H, bounds)
        if res.fun < min(best_f, FAILED):
            best_eta, best_f = res.x, res.fun
    if best_eta is None:
        raise ValueError("KrigingGP: the likelihood could not be evaluated at any start "
                         "(duplicate inputs with conflicting outputs and a zero nugget?)")
    return best_eta, -best_f


def warm_maximise(eta, Z, u, H, bounds):
    """The optimum under smaller ``bounds``, from the optimum ``eta`` under larger ones.

    ``eta`` itself when it lies inside ``bounds`` (it is then optimal there too); else the better of the
    searches from ``eta`` clipped and from the fixed start.

    Returns
    -------
    eta : ndarray, shape (d + 1,)
    ll : float
    """
    if np.all(eta <= bounds[:, 1]):
        return eta, -negative_log_likelihood(eta, Z, u, H)[0]
    fits = [_lbfgs(x0, Z, u, H, bounds) for x0 in (np.clip(eta, bounds[:, 0], bounds[:, 1]), _fixed_start(bounds))]
    res = min(fits, key=lambda r: r.fun)
    return res.x, -res.fun


def choose_theta_bound(Z, u, H, groups, rng, *, theta_bounds, nugget_bounds, candidates, n_restarts):
    """ML hyperparameters under the theta bound with the best grouped CV log density.

    Parameters
    ----------
    Z, u, H
        Hyperparameter-fit data.
    groups : ndarray, shape (n,) or None
        Group of each row. Without groups, fewer than three, or no ``candidates``, the bound is
        ``theta_bounds[1]``.
    rng : numpy.random.RandomState
    theta_bounds, nugget_bounds : (float, float)
    candidates : sequence of float or None
        Upper bounds on theta to choose from.
    n_restarts : int

    Returns
    -------
    eta : ndarray, shape (d + 1,)
    theta_max : float
        The chosen bound.
    ll : float
        Concentrated log-likelihood at ``eta``.
    cv_scores : dict of float to float
        Grouped CV log density per candidate (empty without a choice).
    """
    d = Z.shape[1]
    if not candidates or groups is None or len(np.unique(groups)) < 3:
        theta_max = float(theta_bounds[1])
        eta, ll = maximise_likelihood(Z, u, H, log_bounds(d, theta_bounds, theta_max, nugget_bounds), rng, n_restarts)
        return eta, theta_max, ll, {}
    best, eta, cv_scores = None, None, {}
    # Largest bound first with every restart; a smaller bound reuses that optimum when it lies
    # inside the bound (it is then optimal there too), else starts from it clipped.
    for hi in sorted((float(c) for c in candidates), reverse=True):
        bounds = log_bounds(d, theta_bounds, hi, nugget_bounds)
        eta, ll = maximise_likelihood(Z, u, H, bounds, rng, n_restarts) if eta is None else warm_maximise(eta, Z, u, H, bounds)
        score = grouped_cv_log_density(eta, Z, u, H, groups)
        cv_scores[hi] = score
        if best is None or score > best[0]:
            best = (score, hi, eta, ll)
    _, theta_max, eta, ll = best
    return eta, theta_max, ll, cv_scores
