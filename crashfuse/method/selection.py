"""The ``auto`` model: among fitted candidates, the one whose bias model best predicts its own training tests.

A candidate is a fit of one setting (input mode, K, effects) on the same training tests. Each
training test is left out of the candidate's bias model in closed form - every GP conditioned on
the other tests at its fitted hyperparameters (:meth:`GMMGPBias.held_out_residuals`,
:meth:`OnsetCorrectedBias.held_out_residuals`) - and its bias predicted; the score is the mean over
training tests of each test's mean squared error in m/s^2 (relative bias times its CAE scale), both
branches pooled. No refit: a candidate costs one ``O(n^3)`` solve per GP on at most
:data:`INNER_MAX_ROWS` rows per branch. What the closed form leaves out is in docs/bias-model.md
("The auto model"): the mixture, the hyperparameters and the hybrid's effect laws are not refitted
without the test, which flatters every candidate a little and the flexible ones more.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from crashfuse.gp.subsets import stratified_subset
from crashfuse.io.campaign import Campaign
from crashfuse.method.hybrid import MIN_GAIN
from crashfuse.method.model import FittedModel, training_data
from crashfuse.method.projection import BRANCHES

__all__ = ["INNER_MAX_ROWS", "inner_error", "choose"]

INNER_MAX_ROWS = 1500  # rows per branch (evenly spaced within each test) the held-out residuals are solved on


def inner_error(model: FittedModel, campaign: Campaign) -> float:
    """Mean over the training tests of the held-out squared bias error, (m/s^2)^2; ``inf`` if it has none.

    Parameters
    ----------
    model : FittedModel
        A fit on ``campaign`` (its training tests, surrogate and effect laws are used as fitted).
    campaign : Campaign

    Returns
    -------
    float
        ``inf`` where a GP's rows come from a single test (that test cannot be left out: a cluster
        of one test) or a matrix is singular.
    """
    data = training_data(campaign, model.training_tests, model.config, model.surrogate, model.physics,
                         chain=model.chain)
    squares = {t: [] for t in model.training_tests}
    for b in BRANCHES:
        est, d = model.bias_.get(b), data.branch(b)
        if est is None or d.y.size == 0:
            continue
        rows = stratified_subset(d.groups, INNER_MAX_ROWS)
        groups = d.groups[rows]
        if len(set(groups)) < 2:
            return float("inf")
        e = est.held_out_residuals(d.X[rows], d.y[rows], groups)
        if e is None:
            return float("inf")
        for t in set(groups):
            squares[t].append((e[groups == t] * d.scale[rows][groups == t]) ** 2)
    per_test = [np.mean(np.concatenate(s)) for s in squares.values() if s]
    return float(np.mean(per_test)) if per_test else float("inf")


@dataclasses.dataclass(frozen=True)
class Choice:
    """What :func:`choose` picked.

    Attributes
    ----------
    index : int
        Position of the chosen candidate.
    scores : list of float
        Every candidate's :func:`inner_error`, (m/s^2)^2.
    """

    index: int
    scores: list


def choose(scores, min_gain: float = MIN_GAIN) -> Choice:
    """The simplest candidate no later one improves on by ``min_gain``; candidates listed simplest first.

    Walking the list, a candidate replaces the current choice when its inner error is below
    ``(1 - min_gain)`` times the current one's. The closed-form error flatters flexible candidates
    (the mixture and hyperparameters saw the left-out test), so a small gain is not evidence.

    Parameters
    ----------
    scores : sequence of float
        :func:`inner_error` per candidate, simplest first (e.g. K ascending).
    min_gain : float
        Fraction of the current choice's error a more complex candidate must remove.

    Returns
    -------
    Choice

    Raises
    ------
    ValueError
        No candidate with a finite score.
    """
    scores = [float(s) for s in scores]
    finite = [i for i, s in enumerate(scores) if np.isfinite(s)]
    if not finite:
        raise ValueError(f"expected at least one candidate with a finite inner error, got {scores}")
    best = finite[0]
    for i in finite[1:]:
        if scores[i] < (1.0 - min_gain) * scores[best]:
            best = i
    return Choice(best, scores)
