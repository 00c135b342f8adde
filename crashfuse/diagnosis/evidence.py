"""Held-out evidence for one candidate effect: the folds it acts on, a paired sign test over them,
and its practical size.

An effect may act on a subset of the tests only (an engine that reaches the barrier in the faster
tests, a rate hardening that matters where the crush is fast). On the other folds the candidate's
held-out prediction equals the reference's: those folds are ties, evidence neither way. So a
candidate is judged on the folds where it **changes the held-out prediction materially** - by more
than :data:`MOVE` of the held-out test's rms deceleration over its record, more than fitting an
effect to a control's noise and CAE scatter moves it (docs/decisions.md, section 21):

- statistically: among those affected folds its held-out error must be lower often enough that a
  one-sided sign test rejects "better or worse with equal chance" at :data:`ALPHA` (at least
  :data:`MIN_AFFECTED` folds), or by enough that a one-sided sign-flip permutation test of the
  folds' held-out rms error changes does (large gains on several folds against small losses on
  others: an effect of two withheld that its partner masks on some folds) - or, on as few as
  :data:`MIN_MATERIAL` folds, it must be better on every one by more than the test-to-test scatter (the held-out rms
  error a typical test keeps whichever model predicts it): a fit to noise does not predict a test
  better by more than what is left on it;
- practically: the held-out mean squared error must fall by at least ``threshold`` (relative) both
  over every fold and over the affected folds.

An affected fold whose held-out test is the only affected one of its powertrain label is not
counted for a law with parameters per label: that fold fits them from no test the effect acts on.

Pure functions on per-fold arrays; the fits and rollouts are the caller's.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from crashfuse.units import G0

MOVE = 0.05  # a fold is affected when its held-out prediction moves by more than this share of the test's rms
# One-sided sign test over the affected folds: 1/8 lets 8 of 11 pass (p = 0.113), the old rule's
# two thirds of 11 folds, so an effect acting on every test meets no stricter a count than before.
ALPHA = 0.125
MIN_AFFECTED = 4  # the sign test needs four folds (three of three would reach ALPHA by chance 1 in 8)
MIN_MATERIAL = 3  # the fewest affected folds, all better by more than the scatter, that are evidence
EXACT_FLIPS = 16  # folds up to which the permutation test enumerates every sign flip (beyond: a seeded sample)


@dataclasses.dataclass(frozen=True)
class Evidence:
    """The held-out evidence of one candidate against the effects chosen before it.

    Attributes
    ----------
    affected : ndarray of bool, shape (n_folds,)
        Folds whose held-out prediction the candidate changes by more than ``move`` of the test's rms.
    sole : ndarray of bool, shape (n_folds,)
        Affected folds not counted: the only affected test of its group (:func:`sole_witnesses`).
    wins, losses : int
        Counted affected folds whose held-out error falls / rises.
    p_value : float
        One-sided sign test of ``wins`` among ``wins + losses`` (1.0 without affected folds).
    permutation_p : float
        One-sided sign-flip permutation test of the counted folds' held-out rms error falls
        (:func:`permutation_test`; 1.0 without affected folds).
    scatter : float
        Test-to-test scatter, m/s^2: the square root of the median over folds of the smaller of
        the two held-out mean squared errors.
    material : ndarray of bool, shape (n_folds,)
        Counted folds whose held-out rms error falls by more than ``scatter``.
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
    sole: np.ndarray
    wins: int
    losses: int
    p_value: float
    permutation_p: float
    scatter: float
    material: np.ndarray
    ratio: float
    affected_ratio: float
    accepted: bool
    reason: str


def sign_test(wins: int, n: int) -> float:
    """One-sided sign test: P(at least ``wins`` successes of ``n`` fair coin flips); 1.0 for ``n`` = 0."""
    if n == 0:
        return 1.0
    return sum(math.comb(n, k) for k in range(wins, n + 1)) / 2.0 ** n


def permutation_test(gains) -> float:
    """One-sided sign-flip permutation test that paired ``gains`` (reference minus candidate, per fold)
    are positive: the share of sign assignments whose sum is at least the observed one (1.0 for none).

    Exact up to :data:`EXACT_FLIPS` folds; beyond, over 2^16 sign vectors drawn with a fixed seed
    and the observed one (so never 0).
    """
    gains = np.asarray(gains, float)
    if gains.size == 0:
        return 1.0
    if gains.size <= EXACT_FLIPS:
        signs = 1 - 2 * ((np.arange(2 ** gains.size)[:, None] >> np.arange(gains.size)) & 1)
    else:
        drawn = np.random.default_rng(0).choice((-1, 1), size=(2 ** EXACT_FLIPS, gains.size))
        signs = np.vstack([np.sign(gains) + (gains == 0), drawn])
    sums = signs @ np.abs(gains)
    return float(np.mean(sums >= gains.sum() - 1e-12 * np.abs(gains).sum()))


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


def sole_witnesses(affected, groups) -> np.ndarray:
    """Affected folds whose held-out test is the only affected test of its group.

    A law with parameters per group (a powertrain mass and gap per label) fits them, in such a fold,
    from no test the effect acts on: its held-out prediction tests the starting point, not the effect.

    Parameters
    ----------
    affected : ndarray of bool, shape (n_folds,)
    groups : array_like of int, shape (n_folds,), or None
        Group of each fold's held-out test; None for a law without per-group parameters.
    """
    affected = np.asarray(affected, bool)
    if groups is None:
        return np.zeros_like(affected)
    groups = np.asarray(groups)
    peers = np.array([(affected & (groups == g)).sum() for g in groups])
    return affected & (peers == 1)


def judge(reference_mse, candidate_mse, change_rms, test_rms, threshold: float, move: float = MOVE,
          alpha: float = ALPHA, min_affected: int = MIN_AFFECTED, groups=None) -> Evidence:
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
    groups : array_like of int, optional
        Group of each held-out test for a law with per-group parameters: an affected fold that is
        the only one of its group is not counted (:func:`sole_witnesses`).

    Returns
    -------
    Evidence
    """
    ref, cand = np.asarray(reference_mse, float), np.asarray(candidate_mse, float)
    affected = affected_folds(change_rms, test_rms, move)
    sole = sole_witnesses(affected, groups)
    counted = affected & ~sole
    wins = int((cand < ref)[counted].sum())
    losses = int((cand > ref)[counted].sum())
    p = sign_test(wins, wins + losses)
    gain = np.sqrt(ref) - np.sqrt(cand)
    p_perm = permutation_test(gain[counted])
    scatter = float(np.sqrt(np.median(np.minimum(ref, cand))))
    material = counted & (gain > scatter)
    ratio = float(cand.sum() / ref.sum())
    aff_ratio = float(cand[affected].sum() / ref[affected].sum()) if affected.any() else 1.0
    n = int(counted.sum())
    if n >= min_affected and min(p, p_perm) <= alpha or n >= MIN_MATERIAL and material.sum() == n:
        reason = _too_small(ratio, aff_ratio, threshold)
    else:
        reason = _no_evidence(n, min(p, p_perm), int(material.sum()), scatter, alpha, min_affected)
    return Evidence(affected, sole, wins, losses, p, p_perm, scatter, material, ratio, aff_ratio, reason == "", reason)


def _no_evidence(n: int, p: float, n_material: int, scatter: float, alpha: float, min_affected: int) -> str:
    fewest = min(MIN_MATERIAL, min_affected)
    if n < fewest:
        return f"acts on {n} counted folds, fewer than {fewest}"
    beyond = f"better by more than the scatter {scatter / G0:.2f} g on {n_material} of {n}"
    if n < min_affected:
        return f"acts on {n} counted folds (fewer than {min_affected} for the sign test), {beyond}"
    return f"sign and permutation tests p >= {p:.3f} > {alpha}, {beyond}"


def _too_small(ratio: float, aff_ratio: float, threshold: float) -> str:
    if ratio > 1.0 - threshold:
        return f"held-out MSE ratio {ratio:.3f} above {1.0 - threshold:.3f}"
    if aff_ratio > 1.0 - threshold:
        return f"held-out MSE ratio on the affected folds {aff_ratio:.3f} above {1.0 - threshold:.3f}"
    return ""
