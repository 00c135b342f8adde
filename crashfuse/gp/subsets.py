"""Which training rows enter kriging's hyperparameter search and which it conditions on.

The likelihood costs ``O(n^3)`` per evaluation, so the search runs on a subset: a seeded random one
(:func:`random_subset`) or, with groups (tests), a deterministic one evenly spaced within each group
(:func:`stratified_subset`). The conditioning set contains it (:func:`condition_subset`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["random_subset", "stratified_subset", "condition_subset"]


def random_subset(n, limit, rng):
    """Sorted seeded random subset of ``range(n)`` of size ``min(n, limit)``.

    Parameters
    ----------
    n : int
    limit : int or None
        None: every row.
    rng : numpy.random.RandomState

    Returns
    -------
    ndarray of int
    """
    if limit is None or n <= limit:
        return np.arange(n)
    return np.sort(rng.choice(n, size=int(limit), replace=False))


def stratified_subset(groups, limit):
    """Deterministic subset: about ``limit`` rows, evenly spaced within each group, sorted.

    Parameters
    ----------
    groups : ndarray, shape (n,)
    limit : int or None

    Returns
    -------
    ndarray of int
    """
    n = len(groups)
    if limit is None or n <= limit:
        return np.arange(n)
    keep = []
    for grp in np.unique(groups):
        idx = np.flatnonzero(groups == grp)
        m = max(1, int(round(limit * len(idx) / n)))
        keep.append(idx[np.unique(np.linspace(0, len(idx) - 1, m).round().astype(int))])
    return np.sort(np.concatenate(keep))


def condition_subset(n, i_fit, limit, rng, groups=None):
    """Conditioning set: all rows, or the fit subset ``i_fit`` topped up to about ``limit``.

    Topped up evenly within each group when ``groups`` are given (:func:`stratified_subset`: every
    test keeps its share along its pulse), else at random.

    Parameters
    ----------
    n : int
    i_fit : ndarray of int
        The hyperparameter-fit subset.
    limit : int or None
    rng : numpy.random.RandomState
    groups : ndarray, shape (n,), optional

    Returns
    -------
    ndarray of int, sorted
    """
    if limit is None or n <= limit:
        return np.arange(n)
    if groups is not None and len(i_fit) < limit:
        rest = np.setdiff1d(np.arange(n), i_fit)
        return np.union1d(i_fit, rest[stratified_subset(groups[rest], int(limit) - len(i_fit))])
    if len(i_fit) >= limit:
        return np.sort(rng.choice(i_fit, size=int(limit), replace=False))
    rest = np.setdiff1d(np.arange(n), i_fit)
    extra = rng.choice(rest, size=int(limit) - len(i_fit), replace=False)
    return np.sort(np.concatenate([i_fit, extra]))
