"""Sim-to-real gap diagnosis: where the gap lies, which effect causes it, how far it shrinks.

1. Where: :func:`crashfuse.diagnosis.gap.locate_gap` (the bias field and its significant regions).
2. Which: every effect of :mod:`crashfuse.catalogue` is a force law (:mod:`crashfuse.method.laws`) added to the CAE
   dynamics with a few physical parameters, fitted to the tests (:mod:`crashfuse.method.effect_fit`).
   Effects are compared on held-out evidence: the leave-one-test-out mean squared error of the
   CAE + effects rollout against the held-out test over its record. Greedy forward selection: each
   round fits every remaining effect together with those already chosen (all folds at once) and
   adds the best one only if its evidence holds (:mod:`crashfuse.diagnosis.evidence`: judged on the
   folds whose held-out prediction it changes materially, a sign test over them at ``alpha``, and a
   held-out error drop of at least ``threshold``) and none of its own parameters sits at its upper
   bound (the law would need more than is physical); otherwise the search stops - possibly with nothing
   chosen, when no effect explains the gap beyond what measurement noise and the CAE model's own
   scatter do.
3. How far it shrinks: leave-one-test-out ISO/TS 18571 scores for CAE alone, CAE + effects,
   CAE + effects + GMM-GPR residual (the method on a campaign whose CAE runs were replaced by the
   CAE + effects rollouts of each fold) and GMM-GPR alone.

Parameter uncertainty is the jackknife standard error over the leave-one-test-out fits.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

from crashfuse.catalogue import EFFECTS, F_REF, V_REF, check_effect
from crashfuse.gp.threads import cpu_kernels, one_blas_thread
from crashfuse.method.effect_fit import (DT, FoldFits, TestCase, better_of, fit_beyond, fit_folds, loto_sets,
                                         parameters_to_fit, predict, test_case)
from crashfuse.method.laws import damping_force, decay_length, headline
from crashfuse.errors import InputError
from crashfuse.diagnosis.evidence import ALPHA, MIN_MATERIAL, MOVE, Evidence, judge
from crashfuse.diagnosis.gap import locate_gap
from crashfuse.io.atomic import atomic_path, write_text
from crashfuse.io.campaign import Campaign
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.pulse import Pulse
from crashfuse.evaluation.iso_table import SCORES, WINDOWS, window_bounds
from crashfuse.method.config import MethodConfig
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.units import G0, MPH, MS

THRESHOLD = 0.10  # relative drop of the held-out mean squared error an effect must bring
HELD_INSIDE = 0.95  # a parameter fitted at its physical limit is refitted held at this fraction of it
RIGID_LINK_HZ = 100.0  # an extra mass whose link rings faster reads as rigid: a CFC 60 pulse (100 Hz) cannot tell


@dataclasses.dataclass
class Candidate:
    """One effect's evidence from the greedy round that last evaluated it."""

    effect: str
    round: int
    fits: FoldFits
    heldout_mse: np.ndarray  # (n_tests,) (m/s^2)^2, fold i predicting test i
    reference_mse: np.ndarray  # the same for the effects chosen before this round
    evidence: Evidence
    acts_on: list  # test ids of the affected folds
    chosen: bool = False
    partner: str | None = None  # the effect it was fitted and judged with when added as a pair
    not_told_from: list = dataclasses.field(default_factory=list)  # :func:`_not_told_apart`, when chosen

    @property
    def ratio(self) -> float:
        return self.evidence.ratio

    @property
    def wins(self) -> int:
        return self.evidence.wins

    @property
    def at_upper_bound(self) -> list:
        """Own parameters at an upper bound that is a physical limit, in the all-tests fit: the law
        needed more than is physical."""
        return _at_limit(self.fits, (self.effect,))


def _at_limit(fits: FoldFits, effects) -> list:
    """Parameters of ``effects`` whose all-tests fit in ``fits`` sits at an upper bound that is a
    physical limit (or at the bound a refit held them to, :func:`_within_limits`)."""
    return [p.name for p, v in zip(fits.params, fits.theta[-1])
            if p.name.split(".")[0] in effects and p.upper_is_limit and np.isclose(v, p.upper, rtol=1e-3)]


@dataclasses.dataclass
class Diagnosis:
    """The result of :func:`diagnose` (``to_json`` gives diagnosis.json)."""

    verdict: list
    candidates: dict
    regions: dict
    shrink: pd.DataFrame  # test_id, model, window_ms, overall, corridor, phase, magnitude, slope
    case: TestCase
    predictions: dict  # model -> (n_tests, n_t) decel m/s^2 on case.time (CAE, CAE+effects)
    settings: dict
    holdout: bool
    gap: object = None  # crashfuse.diagnosis.gap.GapMap (None for a single test)
    pairs: list = dataclasses.field(default_factory=list)  # the pairs of effects tried (:func:`_pair_round`)
    heldout_mse_ratio: float = 1.0  # held-out MSE of CAE + the verdict's effects over CAE's, every fold

    def to_json(self) -> dict:
        mean = self.shrink.groupby(["model", "window_ms"], sort=False)["overall"].mean()
        return {
            "schema": "crashfuse.diagnosis/1",
            "verdict": list(self.verdict),
            "holdout": self.holdout,
            "effects": [_candidate_json(c, self.case) for c in self.candidates.values()],
            "pairs": self.pairs,
            "regions": self.regions,
            "shrink": {m: {w: float(mean[(m, w)]) for w in WINDOWS if (m, w) in mean.index}
                       for m in self.shrink["model"].unique()},
            "shrink_per_test": self.shrink.to_dict(orient="records"),
            "settings": self.settings,
        }


@one_blas_thread  # the effect fits' normal equations: the same bits on any thread count
def diagnose(campaign: Campaign, effects=EFFECTS, threshold: float = THRESHOLD, alpha: float = ALPHA,
             move: float = MOVE, k: int = 1, inputs: str = "state", n_samples: int = 200, random_state: int = 0,
             surrogate: CAESurrogate | None = None, in_sample: bool = False, residual_model: bool = True,
             fold_models: dict | None = None, regions: bool = True, n_jobs: int = 1, progress=print) -> Diagnosis:
    """Diagnose the gap between a campaign's CAE runs and its tests.

    Parameters
    ----------
    campaign : Campaign
        Tests (each with a companion CAE run, or a surrogate from the CAE runs) and CAE runs.
    effects : sequence of str
        Candidate effects (catalogue names).
    threshold : float
        Minimum relative drop of the held-out mean squared error for an effect to be added (over
        every fold and over the folds it acts on).
    alpha : float
        Level of the one-sided sign test over the folds the effect acts on.
    move : float
        A fold is one the effect acts on when its held-out prediction moves by more than this
        share of the test's rms deceleration.
    k, inputs : int, str
        The GMM-GPR residual model (mixture size, input mode) of the shrink table.
    n_samples : int
        Monte Carlo samples of the GMM-GPR predictions.
    random_state : int
    surrogate : CAESurrogate, optional
        Fitted on the CAE runs; fitted here when needed.
    in_sample : bool
        Allow a single-test campaign: evidence is then in-sample (no hold-out), flagged.
    residual_model : bool
        Compute the two GMM-GPR rows of the shrink table (the slow part).
    fold_models : dict of str to FittedModel, optional
        The GMM-GPR alone's fold models, each test's fitted without it with ``k`` and ``inputs`` (the
        workflow's folds): its rows are rolled out from them instead of refitted, and the CAE + effects
        + GMM-GPR folds take their method settings but not their scatter refits (the cost of a fold
        fit, twice and more; on `paper` they move the row's Monte Carlo mean by 0.0006 ISO at most:
        docs/decisions.md, section 67). Default: both fitted here with the input mode's defaults,
        neither with the refits.
    regions : bool
        Locate the gap (:func:`crashfuse.diagnosis.gap.locate_gap`, with the same ``k``); needs two tests.
    n_jobs : int
        Worker processes for the candidate effects of a selection round and the GMM-GPR folds of the
        shrink table (the same numbers with any, to about 1e-11: workers sum some BLAS products in
        another order than the main process).
    progress : callable or None

    Raises
    ------
    InputError
        Fewer than two tests (unless ``in_sample``), no CAE runs, unknown effects, bad settings.
    """
    say = progress or (lambda line: None)
    effects = [check_effect(e, "effects") for e in dict.fromkeys(effects)]
    _check(campaign, threshold, alpha, move, in_sample)
    holdout = len(campaign.tests) >= 2
    regions = regions and holdout
    if surrogate is None and (regions or (holdout and residual_model)):  # fit it once for every part
        surrogate = CAESurrogate(random_state=random_state).fit(campaign)
    case = test_case(campaign, surrogate, random_state)
    n = len(case.test_ids)
    sets = loto_sets(n) if holdout else [[0], [0]]  # a single test: its in-sample fit, twice
    cae = fit_folds(case, (), sets)
    rule = _rule(threshold, alpha, move, holdout)
    chosen, candidates, pairs, current = _select(case, sets, cae, effects, rule, n_jobs, say)
    (cae_pred, cae_mse), (fx_pred, fx_mse) = (_heldout(case, fits) for fits in (cae, current))
    preds = {"CAE": cae_pred, "CAE+effects": fx_pred}
    residual = _residual_config(k, inputs, random_state, fold_models) if holdout and residual_model else None
    shrink = _shrink(campaign, case, preds, current, residual, fold_models, n_samples, surrogate, n_jobs, say)
    settings = dict(effects=list(effects), threshold=threshold, alpha=alpha, move=move, k=k, inputs=inputs,
                    n_samples=n_samples, random_state=random_state, rollout_dt_s=DT, rate_aware=case.rate_aware,
                    kernels=cpu_kernels())
    gap = locate_gap(campaign, surrogate=surrogate, k=k, random_state=random_state) if regions else None
    return Diagnosis(chosen, candidates, gap.to_json() if gap else {}, shrink, case, preds, settings, holdout, gap,
                     pairs, float(fx_mse.sum() / cae_mse.sum()))


@dataclasses.dataclass(frozen=True)
class _Base:
    """The effects chosen before a round: their fits, held-out errors (n_tests,) and predictions (n_tests, n_t)."""

    chosen: tuple
    fits: FoldFits
    mse: np.ndarray
    pred: np.ndarray


def _select(case: TestCase, sets, cae: FoldFits, effects, rule: dict, n_jobs: int, say):
    """Greedy forward selection on held-out evidence over the training ``sets`` of ``cae``, a round's
    candidates fitted on ``n_jobs`` processes; ``rule`` holds :func:`crashfuse.diagnosis.evidence.judge`'s
    threshold, alpha and move. A round adds the best-supported single effect or, when none qualifies,
    the best-supported pair (:func:`_pair_round`); an effect chosen before that the round's makes
    unneeded leaves (:func:`_drop_unneeded`). Returns (chosen, candidates, pairs tried, final fits)."""
    base = _Base((), cae, *_heldout(case, cae)[::-1])
    candidates, pairs, dropped = {}, [], set()
    say(f"diagnose: {len(case.test_ids)} tests, CAE held-out rms {_rms_g(base.mse):.3f} g")
    for rnd in itertools.count(1):
        remaining = [e for e in effects if e not in base.chosen and e not in dropped]
        if not remaining:
            break
        round_fits = Parallel(n_jobs=n_jobs)(delayed(fit_beyond)(case, base.fits, (e,), sets) for e in remaining)
        singles = {}
        for e, fits in zip(remaining, round_fits):
            fits, pred, mse, ev = _judged_within_limits(case, sets, fits, (e,), base, rule)
            singles[e] = _Base((*base.chosen, e), fits, mse, pred)
            candidates[e] = c = _bounded(Candidate(e, rnd, fits, mse, base.mse, ev, _acts_on(case, ev)))
            say(f"  round {rnd} +{e}: {_evidence_line(case, c)}")
        for e in remaining:
            if not candidates[e].evidence.accepted:
                say(f"diagnose: round {rnd} +{e} refused: {candidates[e].evidence.reason}")
        best = _needed_best(case, sets, rule, say, rnd, base, candidates, remaining)
        if best is not None:
            others = _accepted_others(best, singles, candidates)
            candidates[best].not_told_from = _not_told_apart(case, rule, say, rnd, (best,), singles[best], others)
            added, base = [candidates[best]], singles[best]
        else:
            added, tried, base = _pair_round(case, sets, rule, n_jobs, say, rnd, base,
                                             {e: candidates[e] for e in remaining})
            pairs += tried
            if not added:
                break
        for c in added:
            c.chosen = True
            candidates[c.effect] = c
        base = _drop_unneeded(case, sets, rule, say, rnd, base, candidates, dropped)
    for e in base.chosen:  # read as fitted together: the model of the shrink table, not its round's fit
        candidates[e].fits = base.fits
    verdict = set(base.chosen)
    for e, c in candidates.items():  # a pick (or its partner) dropped later, or an alternative named too: no question
        kept = {e, c.partner or e} <= verdict
        c.not_told_from = [o for o in c.not_told_from if kept and not set(o["effect"].split("+")) <= verdict]
    say(f"diagnose: verdict {list(base.chosen) or 'none'}")
    return list(base.chosen), candidates, pairs, base.fits


def _needed_best(case, sets, rule, say, rnd, base: _Base, candidates: dict, names):
    """:func:`best_supported` of ``names``, each pick also needed beyond the effects chosen before
    refitted from its own fit's values (:func:`_alone`, as a pair's member): a candidate whose gain is
    a better optimum of the chosen effects' parameters, not its own law, is refused and the next
    best-supported is tried (docs/decisions.md, section 34)."""
    while (best := best_supported(candidates, names)) is not None and base.chosen:
        c = candidates[best]
        needed = _judged(case, c.fits, (best,), _alone(case, sets, c.fits, base.chosen, base.fits), rule)[2]
        if needed.accepted:
            break
        reason = f"not needed beyond {' '.join(base.chosen)} refitted from its fit: {needed.reason}"
        c.evidence = dataclasses.replace(c.evidence, accepted=False, reason=reason)
        say(f"diagnose: round {rnd} +{best} refused: {reason}")
    return best


def _accepted_others(best: str, singles: dict, candidates: dict) -> dict:
    """The round's ``singles`` ({effect: fit}) but ``best`` whose own evidence was accepted: the alternatives
    its single pick is judged against (:func:`_not_told_apart`)."""
    return {e: fit for e, fit in singles.items() if e != best and candidates[e].evidence.accepted}


def _not_told_apart(case, rule, say, rnd, new: tuple, pick: _Base, alternatives: dict) -> list:
    """The ``alternatives`` ({name: fit}, the round's other accepted singles or supported pairs) that ``pick``,
    the round's choice adding ``new``, is not better than by the evidence rule, judged against each in turn:
    laws the tests cannot tell apart (subtle damping and rate hardening, docs/decisions.md, sections 34 and
    87). Reported with the verdict (but for those it names as well); the choice stays ``pick``."""
    told = []
    for name, other in alternatives.items():
        ev = _evidence(case, pick.fits, new, pick.pred, pick.mse, other, rule)
        if not ev.accepted:
            told.append({"effect": name, "heldout_mse_ratio": float(ev.ratio), "folds_better": int(ev.wins),
                         "folds_worse": int(ev.losses), "why": ev.reason})
            say(f"diagnose: round {rnd} +{'+'.join(new)} not told from +{name}: {ev.reason}")
    return told


def _drop_unneeded(case, sets, rule, say, rnd, base: _Base, candidates: dict, dropped: set) -> _Base:
    """``base`` without the effects chosen in earlier rounds that the later ones make unneeded: each
    must still be needed, by the evidence rule, beyond the others refitted from ``base``'s values
    (:func:`_alone`). Two laws can take up one gap in turn - a force growing with crush speed read
    first as rate hardening, then damping - and the first pick must not stay by its order alone
    (docs/decisions.md, section 43). A dropped effect joins ``dropped`` and is not tried again."""
    latest = max(candidates[e].round for e in base.chosen)
    for e in [e for e in base.chosen if candidates[e].round < latest]:
        rest = tuple(x for x in base.chosen if x != e)
        alone = _alone(case, sets, base.fits, rest)
        needed = _judged(case, base.fits, (e,), alone, rule)[2]
        if needed.accepted:
            continue
        c = candidates[e]
        reason = f"dropped in round {rnd}: not needed beyond {' '.join(rest)} refitted: {needed.reason}"
        c.chosen, c.evidence = False, dataclasses.replace(c.evidence, accepted=False, reason=reason)
        say(f"diagnose: {e} {reason}")
        dropped.add(e)
        base = alone
    return base


def _pair_round(case, sets, rule, n_jobs, say, rnd, base: _Base, singles: dict):
    """Every pair of the effects not yet chosen fitted together (with ``base``'s), when no single
    effect qualified: two withheld effects can each spoil, fitted alone, as many folds as they help
    (docs/decisions.md, section 32).

    Only pairs with a member that, fitted alone, moves the held-out prediction of at least
    :data:`~crashfuse.diagnosis.evidence.MIN_MATERIAL` counted folds are tried: masking shows as a
    member that moves predictions and spoils as many as it helps; two effects the tests do not see
    one at a time are not tried together (on a control or after the last effect, most rounds).

    A pair is supported when its evidence holds against ``base``, no parameter of either member sits
    at a physical bound, and its evidence holds against each member fitted alone (:func:`_alone`,
    from this round's candidates ``singles`` and the pair's values) - each member must be needed.
    Returns the two member candidates of the supported pair of lowest held-out error (or []), a
    summary of every pair tried, and the new base.
    """
    seen = {e for e, c in singles.items() if (c.evidence.affected & ~c.evidence.sole).sum() >= MIN_MATERIAL}
    pairs = [pair for pair in itertools.combinations(singles, 2) if seen.intersection(pair)]
    say(f"diagnose: round {rnd}: no single effect qualifies; {len(pairs)} pairs with "
        f"{' or '.join(sorted(seen)) or 'a member that moves predictions'}")
    if not pairs:
        return [], [], base
    pair_fits = Parallel(n_jobs=n_jobs)(delayed(fit_beyond)(case, base.fits, pair, sets) for pair in pairs)
    supported, tried = {}, []
    for pair, fits in zip(pairs, pair_fits):
        fits, pred, mse, ev = _judged_within_limits(case, sets, fits, pair, base, rule)
        members = [Candidate(e, rnd, fits, mse, base.mse, ev, _acts_on(case, ev), partner=other)
                   for e, other in (pair, pair[::-1])]
        bound = _at_limit(fits, pair)
        reason = ev.reason or (_bound_reason(fits, bound) if bound else "")
        for e, other in (pair, pair[::-1]):
            if not reason:
                alone = _alone(case, sets, fits, (*base.chosen, other), singles[other].fits)
                needed = _judged(case, fits, (e,), alone, rule)[2]
                reason = "" if needed.accepted else f"{e} not needed beyond {other} alone: {needed.reason}"
        say(f"  round {rnd} +{'+'.join(pair)}: {_evidence_line(case, members[0])}; {reason or 'supported'}")
        tried.append({"effects": list(pair), "round": rnd, "heldout_mse_ratio": ev.ratio, "accepted": not reason,
                      "refused_because": reason, "chosen": False})
        if not reason:
            supported[pair] = members, _Base((*base.chosen, *pair), fits, mse, pred)
    if not supported:
        return [], tried, base
    pick = min(supported, key=lambda pair: supported[pair][0][0].ratio)
    members, new_base = supported.pop(pick)
    tried[pairs.index(pick)]["chosen"] = True
    others = {"+".join(pair): fit for pair, (_, fit) in supported.items()}
    members[0].not_told_from = _not_told_apart(case, rule, say, rnd, pick, new_base, others)
    return members, tried, new_base


def _alone(case: TestCase, sets, pair: FoldFits, effects, single: FoldFits | None = None) -> _Base:
    """``effects`` (a pair's fit without one member) fitted as well as the search can: per training
    set the better of ``single``, their fit in the round (if any), and a refit from the pair's values -
    a single fit stuck in a worse optimum must not make the dropped member look needed."""
    names = {p.name for p in parameters_to_fit(case, effects)}
    keep = [i for i, p in enumerate(pair.params) if p.name in names]
    fits = fit_folds(case, effects, sets, start=pair.theta[:, keep])
    if single is not None:
        fits = better_of(single, fits)
    pred, mse = _heldout(case, fits)
    return _Base(tuple(effects), fits, mse, pred)


def _judged_within_limits(case: TestCase, sets, fits: FoldFits, new, base: _Base, rule: dict):
    """:func:`_judged`; where the evidence holds but a parameter of ``new`` sits at its physical limit,
    the same for the refit that holds it a little inside (:func:`_within_limits`). Returns the fits
    judged, the held-out prediction, its mean squared error and the :class:`Evidence`."""
    pred, mse, ev = _judged(case, fits, new, base, rule)
    bound = _at_limit(fits, new)
    if ev.accepted and bound:
        fits = _within_limits(case, sets, fits, bound)
        pred, mse, ev = _judged(case, fits, new, base, rule)
    return fits, pred, mse, ev


def _within_limits(case: TestCase, sets, fits: FoldFits, bound) -> FoldFits:
    """``fits`` refitted with each parameter of ``bound`` held at :data:`HELD_INSIDE` of its physical
    limit, from ``fits``' values and the listed starts. Whether a law needs more than is physical
    must not turn on where one fit stopped: with a second optimum inside the limits (a flat or
    two-basin objective, where the last bits of the BLAS kernels chose the limit; docs/decisions.md,
    section 52) the refit finds it; a law that needs more sits at the held bound again."""
    held = {p.name: HELD_INSIDE * p.upper for p in fits.params if p.name in bound}
    return fit_folds(case, fits.effects, sets, start=fits.theta, listed_too=True, held=held)


def _bound_reason(fits: FoldFits, bound) -> str:
    """Why a law at its physical limit is refused (``bound``: the parameter names)."""
    held = f" (refitted held at {HELD_INSIDE:.0%} of it: there again)" if fits.held else ""
    return f"at a physical bound: {', '.join(bound)}{held}"


def _judged(case: TestCase, fits: FoldFits, new, base: _Base, rule: dict):
    """Held-out prediction, mean squared error and :class:`Evidence` of ``fits`` (``base``'s effects
    plus ``new``) against ``base``'s held-out errors and predictions."""
    pred, mse = _heldout(case, fits)
    return pred, mse, _evidence(case, fits, new, pred, mse, base, rule)


def _evidence(case: TestCase, fits: FoldFits, new, pred, mse, base: _Base, rule: dict):
    """:class:`Evidence` of ``fits``' held-out predictions ``pred`` and errors ``mse`` against ``base``'s."""
    groups = next((g for e in new if (g := _groups(case, fits, e)) is not None), None)
    return judge(base.mse, mse, _rms(case, pred - base.pred), _rms(case, case.target), groups=groups, **rule)


def _acts_on(case: TestCase, ev: Evidence) -> list:
    return [t for t, a in zip(case.test_ids, ev.affected) if a]


def _evidence_line(case: TestCase, c: Candidate) -> str:
    ev = c.evidence
    return (f"held-out rms {_rms_g(c.heldout_mse):.3f} g (x{c.ratio:.3f} MSE), acts on "
            f"{' '.join(c.acts_on) or 'no test'}{_sole_note(case, ev)}: better on {ev.wins}, worse on {ev.losses} "
            f"(sign test p {ev.p_value:.3g}, permutation p {ev.permutation_p:.3g}, x{ev.affected_ratio:.3f} MSE there)"
            + "".join(f"; refitted with {name} held at {upper:.4g}" for name, upper in c.fits.held.items()))


def best_supported(candidates: dict, names) -> str | None:
    """The effect of ``names`` a round adds: the lowest held-out error among the candidates whose
    evidence is accepted (:func:`_bounded`: not at a physical bound); None when there is none.

    Not simply the lowest error: a candidate that lowers the error on some folds and raises it on
    others (two effects withheld, one fitted alone) must not hide one that lowers it consistently.
    """
    supported = [e for e in names if candidates[e].evidence.accepted]
    return min(supported, key=lambda e: candidates[e].ratio, default=None)


def _bounded(c: Candidate) -> Candidate:
    """``c``, refused when one of its own parameters sits at an upper bound that is a physical limit:
    the law needed more than is physical (diagnosis.json says so, as for a pair)."""
    if c.evidence.accepted and c.at_upper_bound:
        reason = _bound_reason(c.fits, c.at_upper_bound)
        c.evidence = dataclasses.replace(c.evidence, accepted=False, reason=reason)
    return c


def _sole_note(case: TestCase, ev: Evidence) -> str:
    sole = [t for t, x in zip(case.test_ids, ev.sole) if x]
    return f" ({' '.join(sole)} the only one of its label: not counted)" if sole else ""


def _groups(case: TestCase, fits: FoldFits, effect: str):
    """The powertrain label of each test when ``effect``'s law has parameters per label, else None."""
    per_label = any("[" in p.name for p in fits.params if p.name.startswith(effect + "."))
    return case.plant.group if per_label else None


def _rule(threshold: float, alpha: float, move: float, holdout: bool) -> dict:
    """The settings of :func:`crashfuse.diagnosis.evidence.judge`. In-sample (one test) there are
    no folds to test: the evidence is the threshold on the in-sample error of a test it acts on."""
    if holdout:
        return dict(threshold=threshold, alpha=alpha, move=move)
    return dict(threshold=threshold, alpha=1.0, move=move, min_affected=1)


def _check(campaign, threshold, alpha, move, in_sample):
    if not (0 <= threshold < 1):
        raise InputError(f"expected a threshold in [0, 1), got {threshold}", field="threshold")
    if not (0 < alpha < 1):
        raise InputError(f"expected alpha in (0, 1), got {alpha}", field="alpha")
    if not (move >= 0):
        raise InputError(f"expected a non-negative move, got {move}", field="move")
    if len(campaign.tests) < 2 and not in_sample:
        raise InputError(f"the campaign has {len(campaign.tests)} test(s): a held-out diagnosis needs at least 2; "
                         f"an in-sample one (in_sample) fits a single test without hold-out", campaign.root, "source")


def _fold_rows(n: int) -> np.ndarray:
    """Problem index predicting test i: its own leave-one-out fold (the in-sample fit for one test)."""
    return np.arange(n)


def _heldout(case: TestCase, fits: FoldFits):
    """Held-out prediction (n_tests, n_t) and mean squared error (n_tests,) of every fold."""
    n = len(case.test_ids)
    return predict(case, fits, _fold_rows(n), range(n))


def _rms(case: TestCase, decel: np.ndarray) -> np.ndarray:
    """Rms of each row over its test's record, m/s^2."""
    return np.sqrt((np.where(case.mask, decel, 0.0) ** 2).sum(axis=1) / case.mask.sum(axis=1))


def _rms_g(mse: np.ndarray) -> float:
    return float(np.sqrt(mse.mean()) / G0)


def _shrink(campaign, case, preds, fits, config, fold_models, n_samples, surrogate, n_jobs, say):
    """The shrink table's rows: CAE and CAE + effects, and with a residual ``config`` the GMM-GPR alone
    and on CAE + effects (leave-one-test-out)."""
    rows = []
    for model, decel in preds.items():
        for i, t in enumerate(case.test_ids):
            rows += _iso_rows(campaign.pulses[t], case.time, decel[i], t, model)
    if config is not None:
        label = f"K{config.k}"
        quick = dict(ks=(config.k,), inputs=(config.inputs,), n_samples=n_samples, random_state=config.random_state,
                     surrogate=surrogate, progress=None,
                     **{name: value for name, value in config.as_dict().items()
                        if name not in ("k", "inputs", "random_state")})
        if fold_models:
            say("diagnose: GMM-GPR alone (leave-one-test-out), from the given fold models")
            rows += [row for t in case.test_ids for row in _model_fold(campaign, fold_models[t], t, n_samples,
                                                                      surrogate, label)]
            alone = []
        else:  # its folds in the pool of the residual's: no process idles between the two sets of folds
            alone = [delayed(_gmm_gpr_fold)(campaign, t, quick) for t in case.test_ids]
        say(f"diagnose: {'GMM-GPR alone and ' if alone else ''}CAE + effects + GMM-GPR residual "
            f"(leave-one-test-out), {n_jobs} jobs")
        folds = Parallel(n_jobs=n_jobs)(alone + [delayed(_effects_fold)(campaign, case, fits, i, quick)
                                                 for i in range(len(case.test_ids))])
        for j, iso in enumerate(folds):
            rows += _relabel(iso, label, "GMM-GPR" if j < len(alone) else "CAE+effects+GMM-GPR")
    return pd.DataFrame(rows, columns=["test_id", "model", "window_ms", *SCORES])


def _residual_config(k: int, inputs: str, random_state: int, fold_models: dict | None) -> MethodConfig:
    """The GMM-GPR residual model's settings: the fold models' (all alike), else the input mode's defaults
    on the test's own CAE run; without the scatter refits (their cost; see :func:`diagnose`)."""
    if not fold_models:
        return MethodConfig(k=k, inputs=inputs, random_state=random_state, use_companion=True, estimate_scatter=False)
    configs = {dataclasses.replace(m.config, estimate_scatter=False) for m in fold_models.values()}
    config = configs.pop()
    problem = residual_fold_problem(config, k, inputs) or ("the fold models' settings differ" if configs else None)
    if problem:
        raise InputError(problem, field="fold_models")
    return config


def residual_fold_problem(config: MethodConfig, k: int, inputs: str) -> str | None:
    """Why a fold model of these settings cannot stand for the GMM-GPR alone with ``k`` and ``inputs``, or None."""
    if (config.k, config.inputs) != (k, inputs) or config.effects:
        return (f"expected the GMM-GPR alone with K = {k} and {inputs} inputs, got K = {config.k}, {config.inputs} "
                f"inputs, effects {config.effects or 'none'}")
    return None


def _model_fold(campaign, model, test_id, n_samples, surrogate, label) -> list[dict]:
    """The ISO rows of a fold model's prediction of its held-out test, as ``evaluate`` scores a fold."""
    from crashfuse.evaluation.loto import scored_fold

    iso = scored_fold(model, campaign, surrogate, test_id, n_samples)["iso"]
    return _relabel(pd.DataFrame(iso), label, "GMM-GPR")


def _gmm_gpr_fold(campaign, test_id, quick) -> pd.DataFrame:
    """ISO table of the GMM-GPR fold holding out ``test_id`` on ``campaign`` (one process: a pool's task)."""
    from crashfuse.evaluation.loto import evaluate

    return evaluate(campaign, holdout=[test_id], n_jobs=1, **quick).iso_table


def _effects_fold(campaign, case, fits, fold, quick) -> pd.DataFrame:
    """:func:`_gmm_gpr_fold` holding out test ``fold`` on the campaign whose CAE runs are CAE + effects (that
    fold's effect fit)."""
    return _gmm_gpr_fold(_effects_campaign(campaign, case, fits, fold), case.test_ids[fold], quick)


def _relabel(iso: pd.DataFrame, label: str, name: str) -> list[dict]:
    part = iso[iso["model"] == label].drop(columns=["inputs"]).assign(model=name)
    return part.to_dict(orient="records")


def _iso_rows(test: Pulse, t, decel, test_id, model) -> list[dict]:
    test = test.after_contact()
    out = []
    for w in WINDOWS:
        lo, hi = window_bounds(w)
        out.append(dict(test_id=test_id, model=model, window_ms=w,
                        **iso_score(test.time, test.decel, t, decel, lo * MS, hi * MS)))
    return out


def _effects_campaign(campaign: Campaign, case: TestCase, fits: FoldFits, fold: int) -> Campaign:
    """The campaign with every test's CAE run replaced by its CAE + effects rollout with fold ``fold``'s fit."""
    n = len(case.test_ids)
    decel, _ = predict(case, fits, np.full(n, fold), range(n))
    frame = campaign.conditions.copy()
    pulses = dict(campaign.pulses)
    new_rows = []
    for i, t in enumerate(case.test_ids):
        test = campaign.pulses[t]
        run_id = f"{t}__cae_effects"
        pulses[run_id] = Pulse(case.time, decel[i], test.v0, test.front_weight, test.rear_weight, run_id, "cae",
                               meta={**{k: test.meta.get(k) for k in ("powertrain", "drive")}, "cfc": 60})
        new_rows.append({**frame.loc[frame["run_id"] == t].iloc[0].to_dict(), "run_id": run_id, "source": "cae",
                         "cae_run_id": None, "pulse_path": None})
        frame.loc[frame["run_id"] == t, "cae_run_id"] = run_id
    frame = pd.concat([frame, pd.DataFrame(new_rows)], ignore_index=True)
    return Campaign(frame, pulses, campaign.root)


def _candidate_json(c: Candidate, case: TestCase) -> dict:
    all_fit = c.fits.theta[-1]
    def own(theta):
        return {p.name: v for p, v in zip(c.fits.params, theta) if p.name.startswith(c.effect + ".")}

    se = _jackknife_se(c.fits.theta[:-1])
    head = headline(c.effect, own(all_fit))
    head_se = _jackknife_se(np.array([list(headline(c.effect, own(t)).values()) for t in c.fits.theta[:-1]]))
    # A value at a bound means the law could not fit within physical limits: read it with care.
    # A value still exactly at a starting point never moved: no test is sensitive to it (e.g. a
    # powertrain gap that no test of that label reaches) - not identified.
    params = {p.name: {"value": float(v), "jackknife_se": _num(s), "unit": p.unit,
                       "at_bound": bool(np.isclose(v, p.lower, rtol=1e-3) or np.isclose(v, p.upper, rtol=1e-3)),
                       "identified": not any(np.isclose(v, x, rtol=1e-9) for x in p.start)}
              for p, v, s in zip(c.fits.params, all_fit, se)}
    return {
        "effect": c.effect, "chosen": c.chosen, "params": params,
        "headline": head, "headline_se": {k: _num(x) for k, x in zip(head, head_se)},
        "evidence": {"round": c.round, "heldout_mse_ratio": c.ratio, "acts_on": list(c.acts_on),
                     "not_counted": [t for t, x in zip(case.test_ids, c.evidence.sole) if x],
                     "folds_better": c.wins, "folds_worse": c.evidence.losses, "sign_test_p": c.evidence.p_value,
                     "permutation_p": c.evidence.permutation_p,
                     "scatter_g": c.evidence.scatter / G0, "folds_beyond_scatter": int(c.evidence.material.sum()),
                     "affected_mse_ratio": c.evidence.affected_ratio, "accepted": c.evidence.accepted,
                     "refused_because": c.evidence.reason, "at_upper_bound": c.at_upper_bound,
                     "held_upper": dict(c.fits.held),
                     "n_folds": int(c.heldout_mse.size), "heldout_rms_g": _rms_g(c.heldout_mse),
                     "reference_rms_g": _rms_g(c.reference_mse), "fitted_with": list(c.fits.effects),
                     "added_with": c.partner, "not_told_from": c.not_told_from},
        "reading": reading(c.effect, own(all_fit), case),
    }


def _jackknife_se(folds: np.ndarray) -> np.ndarray:
    """Jackknife standard error of each column over the leave-one-test-out fits, shape (n_folds, m) -> (m,)."""
    n = folds.shape[0]
    if n < 2:
        return np.full(folds.shape[1], np.nan)
    return np.sqrt((n - 1) / n * ((folds - folds.mean(axis=0)) ** 2).sum(axis=0))


def _num(x):
    return None if not np.isfinite(x) else float(x)


def reading(effect: str, p: dict, case: TestCase) -> str:
    """A plain-language sentence for a fitted effect, at the campaign's highest test speed."""
    v = float(case.plant.v0.max())
    mass = float(case.plant.mass.mean())
    at = f"{v / MPH:.0f} mph"
    if effect == "strain_rate":
        gain = (v / p["strain_rate.d"]) ** (1 / p["strain_rate.q"])
        return (f"the crush force grows with crush speed: by about {100 * gain:.0f} % at the {at} impact speed "
                f"({100 * (V_REF / p['strain_rate.d']) ** (1 / p['strain_rate.q']):.0f} % at {V_REF:.0f} m/s)")
    if effect == "damping":
        return (f"a crush damping growing as the crush speed to the power {p['damping.n']:.2f} "
                f"({p['damping.c'] / 1e3:.1f} kN s/m at {V_REF:.0f} m/s) adds about "
                f"{damping_force(p, v) / mass / G0:.1f} g at first contact at {at}")
    if effect == "mass":
        hz = np.sqrt(p["mass.k_link"] / p["mass.extra"]) / (2 * np.pi)
        link = ("carried rigidly" if hz >= RIGID_LINK_HZ else
                f"on a compliant link ({p['mass.k_link'] / 1e6:.2f} kN/mm, {hz:.0f} Hz): it loads the body late")
        return f"the decelerating mass is about {p['mass.extra']:.0f} kg more than the nominal test weight, {link}"
    if effect == "unloading":
        lam = decay_length(p, F_REF)
        return (f"after maximum crush the force falls along a power law (exponent {p['unloading.n']:.2f}): from "
                f"a {F_REF / 1e3:.0f} kN peak, at first as fast as an exponential decay over {1e3 * lam:.1f} mm, "
                f"reaching zero after {1e3 * p['unloading.n'] * lam:.0f} mm")
    parts = [f"{p[f'powertrain.mass[{lab}]']:.0f} kg ({lab}) after {1e3 * p[f'powertrain.gap[{lab}]']:.0f} mm"
             for lab in case.plant.labels]
    return (f"a powertrain mass is stopped by the barrier once the crush closes its gap: {'; '.join(parts)}; "
            f"its mounts ({p['powertrain.k_mount'] / 1e6:.1f} kN/mm) yield at {p['powertrain.f_mount'] / 1e3:.0f} kN "
            f"after {1e3 * p['powertrain.f_mount'] / p['powertrain.k_mount']:.0f} mm")


def write_diagnosis(diag: Diagnosis, out, campaign: Campaign) -> Path:
    """Write ``diagnosis.json``, ``diagnosis.md``, ``shrink.csv`` and the figures into ``out``.

    Every file is written atomically; ``diagnosis.json`` last, so its presence marks a complete
    diagnosis.
    """
    from crashfuse.reporting import plots

    out = Path(out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    js = diag.to_json()
    figures = {"effects.png": plots.effect_pulses_figure(campaign, diag)}
    if diag.gap is not None:
        figures.update({"bias_map.png": plots.bias_map_figure(diag.gap),
                        "gap_pulses.png": plots.gap_pulses_figure(diag.gap)})
    for name, fig in figures.items():
        plots.save_png(fig, out / "figures" / name)
    js["figures"] = [f"figures/{name}" for name in figures]
    with atomic_path(out / "shrink.csv") as tmp:
        diag.shrink.to_csv(tmp, index=False, float_format="%.6f", lineterminator="\n")
    write_text(out / "diagnosis.md", markdown(js))
    write_text(out / "diagnosis.json", json.dumps(js, indent=2, allow_nan=False) + "\n")
    return out


def markdown(js: dict) -> str:
    """A readable report of a diagnosis.json dict."""
    verdict = ", ".join(js["verdict"]) or "none: no catalogue effect explains the gap beyond noise"
    lines = ["# Sim-to-real gap diagnosis", "", f"**Verdict:** {verdict}", ""]
    lines += _not_told_lines(js["effects"])
    if not js["holdout"]:
        lines += ["**One test, no hold-out:** the evidence below is in-sample fit, not prediction.", ""]
    lines += ["## Which effect", "",
              "| effect | chosen | round | held-out MSE ratio | acts on (held-out prediction moves) | "
              "better / worse there | sign / permutation test p | MSE ratio there | headline | reading |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for e in js["effects"]:
        ev = e["evidence"]
        se = e["headline_se"]
        head = ", ".join(f"{k} = {v:.4g}" + ("" if se[k] is None else f" (se {se[k]:.2g})")
                         for k, v in e["headline"].items())
        pair = f" (with {ev['added_with']})" if ev.get("added_with") else ""
        lines.append(f"| {e['effect']} | {'yes' if e['chosen'] else 'no'} | {ev['round']}{pair} | "
                     f"{ev['heldout_mse_ratio']:.3f} | {' '.join(ev['acts_on']) or 'none'} "
                     f"({len(ev['acts_on'])}/{ev['n_folds']}) | {ev['folds_better']} / {ev['folds_worse']} | "
                     f"{ev['sign_test_p']:.3g} / {ev['permutation_p']:.3g} | {ev['affected_mse_ratio']:.3f} | {head} | "
                     f"{e['reading']} |")
    if js.get("pairs"):
        lines += ["", "Pairs fitted together in a round where no single effect qualified:", ""]
        lines += [f"- round {p['round']} {' + '.join(p['effects'])}: held-out MSE ratio {p['heldout_mse_ratio']:.3f}, "
                  + ("chosen" if p["chosen"] else "supported" if p["accepted"] else f"refused: {p['refused_because']}")
                  for p in js["pairs"]]
    lines += ["", "Fitted parameters (all tests; jackknife standard error over the folds; the verdict's effects "
                  "fitted together):", ""]
    fits = {}  # the chosen effects share the verdict's fit: one line
    for e in js["effects"]:
        fits.setdefault(tuple(e["evidence"]["fitted_with"]), e)
    for e in sorted(fits.values(), key=lambda e: not e["chosen"]):
        ps = "; ".join(f"{k} = {v['value']:.4g} {v['unit']}" + (f" (se {v['jackknife_se']:.2g})"
                                                               if v["jackknife_se"] is not None else "")
                       + (" **at its bound**" if v["at_bound"] else "")
                       + ("" if v["identified"] else " **not identified**") for k, v in e["params"].items())
        name = "verdict" if e["chosen"] else e["effect"]
        lines.append(f"- {name} (fitted with {', '.join(e['evidence']['fitted_with'])}): {ps}")
    lines += ["", "## How far it shrinks (mean ISO/TS 18571 overall, held-out)", "",
              "| model | " + " | ".join(f"{w} ms" for w in WINDOWS) + " |", "|---|" + "---|" * len(WINDOWS)]
    for model, row in js["shrink"].items():
        lines.append(f"| {model} | " + " | ".join(f"{row[w]:.3f}" if w in row else "" for w in WINDOWS) + " |")
    if js["regions"]:
        lines += ["", *_regions_markdown(js["regions"])]
    lines += ["", f"Computed with {js['settings']['kernels']} (docs/decisions.md, sections 56 and 60)."]
    return "\n".join(lines) + "\n"


def not_told_apart(effects: list) -> list[tuple[str, dict]]:
    """(pick, alternative) for each alternative the tests do not tell a chosen effect from
    (:func:`_not_told_apart`), from diagnosis.json's ``effects``; a pair's pick named with its partner."""
    return [("+".join(filter(None, (e["effect"], e["evidence"]["added_with"]))), other)
            for e in effects if e["chosen"] for other in e["evidence"]["not_told_from"]]


def _not_told_lines(effects: list) -> list[str]:
    """A line per pick and alternative the tests do not tell it from."""
    return [line for pick, other in not_told_apart(effects)
            for line in (f"**Not told apart:** {pick} from {other['effect']} (held-out MSE ratio "
                         f"{other['heldout_mse_ratio']:.3f} against it; {other['why']}): the tests support either.",
                         "")]


def _regions_markdown(regions: dict) -> list[str]:
    """The significant intervals, the sub-score carrying the gap per window and the speed regimes."""
    lines = ["## Where the gap lies (95 % band of the bias excludes zero)", "",
             "| rank | branch | interval (mm) | peak (mm) | direction | share of squared gap | carried by | "
             "time windows (ms) |", "|---|---|---|---|---|---|---|---|"]
    for iv in regions["intervals"]:
        wins = ", ".join(f"{w['test_id']} {w['t_lo_ms']:.0f}-{w['t_hi_ms']:.0f}" for w in iv["windows"]
                         if w.get("significant"))
        carrier = (iv.get("subscores") or {}).get("ranking", ["-"])[:1]
        lines.append(f"| {iv['rank']} | {iv['branch']} | {1e3 * iv['x_lo_m']:.0f}-{1e3 * iv['x_hi_m']:.0f} | "
                     f"{1e3 * iv['x_peak_m']:.0f} | {iv['direction']} | {iv['share']:.3f} | "
                     f"{', '.join(carrier)} | {wins} |")
    lines += ["", "| window (ms) | sub-scores by mean deficit (CAE vs test) |", "|---|---|"]
    for w, row in regions["windows"].items():
        lines.append(f"| {w} | " + ", ".join(f"{k} {row['mean_deficit'][k]:.3f}" for k in row["ranking"]) + " |")
    lines += ["", "| regime | speed (mph) | tests | mean squared bias (g^2) |", "|---|---|---|---|"]
    for r in regions["regimes"]:
        lines.append(f"| {r['rank']} | {r['v0_lo_mph']:.1f}-{r['v0_hi_mph']:.1f} | {' '.join(r['tests'])} | "
                     f"{r['mean_sq_bias_g2']:.1f} |")
    return lines
