"""Fitting effect parameters to tests: CAE + effect rollouts against measured pulses.

A :class:`TestCase` holds every test of a campaign with its CAE curve (the companion run where the
test names one, else the CAE surrogate at its condition) and its measured deceleration on the
rollout's time grid. :func:`fit_folds` fits the parameters of a set of effects for many training
sets at once - the leave-one-test-out folds plus the all-tests fit - by minimising the squared
difference between the CAE + effects rollout and the measured pulse over the record
(``sum_t (a_pred - a_test)^2``), with a Levenberg-Marquardt solver vectorised over the folds,
their starting points and the finite-difference Jacobian columns: every iteration is one
batched rollout (:func:`crashfuse.method.laws.simulate`). Parameters are fitted in log space
within their physical bounds.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from crashfuse.method.laws import (Plant, Param, crush_force_rate, curve_plant, parameters, simulate,
                                  simulate_shifted)
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.method.projection import cae_curve
from crashfuse.method.surrogate import CAECurve, CAESurrogate
from crashfuse.signals.domain import displacement_branches

DT = 1.6e-4  # s, rollout step of the fits (2 samples of a 12.5 kHz campaign; Verlet error << noise)
RECORD = 0.1  # s, longest record compared
FD_STEP = 1e-3  # finite-difference step in log-parameter space
MAX_ITER = 30
RTOL = 1e-5  # a set has converged when an accepted step lowers its cost by less than this fraction
FLAT = 1e-6  # a parameter at a bound with less curvature than this fraction of the normal matrix's trace stays there
S_HI_FACTOR = 1.6  # CAE tables reach this factor beyond the longest CAE/test crush
FASTER = 1.2  # impact speed (x v0) of the surrogate curve a rollout meets beyond its CAE run's crush
MIN_CAE_SPEEDS = 3  # distinct CAE impact speeds needed before the CAE force's rate sensitivity is estimated


@dataclasses.dataclass(frozen=True)
class TestCase:
    """The tests of a campaign, ready for batched effect fits.

    Attributes
    ----------
    test_ids : list of str
    plant : crashfuse.method.laws.Plant
        One row per test: its CAE curve, nominal mass, powertrain label.
    target : ndarray, shape (n_tests, n_t)
        Measured deceleration (m/s^2) at ``time`` (0 where ``mask`` is False).
    mask : ndarray of bool, shape (n_tests, n_t)
        True inside each test's record.
    time : ndarray, shape (n_t,)
        Rollout times in s (step :data:`DT`).
    cae_source : list of str
        ``companion`` or ``surrogate`` per test.
    crush : ndarray, shape (n_tests,)
        Each test's largest measured crush in m (where a law that acts beyond some crush was seen).
    rate_aware : bool
        Whether the CAE force follows the rollout's crush speed (:mod:`crashfuse.method.laws`).
    """

    test_ids: list
    plant: Plant
    target: np.ndarray
    mask: np.ndarray
    time: np.ndarray
    cae_source: list
    crush: np.ndarray
    rate_aware: bool = False

    @property
    def n_steps(self) -> int:
        return self.time.size - 1


def test_case(campaign: Campaign, surrogate: CAESurrogate | None = None, random_state: int = 0,
              rate_aware: bool = True) -> TestCase:
    """Every test of ``campaign`` with its CAE curve and measured pulse on the rollout grid.

    The CAE surrogate is fitted (on the CAE runs only) when a test names no companion run or its
    companion never reaches zero velocity (the unloading branch then comes from the surrogate), and
    for ``rate_aware``: the CAE force then follows the rollout's crush speed with the sensitivity
    the CAE runs show (:func:`crashfuse.method.laws.crush_force_rate`), and beyond a test's CAE run's
    maximum crush the reference is the surrogate's curve at :data:`FASTER` times its impact speed.
    It needs CAE runs at :data:`MIN_CAE_SPEEDS` distinct impact speeds; with fewer the CAE force
    depends on crush only (``TestCase.rate_aware`` False).

    Raises
    ------
    InputError
        No tests, no CAE runs, or a test whose CAE curve cannot be formed.
    """
    if not campaign.tests:
        raise InputError("the campaign has no tests: nothing to diagnose", campaign.root, "source")
    if not campaign.cae:
        raise InputError("the campaign has no CAE runs: the diagnosis explains a CAE model's gap", campaign.root,
                         "source")
    rate_aware = rate_aware and len({round(campaign.pulses[r].v0, 6) for r in campaign.cae}) >= MIN_CAE_SPEEDS
    if surrogate is None and (rate_aware or any(_needs_surrogate(campaign, t) for t in campaign.tests)):
        surrogate = CAESurrogate(random_state=random_state).fit(campaign)  # one source of curves for every test
    curves = [cae_curve(campaign, campaign.pulses[t], surrogate) for t in campaign.tests]
    sources = ["surrogate" if campaign.companion(t) is None else "companion" for t in campaign.tests]
    pulses = [campaign.pulses[t] for t in campaign.tests]
    record = min(RECORD, max(p.time[-1] for p in pulses))  # each test is compared within its own record
    time = np.arange(int(np.floor(record / DT + 1e-9)) + 1) * DT
    target = np.array([np.interp(time, p.time, p.decel) for p in pulses])
    mask = np.array([time <= p.time[-1] + 1e-12 for p in pulses])
    s_hi = S_HI_FACTOR * max(max(c.s[-1], c.s_max) for c in curves)
    labels = [powertrain_label(campaign, t) for t in campaign.tests]
    faster = ([faster_curve(surrogate, p.v0, p.front_weight, p.rear_weight, p.meta.get("powertrain"),
                            p.meta.get("drive")) for p in pulses] if rate_aware else None)
    force_rate = functools.partial(crush_force_rate, [campaign.pulses[r] for r in campaign.cae]) if rate_aware else None
    plant = curve_plant(curves, [p.mass for p in pulses], labels, s_hi, faster, force_rate)
    crush = np.array([displacement_branches(p).s_max for p in pulses])
    return TestCase(list(campaign.tests), plant, target, mask, time, sources, crush, rate_aware)


def faster_curve(surrogate: CAESurrogate, v0: float, front_weight: float, rear_weight: float, powertrain=None,
                 drive=None):
    """The surrogate's CAE curve of a vehicle at :data:`FASTER` times its impact speed ``v0`` (m/s), or
    None where it cannot absorb that impact energy (far outside the CAE runs)."""
    try:
        return surrogate.curve(FASTER * v0, front_weight, rear_weight, powertrain, drive)
    except InputError:
        return None


def powertrain_label(campaign: Campaign, test_id: str) -> str:
    """A run's powertrain label as the powertrain law keys it (``all`` where the campaign has none)."""
    row = campaign.conditions.loc[campaign.conditions["run_id"] == test_id].iloc[0]
    value = row.get("powertrain")
    return "all" if value is None or (isinstance(value, float) and np.isnan(value)) else str(value)


def _needs_surrogate(campaign: Campaign, test_id: str) -> bool:
    """A test with no companion, or one whose companion never stops: the projection needs the surrogate."""
    companion = campaign.companion(test_id)
    return companion is None or CAECurve.from_pulse(companion).u is None


@dataclasses.dataclass(frozen=True)
class FoldFits:
    """Fitted parameters of one effect set for several training sets.

    Attributes
    ----------
    effects : tuple of str
    params : tuple of Param
    theta : ndarray, shape (n_problems, n_params)
        Best parameters (SI) per training set.
    cost : ndarray, shape (n_problems,)
        Mean squared training residual in (m/s^2)^2.
    held : dict of str to float
        Upper bounds (SI) that replaced the listed ones in this fit, by parameter name.
    """

    effects: tuple
    params: tuple
    theta: np.ndarray
    cost: np.ndarray
    held: dict = dataclasses.field(default_factory=dict)


def parameters_to_fit(case: TestCase, effects, held: dict | None = None) -> tuple[Param, ...]:
    """The diagnosis laws' parameters of ``effects`` for this case, with their bounds and starting
    points (powertrain: per label of the case's tests); ``held``: upper bounds (SI) in place of the
    listed ones, by parameter name."""
    hint = float(case.plant.mass.min())
    held = held or {}
    return tuple(dataclasses.replace(p, upper=held[p.name]) if p.name in held else p
                 for e in effects for p in parameters(e, case.plant.labels, hint))


def fit_folds(case: TestCase, effects, train_sets, start: np.ndarray | None = None,
              listed_too: bool = False, held: dict | None = None) -> FoldFits:
    """Fit ``effects`` on each training set (vectorised Levenberg-Marquardt, multi-start).

    Parameters
    ----------
    case : TestCase
    effects : sequence of str
        Catalogue effects fitted together.
    train_sets : sequence of sequence of int
        Test indices of each training set (e.g. the leave-one-out folds and all tests).
    start : ndarray, shape (n_sets, n_params), optional
        The starting point per set (SI), e.g. the fit of a smaller effect set plus the new
        effect's first listed start; without it every listed start is tried.
    listed_too : bool
        With ``start``, try every listed start as well and keep each set's best: a warm start
        carries the smaller set's compromise (a powertrain fitted without the rate hardening it
        absorbed) and can hold a fit in that basin.
    held : dict of str to float, optional
        Upper bounds (SI) in place of the listed ones, by parameter name.

    Returns
    -------
    FoldFits
    """
    params = parameters_to_fit(case, effects, held)
    if not params:
        return FoldFits(tuple(effects), (), np.empty((len(train_sets), 0)), _costs(case, train_sets))
    starts = _starts(params, len(train_sets), start, listed_too)
    n_start = starts.shape[0]
    sets = [list(t) for t in train_sets] * n_start
    z = np.log(np.concatenate(starts))
    z, cost = _levenberg_marquardt(case, tuple(effects), params, sets, z)
    cost = cost.reshape(n_start, len(train_sets))
    best = np.argmin(cost, axis=0)
    z = z.reshape(n_start, len(train_sets), -1)[best, np.arange(len(train_sets))]
    return FoldFits(tuple(effects), params, np.exp(z), cost[best, np.arange(len(train_sets))], dict(held or {}))


def warm_start(case: TestCase, current: FoldFits, effects) -> np.ndarray | None:
    """Starting points of ``current``'s effects plus the new ``effects`` (a sequence of names): per
    training set, the values fitted there and each new parameter's first listed start (None when
    ``current`` fitted nothing)."""
    if current.theta.shape[1] == 0:
        return None
    new = [p.start[0] for p in parameters_to_fit(case, effects)]
    return np.hstack([current.theta, np.tile(new, (current.theta.shape[0], 1))])


def fit_beyond(case: TestCase, base: FoldFits, new, train_sets) -> FoldFits:
    """``base``'s effects and the ``new`` ones fitted together on ``base``'s training sets, from
    ``base``'s values (:func:`warm_start`; without any, every listed start).

    A set whose fit ends above ``base``'s own cost - more laws fitting the tests worse than fewer,
    a basin the new laws' first start led the search into - is fitted again from ``base``'s values
    with the new laws off (:attr:`crashfuse.method.laws.Param.off`), and the better of the two kept:
    a law set is never judged on a fit worse than the one it nests (docs/decisions.md, section 86).

    Parameters
    ----------
    case : TestCase
    base : FoldFits
        The fit of the smaller effect set, one row per training set.
    new : sequence of str
        Effects added.
    train_sets : sequence of sequence of int
        ``base``'s training sets.

    Returns
    -------
    FoldFits
    """
    effects = (*base.effects, *new)
    fits = fit_folds(case, effects, train_sets, start=warm_start(case, base, new))
    worse = np.flatnonzero(fits.cost > base.cost)
    off = _off_start(case, base, new) if worse.size else None
    if off is None:
        return fits
    return better_of(fits, fit_folds(case, effects, [train_sets[i] for i in worse], start=off[worse]), worse)


def better_of(fits: FoldFits, other: FoldFits, rows=None) -> FoldFits:
    """``fits`` with each of its ``rows`` (default: all) taken from ``other``'s row in turn where that
    fit ends at a lower cost: per training set the better of two fits of one law set."""
    rows = np.arange(fits.cost.size) if rows is None else rows
    take = other.cost < fits.cost[rows]
    theta, cost = fits.theta.copy(), fits.cost.copy()
    theta[rows[take]], cost[rows[take]] = other.theta[take], other.cost[take]
    return dataclasses.replace(fits, theta=theta, cost=cost)


def _off_start(case: TestCase, base: FoldFits, new) -> np.ndarray | None:
    """``base``'s values per training set and each new parameter's ``off`` value (its first start
    where its law is off by another parameter); None when a new law cannot be turned off."""
    params = parameters_to_fit(case, new)
    laws = {p.name.split(".")[0] for p in params if p.off is not None}
    if laws != set(new):
        return None
    values = np.tile([p.start[0] if p.off is None else p.off for p in params], (base.theta.shape[0], 1))
    return np.hstack([base.theta, values])


def _starts(params, n_sets: int, extra, listed_too: bool = False) -> np.ndarray:
    """Starting points, shape (n_start, n_sets, n_params): ``extra`` (and, ``listed_too``, each
    parameter's listed starts in turn), else the listed starts."""
    n = max(len(p.start) for p in params)
    base = np.array([[p.start[i % len(p.start)] for p in params] for i in range(n)])
    listed = np.repeat(base[:, None, :], n_sets, axis=1)
    if extra is None:
        return listed
    extra = np.asarray(extra, float)[None]
    return np.concatenate([extra, listed]) if listed_too else extra


def _bounds(params):
    return np.log([p.lower for p in params]), np.log([p.upper for p in params])


def _levenberg_marquardt(case, effects, params, sets, z):
    """Minimise each set's squared residual over log-parameters ``z`` (n_sets, d); all sets at once."""
    lo, hi = _bounds(params)
    z = np.clip(z, lo, hi)
    lam = np.full(len(sets), 1e-2)
    res = _residuals(case, effects, params, sets, z, np.arange(len(sets)))
    jac = _jacobian(case, effects, params, sets, z, np.arange(len(sets)), res)
    cost = np.array([r @ r for r in res])
    free = np.array([_free(j.T @ j, zi, lo, hi) for j, zi in zip(jac, z)])
    active = np.ones(len(sets), bool)
    for _ in range(MAX_ITER):
        steps = np.zeros_like(z)
        for i in np.flatnonzero(active):
            f = free[i]
            a, g = jac[i].T @ jac[i], jac[i].T @ res[i]
            if not f.all():
                a, g = a[np.ix_(f, f)], g[f]
            steps[i, f] = -np.linalg.lstsq(a + lam[i] * np.diag(np.diag(a)) + 1e-12 * np.eye(f.sum()) * np.trace(a), g,
                                           rcond=None)[0]
        trial = np.clip(z + steps, lo, hi)
        trial_res = _trial_residuals(case, effects, params, sets, trial, np.flatnonzero(active))
        new_cost = np.array([r @ r if r is not None else np.inf for r in trial_res])
        better = active & (new_cost < cost)
        converged = active & better & (cost - new_cost < RTOL * cost)
        z[better] = trial[better]
        cost[better] = new_cost[better]
        lam = np.where(better, lam / 3.0, lam * 4.0)
        active &= ~converged & (lam < 1e8)
        if not active.any():
            break
        moved = np.flatnonzero(better & active)
        jac_new = _jacobian(case, effects, params, sets, z, moved, trial_res)  # the residuals at z: the trial's
        for i in moved:
            res[i], jac[i] = trial_res[i], jac_new[i]
    n_res = np.array([case.mask[s].sum() for s in sets])
    return z, cost / n_res


def _free(a, z, lo, hi):
    """Which parameters a fit from ``z`` may move, shape (d,) bool: not one that starts at a bound of its
    box with a curvature below ``FLAT`` of the normal matrix ``a``'s trace there. The residuals cannot
    see such a parameter (an extra mass's link started at its rigid bound): Levenberg-Marquardt's
    damping ``lam diag(a)`` does not hold it, and its step off the bound was a ratio of two roundings
    that threw the fit into another basin. It stays where it started (another start explores it)."""
    return ~(((z <= lo) | (z >= hi)) & (np.diag(a) < FLAT * np.trace(a)))


def _samples(params, sets, z, which):
    """Rows and parameter arrays of a batched rollout: every set in ``which`` times every test in it."""
    rows, owner, values = [], [], []
    for i in which:
        rows.extend(sets[i])
        owner.extend([i] * len(sets[i]))
        values.append(np.repeat(z[i][None], len(sets[i]), axis=0))
    return np.array(rows, int), np.array(owner, int), np.exp(np.concatenate(values))


def _run(case, effects, params, rows, theta):
    plant = case.plant.subset(rows)
    traj = simulate(plant, effects, _named(params, theta), DT, case.n_steps)
    return np.where(case.mask[rows], traj.decel - case.target[rows], 0.0)


def _residuals(case, effects, params, sets, z, which):
    """Residual vector per set in ``which`` (None elsewhere), in m/s^2."""
    out = [None] * len(sets)
    if len(which) == 0:
        return out
    rows, owner, theta = _samples(params, sets, z, which)
    diff = _run(case, effects, params, rows, theta)
    for i in which:
        out[i] = diff[owner == i].ravel()
    return out


def _trial_residuals(case, effects, params, sets, z, which):
    """:func:`_residuals` at a trial step; None for a set whose rollout is not finite there, so that the
    step is rejected (its damping raised) instead of ending every set's fit. A law family wider than the
    catalogue's reached such a step on the second world (docs/decisions.md, section 83)."""
    try:
        return _residuals(case, effects, params, sets, z, which)
    except InputError:  # one batched rollout for all sets: find the sets that left the finite range
        out = [None] * len(sets)
        for i in which:
            try:
                out[i] = _residuals(case, effects, params, sets, z, [i])[i]
            except InputError:
                pass
        return out


def _jacobian(case, effects, params, sets, z, which, res):
    """Forward-difference Jacobians (in log-parameters) of the sets in ``which`` (None elsewhere), whose
    residuals at ``z`` are ``res``: every column's rollouts in one :func:`simulate_shifted`."""
    d, n = z.shape[1], len(sets)
    jac = [None] * n
    if len(which) == 0:
        return jac
    rows, _, theta = _samples(params, sets, z, which)
    shifted = np.concatenate([z + FD_STEP * np.eye(d)[j] for j in range(d)])  # d blocks of len(sets)
    moved = _samples(params, sets * d, shifted, np.concatenate([which + k * n for k in range(d)]))[2]
    decel = simulate_shifted(case.plant.subset(rows), effects, _named(params, theta),
                             [_named(params, t) for t in moved.reshape(d, rows.size, d)], DT, case.n_steps)
    diff = np.where(case.mask[rows][:, None], decel - case.target[rows][:, None], 0.0)  # (samples, d, n_t)
    ends = np.cumsum([len(sets[i]) for i in which])  # each set's samples, one block after another
    for i, block in zip(which, np.split(diff, ends[:-1])):
        jac[i] = np.ascontiguousarray((block.transpose(1, 0, 2).reshape(d, -1).T - res[i][:, None]) / FD_STEP)
    return jac


def _named(params, theta):
    """Parameter arrays by name from a matrix (n, len(params)), SI."""
    return {p.name: theta[:, j] for j, p in enumerate(params)}


def _costs(case, train_sets):
    """Mean squared residual of each training set for the CAE alone (no effect, nothing fitted)."""
    out = []
    for rows in train_sets:
        diff = _run(case, (), (), np.asarray(rows, int), np.empty((len(rows), 0)))
        out.append(float((diff ** 2).sum() / case.mask[list(rows)].sum()))
    return np.array(out)


def predict(case: TestCase, fits: FoldFits, problem_rows, test_rows):
    """Roll out test ``test_rows[i]`` with the parameters of problem ``problem_rows[i]``.

    Returns
    -------
    decel : ndarray, shape (len(test_rows), n_t)
        Deceleration in m/s^2 at ``case.time``.
    mse : ndarray, shape (len(test_rows),)
        Mean squared difference from the measured pulse inside the record, (m/s^2)^2.
    """
    test_rows = np.asarray(test_rows, int)
    theta = fits.theta[np.asarray(problem_rows, int)]
    plant = case.plant.subset(test_rows)
    traj = simulate(plant, fits.effects, _named(fits.params, theta), DT, case.n_steps)
    m = case.mask[test_rows]
    diff = np.where(m, traj.decel - case.target[test_rows], 0.0)
    return traj.decel, (diff ** 2).sum(axis=1) / m.sum(axis=1)


def loto_sets(n_tests: int) -> list[list[int]]:
    """The leave-one-test-out training sets, then the all-tests set."""
    every = list(range(n_tests))
    return [[j for j in every if j != i] for i in every] + [every]

