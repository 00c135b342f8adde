"""The fitted model: CAE surrogate + one GMM-GP bias model per branch + its config; save and load.

A :class:`FittedModel` holds everything a prediction needs (:func:`crashfuse.method.rollout.predict`):
the CAE surrogate G_a, the companion CAE runs of the campaign's tests (for ``use_companion``),
the loading and unloading bias models, the training ranges (for extrapolation flags), the
:class:`crashfuse.method.config.MethodConfig`, the campaign's content hash and the crashfuse version.

Model (and shared surrogate) files hold data only (:mod:`crashfuse.io.persist`: a zip of a JSON
header and numpy arrays, checked by SHA-256): opening one runs no code from it. The header records
the kind, ``FORMAT`` of that kind and the crashfuse version; the classes the file may name are
:data:`crashfuse.method.files.TYPES`. :func:`load_model` / :func:`load_surrogate` refuse another
kind, another format version, an older pickle file or a tampered file, and name the file.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path

import numpy as np

import crashfuse
from crashfuse.gp.kriging import SEED_MAX
from crashfuse.method.mixture import GMMGPBias, TooFewPointsError
from crashfuse.method.onset import ONSET_WINDOW, SHRINK_WIDTH, OnsetCorrectedBias
from crashfuse.signals.dynamics import Trajectory
from crashfuse.errors import InputError
from crashfuse.io import persist
from crashfuse.io.campaign import Campaign
from crashfuse.method.chain import MountResonance, body_campaign
from crashfuse.method.config import MethodConfig
from crashfuse.method.effect_fit import faster_curve
from crashfuse.method.hybrid import AUTO, PhysicsFirst, fit_physics
from crashfuse.method.projection import (BRANCHES, CAE_COL, BiasData, bias_data, bias_inputs, cae_curve,
                                         column_velocity, nominal_time, training_test)
from crashfuse.method.surrogate import CAECurve, CAESurrogate
from crashfuse.signals.domain import displacement_branches, rebound_work

# File format version per kind, bumped when that kind's objects change their attributes (older files
# are refused: refit); a change to one kind's objects leaves the other's files valid.
FORMAT = {"model": 13, "surrogate": 2}
# What a user does about a file of another format.
_REFIT = {"model": "refit with `crashfuse fit`", "surrogate": "refit with `crashfuse prepare`"}
CONDITION_COLUMNS = ("v0", "front_weight", "rear_weight")
_MATCH_RTOL = 1e-6  # a condition "is" a test's when v0 and both masses agree to this
_REACH_TOL = 0.02  # crush or rebound up to 2 % beyond the bias data is not flagged (thinning, rounding)
STATE_BINS = 40  # branch-coordinate bins of the joint (x, v) coverage table
STATE_V_TOL = 0.02  # velocity slack of that table, as a fraction of the largest |v| in the data
STATE_FRACTION = 0.05  # flag when more than this fraction of the mean path lies outside it


@dataclasses.dataclass(frozen=True)
class Condition:
    """An impact condition in SI (speed m/s, axle masses kg) with optional labels."""

    v0: float
    front_weight: float
    rear_weight: float
    powertrain: str | None = None
    drive: str | None = None

    def array(self) -> np.ndarray:
        """``[v0, front_weight, rear_weight]``, shape (3,)."""
        return np.array([self.v0, self.front_weight, self.rear_weight])


@dataclasses.dataclass
class FittedModel:
    """Everything a bias-corrected prediction needs (see :func:`fit_model`).

    Attributes
    ----------
    surrogate : CAESurrogate
        Fitted on the campaign's CAE runs only.
    bias_ : dict of str to GMMGPBias, OnsetCorrectedBias or None
        Per branch (the onset correction wraps the loading branch's model); None where the
        training tests gave no points on that branch (zero bias).
    config : MethodConfig
        The settings of the fit (input-mode defaults resolved).
    holdout : list of str
        run_ids of the tests kept out of the bias data, sorted.
    columns : dict of str to tuple of str
        Bias input columns per branch, in order (:func:`crashfuse.method.projection.bias_columns`).
    training_tests : list of str
        run_ids of the fold's training tests.
    groups : dict of str to list of str
        Per branch, the tests that actually contributed bias points (a subset of
        ``training_tests``; never the holdout).
    missing : dict of str to str
        ``"<test>/<branch>"`` -> why that test gave no bias data there.
    ranges : dict
        ``condition``: (lo, hi) arrays of [v0, w_f, w_r] over the training tests; ``x_max`` per
        branch: the largest branch coordinate in the bias data (m); ``cae_condition``: (lo, hi) of
        the CAE runs' conditions (the surrogate's range); ``state`` (``state`` inputs only): per
        branch, the joint (x, v) coverage of the bias data that flags a rollout leaving it;
        ``bias_rms`` per branch: the rms of the training tests' bias in m/s^2 (the learnt target
        times its scale), which bounds the band (:meth:`bias_spread`); ``target_rms`` per branch: the rms
        of the learnt target itself, the band's bound in its units (:meth:`target_spread`);
        ``bias_range`` per branch: the learnt target's span over the training tests' points, 0
        included (:meth:`bias_range`).
    companions : list of (Condition, Pulse)
        Every test's condition and its companion CAE run.
    categories : dict of str to list of str
        Label levels of the one-hot extra inputs (empty unless ``extra_inputs``).
    campaign_hash : str
        :meth:`Campaign.content_hash` of the campaign fitted on.
    version : str
        crashfuse version that fitted it.
    physics : PhysicsFirst or None
        The physics-first hybrid's effect laws (``config.effects``), fitted on the training tests;
        every CAE curve of the model is then CAE + effects (:meth:`cae_curve`).
    fit_seconds : float
        Wall time of the fit (the surrogate's excluded when it was given).
    fit_started : float
        When the fit started, UNIX seconds (0: unknown): a tracked fold run starts then.
    surrogate_file : str or None
        Where the surrogate lives when the file was saved without it (:meth:`save`).
    chain : MountResonance or None
        The tests' measurement chain (``config.chain``), fitted on the training tests and their
        companion runs: the bias is learnt from the tests' body decelerations (their records with the
        mount taken out), and a rollout is read through it (:func:`crashfuse.method.rollout.predict`).
    """

    surrogate: CAESurrogate
    bias_: dict
    config: MethodConfig
    holdout: list
    columns: dict
    training_tests: list
    groups: dict
    missing: dict
    ranges: dict
    companions: list
    categories: dict
    campaign_hash: str
    version: str = crashfuse.__version__
    physics: PhysicsFirst | None = None
    fit_seconds: float = 0.0
    fit_started: float = 0.0
    surrogate_file: str | None = None
    chain: MountResonance | None = None

    @property
    def inputs(self) -> str:
        """Bias input mode: ``paper`` or ``state``."""
        return self.config.inputs

    @property
    def relative(self) -> bool:
        """True if the bias models learn the bias relative to the CAE deceleration."""
        return self.config.target == "relative"

    def all_rows_gps(self) -> dict:
        """Per branch, the GP on every bias row that another K's fit of the same fold can reuse as its
        pooled GP (``fit_model(..., pooled=...)``); branches without one are left out."""
        gps = {b: est.all_rows_gp() for b, est in self.bias_.items() if est is not None}
        return {b: gp for b, gp in gps.items() if gp is not None}

    def condition(self, v0, front_weight, rear_weight, powertrain=None, drive=None) -> Condition:
        """A validated :class:`Condition` (SI).

        Raises
        ------
        InputError
            Non-positive or non-finite numbers; a label missing or unknown where the model uses it.
        """
        for name, val in zip(CONDITION_COLUMNS, (v0, front_weight, rear_weight)):
            if isinstance(val, bool) or not isinstance(val, (int, float, np.number)) or not (np.isfinite(val) and val > 0):
                raise InputError(f"expected a positive finite number (SI), got {val!r}", field=name)
        for name, levels in self.categories.items():
            val = {"powertrain": powertrain, "drive": drive}[name]
            if str(val) not in levels:
                raise InputError(f"this model uses {name} as an input: expected one of {levels}, got {val!r}",
                                 field=name)
        return Condition(float(v0), float(front_weight), float(rear_weight), powertrain, drive)

    def features(self, branch: str, x, v, cond: Condition, curve=None) -> np.ndarray:
        """Bias inputs at branch coordinates ``x`` (m) and velocities ``v`` (m/s); a ``cae_decel_g`` input
        is the deceleration of :meth:`cae_curve` at ``x`` (its loading or unloading branch), or of ``curve``,
        that CAE curve already at hand (anything with ``loading`` and ``unloading``: the rollout's table).

        Parameters
        ----------
        branch : {"loading", "unloading"}
        x, v : ndarray, shape (n,)
        cond : Condition
        curve : CAECurve, optional
            The CAE curve of ``cond`` when the caller has it (only a ``cae_decel_g`` input reads it).

        Returns
        -------
        ndarray, shape (n, len(columns[branch]))
            In the training columns' order (:func:`crashfuse.method.projection.bias_columns`).
        """
        a_cae = None
        if CAE_COL in self.columns[branch]:
            curve = self.cae_curve(cond) if curve is None else curve
            a_cae = curve.loading(x) if branch == "loading" else curve.unloading(x)
        return bias_inputs(self.columns[branch], x, v, cond.v0, cond.front_weight, cond.rear_weight,
                           cond.powertrain, cond.drive, a_cae)

    def x_max(self, branch: str) -> float:
        """Largest branch coordinate (m) in the bias data of ``branch`` (0 without data)."""
        return float(self.ranges["x_max"].get(branch, 0.0))

    def bias_spread(self, branch: str) -> float:
        """Rms of the training tests' bias on ``branch`` (m/s^2), the bound on a relative target's band
        (:func:`crashfuse.method.rollout.predict`); ``inf`` for a file fitted before it was stored."""
        return float(self.ranges.get("bias_rms", {}).get(branch, np.inf))

    def target_spread(self, branch: str) -> float:
        """Rms of the training tests' learnt target on ``branch`` (its units: m/s^2, or dimensionless for a
        relative target), a bound on the band; ``inf`` for a file fitted before it was stored."""
        return float(self.ranges.get("target_rms", {}).get(branch, np.inf))

    def bias_range(self, branch: str) -> tuple[float, float]:
        """(lo, hi): the learnt target's span over the training tests' bias points of ``branch``, 0 (no
        correction) included; (-inf, inf) for a file fitted before it was stored."""
        lo, hi = self.ranges.get("bias_range", {}).get(branch, (-np.inf, np.inf))
        return float(lo), float(hi)

    def rebound_range(self) -> tuple[float, float]:
        """(lo, hi): the rebound speed over the CAE's that the training tests span, 1 included (a record
        ending mid-spring-back counts as a lower bound: :func:`_rebound_ratios`); (0, inf) without tests
        reaching their turnaround, or for a file fitted before it was stored."""
        ratios = self.ranges.get("rebound_ratio")
        if not ratios:
            return 0.0, np.inf
        return min(1.0, min(ratios)), max(1.0, max(ratios))

    def cae_curve(self, cond: Condition) -> CAECurve:
        """The CAE curve at ``cond``: the companion run where ``use_companion`` and one matches, else the
        surrogate; with the hybrid's effect laws added (:attr:`physics`).

        Raises
        ------
        InputError
            If the surrogate would extrapolate (condition outside the CAE runs' range) and no
            companion run matches.
        """
        pulse = self._companion(cond) if self.config.use_companion else None
        if pulse is None:
            curve = self._surrogate_curve(cond, check=True)
        else:
            # Built as the training data built it (projection.cae_curve): a companion that does not reach
            # separation in its record borrows the surrogate's unloading branch.
            curve = CAECurve.from_pulse(pulse, unloading_from=self._surrogate_curve(cond, False))
        return self._with_effects(curve, cond)

    def _with_effects(self, curve: CAECurve, cond: Condition) -> CAECurve:
        if self.physics is None or not self.physics.effects:
            return curve
        faster = faster_curve(self.surrogate, cond.v0, cond.front_weight, cond.rear_weight, cond.powertrain,
                              cond.drive)
        return self.physics.curve(curve, cond.front_weight + cond.rear_weight, cond.powertrain, faster,
                                  cond.front_weight, cond.rear_weight)

    def _surrogate_curve(self, cond: Condition, check: bool) -> CAECurve:
        lo, hi = self.ranges["cae_condition"]
        x = cond.array()
        outside = (x < lo * (1 - _MATCH_RTOL)) | (x > hi * (1 + _MATCH_RTOL))
        if check and outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise InputError(f"{x[i]:.6g} is outside the CAE runs' range [{lo[i]:.6g}, {hi[i]:.6g}] (SI) and no "
                             f"companion CAE run matches this condition: the surrogate would extrapolate",
                             field=CONDITION_COLUMNS[i])
        return self.surrogate.curve(cond.v0, cond.front_weight, cond.rear_weight, cond.powertrain, cond.drive)

    def _companion(self, cond: Condition):
        for c, pulse in self.companions:
            if np.allclose(c.array(), cond.array(), rtol=_MATCH_RTOL, atol=0):
                return pulse
        return None

    def extrapolation(self, cond: Condition, mean_traj) -> dict:
        """Where the prediction leaves the bias data: condition columns, crush and rebound.

        Parameters
        ----------
        cond : Condition
        mean_traj : crashfuse.signals.dynamics.Trajectory
            The mean-function rollout (one sample).

        Returns
        -------
        dict of str to bool
            ``v0``, ``front_weight``, ``rear_weight``: outside the training tests' range;
            ``crush``: maximum crush beyond the loading bias data; ``rebound``: unloading travel
            beyond the unloading bias data; ``state`` (``state`` inputs only): more than
            ``STATE_FRACTION`` of the mean path's (x, v) points on either branch lie where no
            training test was (:func:`state_outside`) - per-column ranges miss a low speed at a
            large crush; ``any``.
        """
        flags = self.condition_outside(cond)
        contact = mean_traj.branch[0] == Trajectory.UNLOADING  # after separation u grows in free flight
        u = (mean_traj.s_max[0] - mean_traj.s[0])[contact]
        flags["crush"] = bool(mean_traj.s_max[0] > (1 + _REACH_TOL) * self.x_max("loading"))
        flags["rebound"] = bool(u.size and u.max() > (1 + _REACH_TOL) * self.x_max("unloading"))
        if "state" in self.ranges:
            flags["state"] = any(state_outside(self.ranges["state"][b], *mean_traj.on_branch(b)[1:]) > STATE_FRACTION
                                 for b in BRANCHES if self.ranges["state"].get(b) is not None)
        flags["any"] = any(flags.values())
        return flags

    def condition_outside(self, cond: Condition) -> dict:
        """Per condition column (``v0``, ``front_weight``, ``rear_weight``): whether ``cond`` lies outside
        the training tests' range."""
        lo, hi = self.ranges["condition"]
        x = cond.array()
        return {name: bool(x[i] < lo[i] * (1 - _MATCH_RTOL) or x[i] > hi[i] * (1 + _MATCH_RTOL))
                for i, name in enumerate(CONDITION_COLUMNS)}

    def nearest_inside(self, cond: Condition) -> Condition:
        """``cond`` with each condition column clipped into the training tests' range (itself inside it)."""
        lo, hi = self.ranges["condition"]
        return dataclasses.replace(cond, **dict(zip(CONDITION_COLUMNS, map(float, np.clip(cond.array(), lo, hi)))))

    def save(self, path: str | os.PathLike, surrogate_file: str | os.PathLike | None = None) -> None:
        """Write the model file atomically (:mod:`crashfuse.io.persist`, kind ``model``).

        With ``surrogate_file`` (the surrogate's own file, :func:`save_surrogate`) the model refers to it
        instead of holding a copy: a fold's model file is then kilobytes, not the surrogate's ~100 MB.
        """
        if surrogate_file is None:
            _save("model", self, path)
        else:
            _save("model", dataclasses.replace(self, surrogate=None, surrogate_file=str(surrogate_file)), path)


def load_model(path: str | os.PathLike, surrogate: CAESurrogate | None = None) -> FittedModel:
    """Read a model file written by :meth:`FittedModel.save`.

    Parameters
    ----------
    path : path-like
    surrogate : CAESurrogate, optional
        For a file saved without its surrogate: that surrogate (default: read from the file it names).

    Raises
    ------
    InputError
        Missing or unreadable file, not a crashfuse model file, another format version, an older
        pickle file, or a damaged or tampered file (a class outside the whitelist, an array that
        does not match its checksum); a referred surrogate that is missing or of another campaign.
    """
    model = _load("model", FittedModel, path)
    if model.surrogate is not None:
        return model
    if surrogate is None:
        if not model.surrogate_file or not Path(model.surrogate_file).is_file():
            raise InputError(f"the model refers to its CAE surrogate file {model.surrogate_file!r}, which is not "
                             f"there: pass it (--surrogate)", path, "surrogate")
        surrogate = load_surrogate(model.surrogate_file)
    if getattr(surrogate, "campaign_hash_", None) != model.campaign_hash:
        raise InputError("the CAE surrogate was fitted on another campaign than the model", path, "surrogate")
    return dataclasses.replace(model, surrogate=surrogate)


def save_surrogate(surrogate: CAESurrogate, path: str | os.PathLike) -> None:
    """Write a fitted CAE surrogate atomically (kind ``surrogate``, shared by evaluation folds)."""
    _save("surrogate", surrogate, path)


def load_surrogate(path: str | os.PathLike) -> CAESurrogate:
    """Read a surrogate file written by :func:`save_surrogate` (InputError as :func:`load_model`)."""
    return _load("surrogate", CAESurrogate, path)


def _save(kind: str, obj, path) -> None:
    from crashfuse.method.files import TYPES  # files.py lists this module's classes: imported when used

    persist.save(path, kind, FORMAT[kind], obj, TYPES)


def _load(kind: str, cls, path):
    from crashfuse.method.files import TYPES

    obj = persist.load(path, kind, FORMAT[kind], TYPES, _REFIT[kind])
    if not isinstance(obj, cls):
        raise InputError(f"not a crashfuse {kind} file (it holds a {type(obj).__name__})", path)
    return obj


def fit_model(campaign: Campaign, config: MethodConfig, *, holdout=None,
              surrogate: CAESurrogate | None = None, physics: PhysicsFirst | None = None,
              pooled: dict | None = None, chain: MountResonance | None = None) -> FittedModel:
    """Fit the CAE surrogate (unless given) and one GMM-GP bias model per branch.

    Parameters
    ----------
    campaign : Campaign
        Tests and CAE runs (SI, CFC 60 as read).
    config : MethodConfig
        The settings: K, input mode, bias target, trend, GMMGPBias settings ... Clusters the data
        cannot support (fewer points than :class:`GMMGPBias` needs) are merged into their nearest
        neighbour: the model keeps fewer GPs (``len(bias_['loading'].gps_)``), it does not fail.
    holdout : str or sequence of str, optional
        Test run_id(s) kept out of the bias data (a leave-one-test-out fold).
    surrogate : CAESurrogate, optional
        Already fitted on this campaign's CAE runs (shared across folds; it sees no test data).
        Otherwise fitted here, seeded with ``config.random_state`` as is, as
        :func:`crashfuse.evaluation.loto.evaluate` and ``crashfuse prepare`` do (so fitting with
        holdout T is T's fold).
    physics : PhysicsFirst, optional
        The effect laws of ``config.effects`` already fitted on this fit's training tests
        (:func:`crashfuse.method.hybrid.fit_physics`; shared by the folds of every K and input
        mode that hold out the same test). Otherwise fitted here when ``config.effects`` names any.
    pooled : dict of str to KrigingGP, optional
        Per branch, the pooled GP already fitted: :meth:`FittedModel.all_rows_gps` of another K's fit
        with the same holdout and settings (the same fit, so the result is identical and its cost saved).
    chain : MountResonance, optional
        With ``config.chain``, the measurement chain already fitted on this fit's training tests
        (:attr:`FittedModel.chain` of another K's fit with the same holdout); otherwise fitted here.

    Returns
    -------
    FittedModel

    Raises
    ------
    InputError
        No CAE runs; an unknown or non-test holdout; no training test left; a branch with fewer
        bias points than the model has parameters; a rate law without CAE runs at several speeds.
    ValueError
        ``physics`` fitted on other tests or other effects than this fit's; a ``pooled`` GP that is not
        this fit's.
    """
    t0, started = time.perf_counter(), time.time()
    if not isinstance(config, MethodConfig):
        raise TypeError(f"expected a MethodConfig, got {type(config).__name__}")
    if not campaign.cae:
        raise InputError("the campaign has no CAE runs: the method corrects a CAE model", campaign.root, "source")
    held = holdout_tests(campaign, holdout)
    train = [t for t in campaign.tests if t not in held]
    if not train:
        raise InputError("no training test left after the holdout", campaign.root, "holdout")
    if surrogate is None:
        surrogate = CAESurrogate(random_state=config.random_state).fit(campaign)
    if physics is None and config.effects:
        physics = fit_physics(campaign, train, config.effects, surrogate)
    if physics is not None and (physics.tests != sorted(train) or config.effects not in (AUTO, physics.effects)):
        raise ValueError(f"physics fitted on {physics.tests} with {physics.effects}, this fit trains on "
                         f"{sorted(train)} with {config.effects}")
    if not config.chain:
        chain = None
    elif chain is None:
        chain = fit_chain(campaign, train)
    curves = training_curves(campaign, train, surrogate, physics)
    data = training_data(campaign, train, config, surrogate, physics, curves, chain)
    seeds = np.random.RandomState(config.random_state).randint(SEED_MAX, size=len(BRANCHES))
    pooled = pooled or {}
    bias = {b: _fit_branch(data, b, config, int(seed), campaign.root, pooled.get(b))
            for b, seed in zip(BRANCHES, seeds)}
    return FittedModel(
        surrogate=surrogate, bias_=bias, config=config, holdout=sorted(held),
        columns={b: data.branch(b).columns for b in BRANCHES}, training_tests=train,
        groups={b: sorted(set(data.branch(b).groups)) for b in BRANCHES}, missing=dict(data.missing),
        ranges=_ranges(campaign, train, data, curves), companions=_companions(campaign),
        categories=dict(data.categories), campaign_hash=campaign.content_hash(), physics=physics,
        fit_seconds=time.perf_counter() - t0, fit_started=started, chain=chain,
    )


def fit_chain(campaign: Campaign, tests) -> MountResonance | None:
    """The tests' measurement chain fitted on ``tests`` and their companion CAE runs (on the test's times).

    None where none of ``tests`` names a companion run: the bias is then learnt against the surrogate's
    curves, and the chain is not fitted (a stated fallback, recorded as the model's ``chain``). None too
    where the fitted mount removes nothing of the difference (:attr:`MountResonance.removes_nothing`):
    tests that do not ring are read as they are.
    """
    pairs = []
    for t in tests:
        test, cae = training_test(campaign, t), campaign.companion(t)
        if cae is not None:
            pairs.append((test.time, test.decel, np.interp(test.time, cae.time, cae.decel)))
    chain = MountResonance().fit(pairs) if pairs else None
    return None if chain is None or chain.removes_nothing else chain


def training_data(campaign: Campaign, tests, config: MethodConfig, surrogate: CAESurrogate,
                  physics: PhysicsFirst | None = None, curves: dict | None = None,
                  chain: MountResonance | None = None) -> BiasData:
    """The bias data of ``tests`` as a fit with ``config`` learns them (each test with its companion run,
    plus the hybrid's effect laws where ``physics`` is given).

    Parameters
    ----------
    campaign : Campaign
    tests : sequence of str
        Test run_ids.
    config : MethodConfig
        Supplies the input mode, extra inputs, thinning, target, weights and velocity coordinate.
    surrogate : CAESurrogate
        The CAE curve of a test without a companion run.
    physics : PhysicsFirst, optional
        Effect laws added to every test's CAE curve (:meth:`FittedModel.cae_curve` does the same).
    curves : dict, optional
        :func:`training_curves` of these tests, when already at hand.
    chain : MountResonance, optional
        The tests' measurement chain: the bias is that of the tests' body decelerations
        (:func:`crashfuse.method.chain.body_campaign`).

    Returns
    -------
    BiasData
    """
    if chain is not None:
        campaign = body_campaign(campaign, chain, tests)
    return bias_data(campaign, tests, config.inputs, config.extra_inputs, config.n_grid, surrogate=surrogate,
                     use_companion=True, cae_curves=curves or training_curves(campaign, tests, surrogate, physics),
                     target=config.target, weights=config.weights, velocity=config.velocity,
                     cae_decel=config.cae_decel)


def training_curves(campaign: Campaign, tests, surrogate: CAESurrogate, physics: PhysicsFirst | None = None) -> dict:
    """The CAE curve each test's bias is measured against, by run_id: its companion run (else the
    surrogate's curve at its condition), plus the hybrid's effect laws where ``physics`` is given."""
    curves = {}
    for t in tests:
        p = training_test(campaign, t)
        curve = cae_curve(campaign, p, surrogate)
        if physics is not None and physics.effects:
            curve = physics.curve(curve, p.mass, p.meta.get("powertrain"),
                                  faster_curve(surrogate, p.v0, p.front_weight, p.rear_weight,
                                               p.meta.get("powertrain"), p.meta.get("drive")),
                                  p.front_weight, p.rear_weight)
        curves[t] = curve
    return curves


def holdout_tests(campaign: Campaign, holdout) -> set[str]:
    """The run_ids in ``holdout`` (None, one run_id or several) as a set; InputError if one is not a test."""
    held = set() if holdout is None else {holdout} if isinstance(holdout, str) else set(holdout)
    not_tests = sorted(held - set(campaign.tests))
    if not_tests:
        raise InputError(f"expected test run_ids to hold out, got {not_tests}", campaign.root, "holdout")
    return held


def _fit_branch(data: BiasData, branch: str, config: MethodConfig, seed: int, root, pooled_gp=None):
    """One branch's GMMGPBias (wrapped in the held-out shrinkage and the onset correction on the loading
    branch where the config asks; ``pooled_gp`` as :meth:`GMMGPBias.fit` takes it); None for an unloading branch without data
    (zero bias there)."""
    d = data.branch(branch)
    if d.y.size == 0 and branch == "unloading":
        return None
    est = GMMGPBias(n_clusters=config.k, assignment=config.assignment, random_state=seed,
                    **config.bias_params(d.columns))
    if (config.onset or config.shrink) and branch == "loading":
        est = OnsetCorrectedBias(base=est, time=functools.partial(nominal_time, d.columns),
                                 window=ONSET_WINDOW if config.onset else None,
                                 shrink_width=SHRINK_WIDTH if config.shrink else None)
    try:
        return est.fit(d.X, d.y, d.groups, pooled_gp=pooled_gp)
    except TooFewPointsError as err:  # too few points for K and the GP parameters
        raise InputError(f"{branch} branch, {d.y.size} bias points from {len(set(d.groups))} tests: {err}",
                         root, "k") from None


def _ranges(campaign: Campaign, train: list, data: BiasData, curves: dict) -> dict:
    conds = campaign.conditions.set_index("run_id")
    cols = ["v0_mps", "front_weight_kg", "rear_weight_kg"]
    tr, cae = conds.loc[train, cols].to_numpy(float), conds.loc[campaign.cae, cols].to_numpy(float)
    x_max = {b: float(data.branch(b).X[:, 0].max()) if data.branch(b).y.size else 0.0 for b in BRANCHES}
    out = {"condition": (tr.min(axis=0), tr.max(axis=0)), "cae_condition": (cae.min(axis=0), cae.max(axis=0)),
           "x_max": x_max, "bias_rms": {b: _bias_rms(data.branch(b)) for b in BRANCHES},
           "target_rms": {b: _target_rms(data.branch(b)) for b in BRANCHES},
           "bias_range": {b: _bias_range(data.branch(b)) for b in BRANCHES},
           "rebound_ratio": _rebound_ratios(campaign, curves)}
    if data.inputs == "state":
        out["state"] = {b: _state_table(data.branch(b)) if data.branch(b).y.size else None for b in BRANCHES}
    return out


def _rebound_ratios(campaign: Campaign, curves: dict) -> list:
    """Each training test's rebound speed over its CAE curve's (tests that reach the unloading).

    A record that ends while the spring-back still pushes gives its ratio so far, a lower bound: it may
    widen the span upwards only (at least 1). Left out, the slow tests whose held unloading outlasts their
    record left the span to the fast tests', and the rebound bound cut a slow test's correct rebound of
    three times the CAE's to 1.5 (docs/decisions.md, section 69).
    """
    out = []
    for test_id, curve in curves.items():
        unloading = displacement_branches(campaign.pulses[test_id]).unloading
        if unloading is None or curve.u is None or unloading.x.size < 2:
            continue
        work, peak = rebound_work(unloading.x, unloading.decel)
        cae_work = rebound_work(curve.u, curve.a_unloading)[0]
        if cae_work > 0:
            ratio = float(np.sqrt(work / cae_work))
            out.append(ratio if peak < unloading.x.size - 1 else max(ratio, 1.0))
    return out


def _bias_rms(d) -> float:
    """Rms of one branch's bias data in m/s^2 (0 without data)."""
    return float(np.sqrt(np.mean((d.y * d.scale) ** 2))) if d.y.size else 0.0


def _target_rms(d) -> float:
    """Rms of one branch's learnt target in its units (0 without data)."""
    return float(np.sqrt(np.mean(d.y**2))) if d.y.size else 0.0


def _bias_range(d) -> tuple[float, float]:
    """Span of one branch's learnt bias target with 0 included ((0, 0) without data)."""
    return float(d.y.min(initial=0.0)), float(d.y.max(initial=0.0))


def _state_table(d) -> tuple:
    """:func:`state_table` of one branch's bias data (velocity column back in m/s)."""
    return state_table(d.X[:, 0], column_velocity(d.columns[1], d.X[:, 1]))


def state_table(x, v, n_bins: int = STATE_BINS):
    """Joint coverage of the bias data: the velocity range seen in each branch-coordinate bin.

    Parameters
    ----------
    x, v : ndarray, shape (n,)
        Branch coordinate (m) and velocity (m/s) of the training rows.
    n_bins : int

    Returns
    -------
    edges : ndarray, shape (n_bins + 1,)
        Bin edges in m, from 0 to the largest x.
    v_lo, v_hi : ndarray, shape (n_bins,)
        Velocity range per bin widened by ``STATE_V_TOL`` of the largest |v| (empty bins:
        ``+inf, -inf``, so everything there is outside).
    """
    edges = np.linspace(0.0, float(np.max(x)), n_bins + 1)
    i = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n_bins - 1)
    v_lo, v_hi = np.full(n_bins, np.inf), np.full(n_bins, -np.inf)
    np.minimum.at(v_lo, i, v)
    np.maximum.at(v_hi, i, v)
    tol = STATE_V_TOL * float(np.max(np.abs(v)))
    return edges, v_lo - tol, v_hi + tol


def state_outside(table, x, v) -> float:
    """Fraction of (x, v) points outside the joint coverage ``table`` (:func:`state_table`).

    Points beyond the table's last edge count as outside (the crush flag covers them too).
    """
    if np.size(x) == 0:
        return 0.0
    edges, v_lo, v_hi = table
    i = np.searchsorted(edges, x, side="right") - 1
    inside = (i >= 0) & (i < len(v_lo)) | np.isclose(x, edges[-1])
    i = np.clip(i, 0, len(v_lo) - 1)
    inside &= (v >= v_lo[i]) & (v <= v_hi[i])
    return float(1.0 - inside.mean())


def _companions(campaign: Campaign) -> list:
    out = []
    for t in campaign.tests:
        pulse = campaign.companion(t)
        if pulse is not None:
            p = campaign.pulses[t]
            out.append((Condition(p.v0, p.front_weight, p.rear_weight, p.meta.get("powertrain"),
                                  p.meta.get("drive")), pulse))
    return out

