"""Joint draws from a Gaussian predictive distribution, with the smallest diagonal jitter that factorises it.

Smooth GPs on dense grids have numerically singular predictive covariances; :func:`jittered_cholesky` adds
``j * mean(diag(cov))`` to the diagonal, ``j`` trying 1e-12, 1e-11, ..., 1e-4 in turn, so the added standard
deviation is at most 1 % of the average predictive one.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cholesky
from sklearn.utils import check_random_state

__all__ = ["JITTERS", "jittered_cholesky", "joint_draws"]

JITTERS = 10.0 ** np.arange(-12, -3)  # relative jitters tried, in order


def jittered_cholesky(cov):
    """Lower Cholesky factor of ``cov + j mean(diag) I`` with the smallest working jitter.

    Parameters
    ----------
    cov : ndarray, shape (m, m)

    Returns
    -------
    ndarray, shape (m, m)

    Raises
    ------
    numpy.linalg.LinAlgError
        Not positive definite even with the largest jitter.
    """
    if cov.size == 0:
        return cov
    scale = max(float(np.mean(np.diag(cov))), np.finfo(float).tiny)
    for j in JITTERS:
        try:
            return cholesky(cov + j * scale * np.eye(len(cov)), lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            continue
    raise np.linalg.LinAlgError("predictive covariance is not positive semi-definite even with "
                                f"a jitter of {JITTERS[-1]:g} x its mean variance")


def joint_draws(mean, cov, n_samples, random_state):
    """Draws from ``N(mean, cov)``, shape (n_samples, m).

    Parameters
    ----------
    mean : ndarray, shape (m,)
    cov : ndarray, shape (m, m)
    n_samples : int
    random_state : int, RandomState or None

    Returns
    -------
    ndarray, shape (n_samples, m)
    """
    Lc = jittered_cholesky(cov)
    z = check_random_state(random_state).standard_normal((len(mean), n_samples))
    return (mean[:, None] + Lc @ z).T
