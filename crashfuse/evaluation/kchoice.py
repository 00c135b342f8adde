"""The default-K rule of the method: inner leave-one-test-out log density on the training tests.

An evaluation, not part of the model: every K is refitted once per training test. The gap map's
K (:func:`crashfuse.diagnosis.gap.mixture_bic_k`) answers another question - how many clusters the
loading branch's bias inputs form, by the BIC of a mixture alone - and fits no GP.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from crashfuse.io.campaign import Campaign
from crashfuse.method.config import MethodConfig
from crashfuse.method.model import fit_model, holdout_tests, training_data
from crashfuse.method.projection import BRANCHES
from crashfuse.method.surrogate import CAESurrogate

SD_FLOOR = 1e-12  # predictive std floor, relative to max(1, largest |bias|): a zero std has no density


def choose_k(campaign: Campaign, config: MethodConfig, ks=(1, 2, 3), holdout=None,
             surrogate: CAESurrogate | None = None) -> tuple[int, dict]:
    """The K whose bias model best predicts each training test when refitted without it.

    For each K and each training test ``t`` (all but ``holdout``), the whole bias model (mixture
    and GPs, hyperparameters included) is refitted on the other training tests and scores the
    bias points of ``t``: the mean marginal normal log density per point (y units, predictive
    std of the selected or blended GP), both branches pooled. A held-out test is never used.

    Parameters
    ----------
    campaign : Campaign
    config : MethodConfig
        The fit's settings (input mode, seed, GP settings, e.g. a cheaper ``n_restarts`` for the
        many refits); its ``k`` is replaced by each of ``ks`` and ``estimate_scatter`` is off (the
        density uses the latent std, not the test-to-test scatter).
    ks : sequence of int
        Candidate K.
    holdout : str or sequence of str, optional
        Tests left out of everything (an outer fold).
    surrogate : CAESurrogate, optional
        Fitted once here (seeded with ``config.random_state``) if not given.

    Returns
    -------
    k : int
        The best K (the smallest among ties).
    scores : dict of int to float
        Mean log density per bias point for each K.
    """
    surrogate = surrogate or CAESurrogate(random_state=config.random_state).fit(campaign)
    outer = holdout_tests(campaign, holdout)
    train = [t for t in campaign.tests if t not in outer]
    data = training_data(campaign, train, config, surrogate)
    scores = {}
    for k in ks:
        refit = dataclasses.replace(config, k=k, estimate_scatter=False)
        logs = [_held_out_density(campaign, refit, [t, *outer], surrogate, data) for t in train]
        scores[int(k)] = float(np.mean(np.concatenate([x for per_test in logs for x in per_test])))
    return max(scores, key=lambda k: (scores[k], -k)), scores


def _held_out_density(campaign, config, holdout, surrogate, data) -> list:
    """:func:`_log_density` of ``holdout[0]`` under the model refitted without ``holdout``; with the hybrid's
    effects that test's bias is taken against the refit's own CAE + effects curve."""
    model = fit_model(campaign, config, holdout=holdout, surrogate=surrogate)
    if model.physics is not None:
        data = training_data(campaign, holdout[:1], config, surrogate, model.physics)
    return _log_density(model, data, holdout[0])


def _log_density(model, data, test_id: str) -> list:
    """Per branch, the normal log density of ``test_id``'s bias points under ``model`` (shape (n_b,))."""
    out = []
    for b in BRANCHES:
        d, est = data.branch(b), model.bias_.get(b)
        rows = d.groups == test_id
        if est is None or not rows.any():
            continue
        mu, sd = est.predict(d.X[rows], return_std=True)
        sd = np.maximum(sd, SD_FLOOR * max(1.0, float(np.abs(d.y).max())))
        out.append(-0.5 * (np.log(2 * np.pi * sd**2) + (d.y[rows] - mu) ** 2 / sd**2))
    return out
