"""Where the sim-to-real gap lies: the bias field, its significant intervals, sub-scores and speed regimes.

:func:`locate_gap` fits the method's paper-input GMM-GP bias model on every test of a campaign
(companion CAE runs where tests name one, else the CAE surrogate) and reads it four ways:

1. the latent bias field (mean and 95 % band, no nugget) over displacement and impact speed,
   axle masses those of the tests at that speed, and along each test's own condition on both
   branches;
2. displacement intervals where the band excludes zero and the mean exceeds ISO/TS 18571's inner
   corridor (5 % of the test's peak deceleration: smaller differences rate as a perfect match):
   per test, runs of grid points of one sign at least ``MIN_RUN`` long; then, per branch and
   sign, the runs of all tests merged where they overlap (or nearly touch); ranked by their
   share of the squared gap;
3. which ISO/TS 18571 sub-score carries the CAE-vs-test gap in each rating window and each
   significant time window (the largest weighted deficit ``w_k (1 - score_k)``);
4. the mixture's clusters as speed regimes, ranked by their mean squared bias.

The rules and the JSON fields are in ``docs/diagnosis-gap.md``. It sees only the campaign.
Everything is SI inside; :meth:`GapMap.to_json` converts at the boundary (keys carry units).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from sklearn.mixture import GaussianMixture
from sklearn.preprocessing import StandardScaler

from crashfuse.signals.domain import Branch, displacement_branches
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.signals.iso18571 import A0
from crashfuse.signals.iso18571 import DT as ISO_DT
from crashfuse.signals.iso18571 import MIN_SAMPLES as ISO_MIN_SAMPLES
from crashfuse.signals.iso18571 import WEIGHTS, iso_score
from crashfuse.method.config import MethodConfig
from crashfuse.method.model import Condition, FittedModel, fit_model
from crashfuse.method.projection import BRANCHES, bias_data
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.units import G0, MPH, MS

Z95 = 1.959963984540054  # two-sided 95 % normal quantile
N_PROFILE = 200  # grid points along each test's branch
MAP_SHAPE = (60, 160)  # bias map cells: impact speeds x displacements
MIN_RUN = 0.02  # a per-test significant run must span 2 % of the test's branch reach (drops specks)
MERGE_GAP = 0.01  # runs of different tests merge when closer than 1 % of the branch's largest reach
K_CANDIDATES = (1, 2, 3)
SUBSCORES = tuple(WEIGHTS)  # corridor, phase, magnitude, slope


@dataclasses.dataclass(frozen=True, eq=False)
class Profile:
    """The bias along one test's branch at its own condition.

    Attributes
    ----------
    x : ndarray, shape (n,)
        Branch coordinate in m (``s`` loading, ``u = s_max - s`` unloading), 0 to the test's reach.
    mean, std : ndarray, shape (n,)
        Latent bias mean and std in m/s^2 (test minus CAE).
    significant : ndarray of bool, shape (n,)
        Inside a kept run: the 95 % band excludes zero and ``|mean|`` exceeds the test's floor
        (``A0`` x its peak deceleration), over at least ``MIN_RUN`` of the reach.
    time : ndarray, shape (n,)
        The time in s at which the test's own pulse is at ``x``.
    """

    x: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    significant: np.ndarray
    time: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class TestGap:
    """One test: condition, bias profiles per branch, and its pulse and CAE pulse in time.

    Attributes
    ----------
    test_id : str
    v0, front_weight, rear_weight : float
        m/s, kg, kg.
    profiles : dict of str to Profile
        Per branch present in the test (loading always).
    time, decel : ndarray, shape (n,)
        The test pulse, s and m/s^2.
    cae_time, cae_decel : ndarray, shape (m,)
        Its CAE pulse (companion run, else the surrogate's rollout), s and m/s^2.
    cae_source : str
        The companion run_id or ``"surrogate"``.
    """

    test_id: str
    v0: float
    front_weight: float
    rear_weight: float
    profiles: dict
    time: np.ndarray
    decel: np.ndarray
    cae_time: np.ndarray
    cae_decel: np.ndarray
    cae_source: str

    def significant_windows(self) -> list[tuple[str, float, float, int]]:
        """``(branch, t_lo, t_hi, sign)`` of every significant run of this test, times in s."""
        return [(b, float(p.time[a]), float(p.time[e - 1]), sign) for b, p in self.profiles.items()
                for a, e, sign in _runs(np.sign(p.mean) * p.significant)]


@dataclasses.dataclass(frozen=True)
class Interval:
    """A campaign-level significant interval on one branch, one sign.

    Attributes
    ----------
    branch : str
    x_lo, x_hi : float
        Branch coordinate bounds in m.
    sign : int
        +1 where the test decelerates more than the CAE, -1 less.
    share : float
        Fraction of the total squared gap inside it (see ``docs/diagnosis-gap.md``).
    x_peak : float
        Where the squared gap summed over tests peaks inside it, m.
    core : (float, float)
        The middle half of its squared gap (25 % and 75 % of the cumulative mass), m.
    tests : tuple of str
        Tests whose own significant runs make it up.
    windows : dict of str to (float, float)
        Per test reaching ``x_lo``: the time (s) its pulse spends inside the interval.
    subscores : dict
        Sub-score deficits CAE vs test inside the supporting tests' time windows (``_subscore_summary``).
    """

    branch: str
    x_lo: float
    x_hi: float
    sign: int
    share: float
    x_peak: float
    core: tuple
    tests: tuple
    windows: dict
    subscores: dict


@dataclasses.dataclass(frozen=True)
class Regime:
    """A mixture cluster of the loading-branch bias model read as a speed regime.

    Attributes
    ----------
    cluster : int
        GP index in the fitted model.
    v0_lo, v0_hi : float
        Impact speed range of its points in m/s.
    x_lo, x_hi : float
        Displacement range of its points in m.
    tests : dict of str to float
        Test -> fraction of that test's bias points in the cluster (tests with any).
    mean_sq_bias : float
        Mean of the observed squared bias ``(a_test - a_cae)^2`` over its points, (m/s^2)^2.
    n_points : int
    """

    cluster: int
    v0_lo: float
    v0_hi: float
    x_lo: float
    x_hi: float
    tests: dict
    mean_sq_bias: float
    n_points: int


@dataclasses.dataclass(frozen=True, eq=False)
class GapMap:
    """Where the gap lies (see :func:`locate_gap`); ``to_json()`` is ``regions`` of diagnosis.json.

    Attributes
    ----------
    k : int
        Mixture components asked for; ``k_rule`` says how it was chosen, ``bic`` the BIC per K tried.
    s_grid : ndarray, shape (n_s,)
        Map displacements in m.
    v0_grid : ndarray, shape (n_v,)
        Map impact speeds in m/s.
    map_mean, map_std : ndarray, shape (n_v, n_s)
        Loading-branch latent bias mean and std in m/s^2, axle masses those of the tests at each
        speed (mean over tests sharing a speed, linear in between).
    map_significant, map_covered : ndarray of bool, shape (n_v, n_s)
        Band excludes zero and ``|mean|`` exceeds the floor (``A0`` x the tests' peak deceleration,
        interpolated over speed); the cell lies within the crush the tests reach at that speed.
    tests : tuple of TestGap
    intervals : tuple of Interval
        Ranked by share, largest first.
    windows : dict of str to dict
        Rating window label (``"0-60"``) -> ``{"tests": {id: scores}, "ranking": [...]}``.
    regimes : tuple of Regime
        Ranked by mean squared bias, largest first.
    total_sq_gap : float
        Sum over tests and branches of the integral of the squared latent mean, (m/s^2)^2 m.
    """

    k: int
    k_rule: str
    bic: dict
    s_grid: np.ndarray
    v0_grid: np.ndarray
    map_mean: np.ndarray
    map_std: np.ndarray
    map_significant: np.ndarray
    map_covered: np.ndarray
    tests: tuple
    intervals: tuple
    windows: dict
    regimes: tuple
    total_sq_gap: float

    def to_json(self) -> dict:
        """JSON-ready dict (``regions`` of diagnosis.json): units in the key names, ms, g, mph."""
        return {
            "bias_model": {"inputs": "paper", "k": self.k, "k_rule": self.k_rule,
                           "bic": {str(k): round(v, 3) for k, v in self.bic.items()},
                           "n_clusters": len(self.regimes)},
            "significance": {"band": "95 % latent (no nugget)", "z": Z95,
                             "floor_fraction_of_peak": A0, "min_run_fraction": MIN_RUN,
                             "merge_gap_fraction": MERGE_GAP},
            "total_sq_gap_g2m": self.total_sq_gap / G0**2,
            "intervals": [_interval_json(i, rank) for rank, i in enumerate(self.intervals, start=1)],
            "windows": {label: _window_json(w) for label, w in self.windows.items()},
            "regimes": [_regime_json(r, rank) for rank, r in enumerate(self.regimes, start=1)],
            "tests": [_test_json(t) for t in self.tests],
        }


def locate_gap(campaign: Campaign, surrogate: CAESurrogate | None = None, k: int | None = None,
               random_state: int = 0, windows_ms=((0, 20), (0, 40), (0, 60))) -> GapMap:
    """Locate the CAE-vs-test gap of a campaign (all tests, paper inputs, companion CAE runs).

    Parameters
    ----------
    campaign : Campaign
        At least two tests and some CAE runs.
    surrogate : CAESurrogate, optional
        Fitted on the campaign's CAE runs (fitted here, seeded by ``random_state``, if not given).
    k : int, optional
        Mixture components; default the BIC-best of 1-3 (:func:`mixture_bic_k`).
    random_state : int
        Seeds the surrogate, the mixture and the GPs.
    windows_ms : sequence of (float, float)
        ISO/TS 18571 rating windows in ms for the sub-score breakdown.

    Returns
    -------
    GapMap

    Raises
    ------
    InputError
        Fewer than two tests, no CAE runs, a bad ``k`` or window.
    """
    _check_campaign(campaign)
    windows = _check_windows(windows_ms)
    if surrogate is None:
        surrogate = CAESurrogate(random_state=random_state).fit(campaign)
    data = bias_data(campaign, campaign.tests, "paper", surrogate=surrogate, use_companion=True).loading
    bic = {}
    if k is None:
        k, bic = mixture_bic_k(data.X, random_state)
    config = MethodConfig(k=k, inputs="paper", use_companion=True, random_state=random_state,
                          estimate_scatter=False)  # significance: the latent band
    model = fit_model(campaign, config, surrogate=surrogate)
    tests = tuple(_test_gap(campaign, model, t) for t in campaign.tests)
    total = sum(_sq_mass(p, None, -np.inf, np.inf) for t in tests for p in t.profiles.values())
    intervals = tuple(sorted(_intervals(tests, total), key=lambda i: -i.share))
    grid = _bias_map(model, tests)
    return GapMap(k=int(k), k_rule="given" if not bic else "min BIC of the loading-branch mixture, K in 1-3",
                  bic=bic, **grid, tests=tests, intervals=intervals,
                  windows={label: _subscore_summary({t.test_id: _window_subscores(t, *w) for t in tests})
                           for label, w in windows.items()},
                  regimes=_regimes(model, data), total_sq_gap=float(total))


def mixture_bic_k(X, random_state: int = 0, candidates=K_CANDIDATES) -> tuple[int, dict]:
    """How many clusters the gap map's bias inputs form: the K of a mixture alone by BIC.

    A mixture of the same form as :class:`crashfuse.method.mixture.GMMGPBias`'s (full covariance, 5
    initialisations, covariance floor 1e-3) on its clustering view (standardised inputs), seeded
    with ``random_state`` as given and without its small-cluster merging, so the K chosen here is a
    model-selection reading, not the clusters the bias model then fits; candidates above the number
    of points are skipped. It fits no GP and looks at no held-out test: the method's default K,
    how well the whole bias model predicts a test it did not see, is the ``auto`` model's
    (:func:`crashfuse.method.selection.choose`).

    Parameters
    ----------
    X : ndarray, shape (n, d)
        Loading-branch bias inputs of the training tests (SI).
    random_state : int
    candidates : sequence of int

    Returns
    -------
    k : int
        The candidate with the smallest BIC.
    bic : dict of int to float
    """
    C = StandardScaler().fit_transform(X)
    bic = {int(c): float(GaussianMixture(c, covariance_type="full", n_init=5, reg_covar=1e-3,
                                         random_state=random_state).fit(C).bic(C))
           for c in candidates if c <= len(C)}
    return min(bic, key=bic.get), bic


# ----------------------------------------------------------------------------- inputs
def _check_campaign(campaign: Campaign) -> None:
    if len(campaign.tests) < 2:
        raise InputError(f"expected at least two tests to locate a gap, got {len(campaign.tests)}",
                         campaign.root, "source")
    if not campaign.cae:
        raise InputError("the campaign has no CAE runs: there is no CAE model to compare the tests with",
                         campaign.root, "source")


def _check_windows(windows_ms) -> dict[str, tuple[float, float]]:
    """Rating windows by label (``"0-60"``) in s; InputError unless each is 0 <= start < end ms."""
    out = {}
    for w in windows_ms:
        try:
            start, end = (float(v) for v in w)
        except (TypeError, ValueError):
            start, end = np.nan, np.nan
        if not (0 <= start < end):
            raise InputError(f"expected windows (start_ms, end_ms) with 0 <= start < end, got {w!r}",
                             field="windows_ms")
        out[f"{start:g}-{end:g}"] = (start * MS, end * MS)
    return out


def _condition(pulse) -> Condition:
    return Condition(pulse.v0, pulse.front_weight, pulse.rear_weight, pulse.meta.get("powertrain"),
                     pulse.meta.get("drive"))


# --------------------------------------------------------------------- per-test bias
def _test_gap(campaign: Campaign, model: FittedModel, test_id: str) -> TestGap:
    """Bias profiles of one test along its branches, and its test and CAE pulses."""
    test = campaign.pulses[test_id].after_contact()
    cond = _condition(test)
    curve = model.cae_curve(cond)
    br = displacement_branches(test)
    reach = {"loading": min(br.loading.x[-1], curve.s[-1])}
    if br.unloading is not None and curve.u is not None and br.unloading.x.size >= 2:
        reach["unloading"] = br.unloading.x[-1]  # CAE unloading is 0 after separation: covers any u
    branches = {"loading": br.loading, "unloading": br.unloading}
    floor = A0 * float(np.abs(test.decel).max())
    profiles = {b: _profile(model, b, cond, branches[b], r, floor) for b, r in reach.items()
                if model.bias_.get(b) is not None}
    companion = campaign.companion(test_id)
    if companion is not None:
        cae_time, cae_decel, source = companion.time, companion.decel, companion.run_id
    else:
        traj = curve.rollout(test.dt, test.time.size - 1)
        cae_time, cae_decel, source = traj.time, traj.decel[0], "surrogate"
    return TestGap(test_id, test.v0, test.front_weight, test.rear_weight, profiles, test.time, test.decel,
                   cae_time, cae_decel, source)


def _profile(model: FittedModel, branch: str, cond: Condition, own: Branch, reach: float,
             floor: float) -> Profile:
    """Latent bias along ``[0, reach]`` at the test's condition, with its significant runs."""
    x = np.linspace(0.0, reach, N_PROFILE)
    mean, std = model.bias_[branch].predict(model.features(branch, x, None, cond), return_std=True)
    return Profile(x, mean, std, _significant_runs(mean, std, floor), np.interp(x, own.x, own.time))


def _significant(mean, std, floor):
    """Band excludes zero and the mean exceeds the practical floor (m/s^2)."""
    return np.abs(mean) > np.maximum(Z95 * std, floor)


def _significant_runs(mean: np.ndarray, std: np.ndarray, floor: float) -> np.ndarray:
    """Significant points (:func:`_significant`) in same-sign runs of at least ``MIN_RUN`` of the grid."""
    sign = np.sign(mean) * _significant(mean, std, floor)
    keep = np.zeros(mean.size, bool)
    for lo, hi, _ in _runs(sign):
        keep[lo:hi] = (hi - lo) >= max(2, MIN_RUN * (mean.size - 1) + 1)
    return keep


def _runs(sign: np.ndarray) -> list[tuple[int, int, int]]:
    """Maximal runs ``[lo, hi)`` of equal non-zero sign, with that sign."""
    edges = np.flatnonzero(np.diff(sign)) + 1
    starts, ends = np.r_[0, edges], np.r_[edges, sign.size]
    return [(int(a), int(b), int(sign[a])) for a, b in zip(starts, ends) if sign[a] != 0]


def _sq_mass(p: Profile, sign, lo: float, hi: float) -> float:
    """Integral of mean^2 over ``[lo, hi]`` where the mean has ``sign`` (any if None), (m/s^2)^2 m."""
    inside = (p.x >= lo) & (p.x <= hi)
    if sign is not None:
        inside &= np.sign(p.mean) == sign
    return float(np.trapezoid(np.where(inside, p.mean**2, 0.0), p.x))


# ----------------------------------------------------------------------- intervals
def _intervals(tests: tuple, total: float) -> list[Interval]:
    """Per branch and sign, every test's significant runs merged across tests."""
    out = []
    for branch in BRANCHES:
        profiles = {t.test_id: t.profiles[branch] for t in tests if branch in t.profiles}
        if not profiles:
            continue
        tol = MERGE_GAP * max(p.x[-1] for p in profiles.values())
        for sign in (1, -1):
            runs = [(p.x[a], p.x[b - 1], tid) for tid, p in profiles.items()
                    for a, b, s in _runs(np.sign(p.mean) * p.significant) if s == sign]
            out += [_interval(branch, sign, group, tests, total) for group in _merge(runs, tol)]
    return out


def _merge(runs: list, tol: float) -> list[list]:
    """Group ``(lo, hi, test)`` runs whose spans overlap or lie within ``tol`` of each other."""
    groups = []
    for run in sorted(runs):
        if groups and run[0] <= max(r[1] for r in groups[-1]) + tol:
            groups[-1].append(run)
        else:
            groups.append([run])
    return groups


def _interval(branch: str, sign: int, group: list, tests: tuple, total: float) -> Interval:
    lo, hi = min(r[0] for r in group), max(r[1] for r in group)
    mass = sum(_sq_mass(t.profiles[branch], sign, lo, hi) for t in tests if branch in t.profiles)
    windows = {t.test_id: _time_window(t.profiles[branch], lo, hi) for t in tests
               if branch in t.profiles and t.profiles[branch].x[-1] >= lo}
    x_peak, core = _concentration([t.profiles[branch] for t in tests if branch in t.profiles], sign, lo, hi)
    support = tuple(sorted({r[2] for r in group}))
    scores = _subscore_summary({t.test_id: _window_subscores(t, *windows[t.test_id])
                                for t in tests if t.test_id in support})
    return Interval(branch, float(lo), float(hi), sign, mass / total if total > 0 else 0.0, x_peak, core, support,
                    windows, scores)


def _concentration(profiles: list, sign: int, lo: float, hi: float) -> tuple[float, tuple]:
    """Peak and middle half of the same-sign squared mean summed over tests, on ``[lo, hi]`` (m)."""
    x = np.linspace(lo, hi, N_PROFILE)
    density = sum(np.where((x <= p.x[-1]) & (np.sign(np.interp(x, p.x, p.mean)) == sign),
                           np.interp(x, p.x, p.mean) ** 2, 0.0) for p in profiles)
    cum = np.r_[0.0, np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(x))]
    if cum[-1] <= 0:
        return float(x[np.argmax(density)]), (float(lo), float(hi))
    return float(x[np.argmax(density)]), tuple(float(np.interp(q * cum[-1], cum, x)) for q in (0.25, 0.75))


def _time_window(p: Profile, lo: float, hi: float) -> tuple[float, float]:
    """Times (s) the test's pulse spends in ``[lo, hi]`` of the branch (monotonic in time)."""
    return float(np.interp(lo, p.x, p.time)), float(np.interp(min(hi, p.x[-1]), p.x, p.time))


# ----------------------------------------------------------------------- sub-scores
def _window_subscores(t: TestGap, start: float, end: float) -> dict | None:
    """ISO/TS 18571 CAE-vs-test scores in ``[start, end]`` s, or None if shorter than 1 ms or uncovered."""
    covered = max(t.time[0], t.cae_time[0]) <= start and min(t.time[-1], t.cae_time[-1]) >= end
    if not covered or end - start < (ISO_MIN_SAMPLES - 1) * ISO_DT:
        return None
    return iso_score(t.time, t.decel, t.cae_time, t.cae_decel, start, end)


def _subscore_summary(scores: dict) -> dict:
    """Per test: scores and the sub-score carrying the gap; overall: sub-scores ranked by mean deficit.

    The deficit of sub-score k is ``w_k (1 - score_k)`` with the overall rating's weights, so the
    deficits of a test add up to ``1 - overall``.
    """
    rated = {tid: s for tid, s in scores.items() if s is not None}
    per_test = {tid: {**s, "carrier": max(SUBSCORES, key=lambda k: WEIGHTS[k] * (1 - s[k]))}
                for tid, s in rated.items()}
    mean = {k: float(np.mean([WEIGHTS[k] * (1 - s[k]) for s in rated.values()])) if rated else None
            for k in SUBSCORES}
    ranking = sorted((k for k in SUBSCORES if mean[k] is not None), key=lambda k: -mean[k])
    return {"tests": per_test, "mean_deficit": mean, "ranking": ranking,
            "unrated": sorted(tid for tid, s in scores.items() if s is None)}


# ------------------------------------------------------------------------ bias map
def _bias_map(model: FittedModel, tests: tuple) -> dict:
    """Loading-branch latent bias on speeds x displacements, axle masses those of the tests at each speed.

    Per test speed the mean over its tests (reach, peak: the largest), linear in between: at the
    campaign's mean masses the GP sits off its data at most speeds (``docs/diagnosis-gap.md``).
    """
    v0s = np.array([t.v0 for t in tests])
    speeds = np.unique(v0s)

    def at_speed(values, agg):
        values = np.asarray(values)
        return np.interp(v0_grid, speeds, [agg(values[v0s == v]) for v in speeds])

    v0_grid = np.linspace(speeds[0], speeds[-1], MAP_SHAPE[0])
    reach = at_speed([t.profiles["loading"].x[-1] for t in tests], np.max)
    s_grid = np.linspace(0.0, reach.max(), MAP_SHAPE[1])
    masses = zip(at_speed([t.front_weight for t in tests], np.mean), at_speed([t.rear_weight for t in tests], np.mean))
    X = np.vstack([model.features("loading", s_grid, None, Condition(v, wf, wr))
                   for v, (wf, wr) in zip(v0_grid, masses)])
    mean, std = (a.reshape(MAP_SHAPE) for a in model.bias_["loading"].predict(X, return_std=True))
    floor = A0 * at_speed([np.abs(t.decel).max() for t in tests], np.max)
    return dict(s_grid=s_grid, v0_grid=v0_grid, map_mean=mean, map_std=std,
                map_significant=_significant(mean, std, floor[:, None]),
                map_covered=s_grid[None, :] <= reach[:, None])


# ------------------------------------------------------------------------- regimes
def _regimes(model: FittedModel, data) -> tuple:
    """The loading model's clusters with their speed and crush ranges, tests and mean squared bias."""
    est = model.bias_["loading"]
    labels = np.argmax(est.predict_responsibilities(data.X), axis=1)  # the 'select' rule's GP
    out = []
    for g in range(len(est.gps_)):
        inside = labels == g
        if not inside.any():
            continue
        groups = data.groups[inside]
        tests = {str(t): float(np.sum(groups == t) / np.sum(data.groups == t))
                 for t in dict.fromkeys(groups)}
        X = data.X[inside]
        out.append(Regime(g, float(X[:, 1].min()), float(X[:, 1].max()), float(X[:, 0].min()),
                          float(X[:, 0].max()), tests, float(np.mean(data.y[inside] ** 2)), int(inside.sum())))
    return tuple(sorted(out, key=lambda r: -r.mean_sq_bias))


# -------------------------------------------------------------------------- JSON
def _interval_json(i: Interval, rank: int) -> dict:
    return {"rank": rank, "branch": i.branch, "x_lo_m": i.x_lo, "x_hi_m": i.x_hi, "x_peak_m": i.x_peak,
            "core_lo_m": i.core[0], "core_hi_m": i.core[1], "direction": _direction(i.sign), "share": i.share,
            "tests": list(i.tests),
            "windows": [{"test_id": tid, "t_lo_ms": lo / MS, "t_hi_ms": hi / MS, "significant": tid in i.tests}
                        for tid, (lo, hi) in i.windows.items()],
            "subscores": _window_json(i.subscores)}


def _window_json(w: dict) -> dict:
    return {"ranking": w["ranking"], "mean_deficit": w["mean_deficit"], "unrated": w["unrated"],
            "tests": {tid: {k: s[k] for k in ("overall", *SUBSCORES, "carrier")} for tid, s in w["tests"].items()}}


def _regime_json(r: Regime, rank: int) -> dict:
    return {"rank": rank, "cluster": r.cluster, "v0_lo_mps": r.v0_lo, "v0_hi_mps": r.v0_hi,
            "v0_lo_mph": r.v0_lo / MPH, "v0_hi_mph": r.v0_hi / MPH, "s_lo_m": r.x_lo, "s_hi_m": r.x_hi,
            "tests": r.tests, "mean_sq_bias_g2": r.mean_sq_bias / G0**2, "n_points": r.n_points}


def _test_json(t: TestGap) -> dict:
    return {"test_id": t.test_id, "v0_mps": t.v0, "v0_mph": t.v0 / MPH, "cae": t.cae_source,
            "significant_fraction": {b: float(np.mean(p.significant)) for b, p in t.profiles.items()},
            "reach_m": {b: float(p.x[-1]) for b, p in t.profiles.items()},
            "significant_windows": [{"branch": b, "t_lo_ms": lo / MS, "t_hi_ms": hi / MS, "direction": _direction(sign)}
                                    for b, lo, hi, sign in t.significant_windows()]}


def _direction(sign: int) -> str:
    return "test above CAE" if sign > 0 else "test below CAE"
