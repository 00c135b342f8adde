"""Held-out evidence for one candidate effect: the folds it acts on, a paired sign test over them,
and its practical size.

An effect may act on a subset of the tests only (an engine that reaches the barrier in the faster
tests, a rate hardening that matters where the crush is fast). On the other folds the candidate's
held-out prediction equals the reference's: those folds are ties, evidence neither way. So a
candidate is judged on the folds where it **changes the held-out prediction materially** - by more
than :data:`MOVE` of the held-out test's rms deceleration over its record, more than fitting an
effect to a control's noise and CAE scatter moves it (docs/decisions.md, section 21):

- statistically: among those affected folds (at least :data:`MIN_AFFECTED`) its held-out error must
  be lower often enough that a one-sided sign test rejects "better or worse with equal chance" at
  :data:`ALPHA`;
- practically: the held-out mean squared error must fall by at least ``threshold`` (relative) both
  over every fold and over the affected folds.

Pure functions on per-fold arrays; the fits and rollouts are the caller's.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

MOVE = 0.05  # a fold is affected when its held-out prediction moves by more than this share of the test's rms
ALPHA = 0.10  # one-sided sign test over the affected folds
MIN_AFFECTED = 4  # fewer affected folds cannot reach ALPHA: four wins of four give p = 1/16


@dataclasses.dataclass(frozen=True)
class Evidence:
    """The held-out evidence of one candidate against the effects chosen before it.

    Attributes
    ----------
    affected : ndarray of bool, shape (n_folds,)
        Folds whose held-out prediction the candidate changes by more than ``move`` of the test's rms.
    wins, losses : int
        Affected folds whose held-out error falls / rises.
    p_value : float
        One-sided sign test of ``wins`` among ``wins + losses`` (1.0 without affected folds).
    ratio : float
        Held-out mean squared error against the reference's, over every fold.
    affected_ratio : float
        The same over the affected folds (1.0 without any).
    accepted : bool
        Every criterion met.
    reason : str
        The first criterion that failed ('' when accepted).
    """

    affected: np.ndarray
    wins: int
    losses: int
    p_value: float
    ratio: float
    affected_ratio: float
    accepted: bool
    reason: str


def sign_test(wins: int, n: int) -> float:
    """One-sided sign test: P(at least ``wins`` successes of ``n`` fair coin flips); 1.0 for ``n`` = 0."""
    if n == 0:
        return 1.0
    return sum(math.comb(n, k) for k in range(wins, n + 1)) / 2.0 ** n


def affected_folds(change_rms, test_rms, move: float = MOVE) -> np.ndarray:
    """Folds whose held-out prediction moves by more than ``move`` times the held-out test's rms.

    Parameters
    ----------
    change_rms : array_like, shape (n_folds,)
        Rms over the record of the candidate's minus the reference's held-out prediction, m/s^2.
    test_rms : array_like, shape (n_folds,)
        Rms of each held-out test's measured deceleration over its record, m/s^2.
    move : float
    """
    return np.asarray(change_rms, float) > move * np.asarray(test_rms, float)


def judge(reference_mse, candidate_mse, change_rms, test_rms, threshold: float, move: float = MOVE,
          alpha: float = ALPHA, min_affected: int = MIN_AFFECTED) -> Evidence:
    """Judge one candidate on its held-out errors and how far it moves each held-out prediction.

    Parameters
    ----------
    reference_mse, candidate_mse : array_like, shape (n_folds,)
        Held-out mean squared error per fold of the effects chosen so far and of those plus the
        candidate, (m/s^2)^2.
    change_rms, test_rms : array_like, shape (n_folds,)
        See :func:`affected_folds`.
    threshold : float
        Minimum relative drop of the held-out mean squared error (over every fold and over the
        affected folds).
    move, alpha, min_affected : float, float, int
        See :data:`MOVE`, :data:`ALPHA`, :data:`MIN_AFFECTED`.

    Returns
    -------
    Evidence
    """
    ref, cand = np.asarray(reference_mse, float), np.asarray(candidate_mse, float)
    affected = affected_folds(change_rms, test_rms, move)
    wins = int((cand < ref)[affected].sum())
    losses = int((cand > ref)[affected].sum())
    p = sign_test(wins, wins + losses)
    ratio = float(cand.sum() / ref.sum())
    aff_ratio = float(cand[affected].sum() / ref[affected].sum()) if affected.any() else 1.0
    reason = _first_failure(int(affected.sum()), p, ratio, aff_ratio, threshold, alpha, min_affected)
    return Evidence(affected, wins, losses, p, ratio, aff_ratio, reason == "", reason)


def _first_failure(n_affected, p, ratio, aff_ratio, threshold, alpha, min_affected) -> str:
    if n_affected < min_affected:
        return f"acts on {n_affected} folds, fewer than {min_affected}"
    if p > alpha:
        return f"sign test p = {p:.3f} > {alpha}"
    if ratio > 1.0 - threshold:
        return f"held-out MSE ratio {ratio:.3f} above {1.0 - threshold:.3f}"
    if aff_ratio > 1.0 - threshold:
        return f"held-out MSE ratio on the affected folds {aff_ratio:.3f} above {1.0 - threshold:.3f}"
    return ""
