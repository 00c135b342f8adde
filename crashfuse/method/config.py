"""Every setting of a fit, typed: :class:`MethodConfig` and each input mode's defaults.

A config is frozen and plain (str, int, float, bool, None and tuples of them), so a model file can
store it and a fold JSON or MLflow run can log it. Bad values raise
:class:`crashfuse.errors.InputError` naming the setting (the field's own name: ``k``, ``inputs``,
``random_state`` ...; the command line maps it to its flag).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from crashfuse.errors import InputError
from crashfuse.method.hybrid import check_effects
from crashfuse.method.mixture import GMMGPBias
from crashfuse.method.projection import CAE_DECEL, INPUTS, TARGETS, VELOCITY, is_label

ASSIGNMENTS = ("select", "blend")  # cluster rules of GMMGPBias
TRENDS = ("zero", "constant", "linear")  # trends of KrigingGP
_THETA_MIN, _THETA_MAX = GMMGPBias().theta_bounds  # the bias model's own bounds on its GPs' theta
_NUGGET_MIN, _NUGGET_MAX = GMMGPBias().nugget_bounds  # ... and on their nugget

# The settings that depend on the input mode, and why each mode has its value.
MODE_DEFAULTS = {
    "paper": {
        "target": "absolute",  # as published: the GPs learn the bias in m/s^2
        "trend": "constant",  # as published: the GPs' constant level
        "pooled": False,  # as published: each cluster GP on its own points
        "onset": False,  # the paper inputs carry no velocity, hence no time since contact
        "shrink": False,  # as published: the GP mean as it is
        "use_companion": False,  # as published: a condition's CAE curve from the surrogate G_a
        "chain": False,  # as published: the bias against the CAE pulse as it is
        "theta_min": _THETA_MIN,  # the bias model's own bound: an input may drop out entirely
        "nugget_min": _NUGGET_MIN,  # the bias model's own bound: the GPs may interpolate the tests
        "cae_decel": "none",  # as published: the inputs [x, v0, w_f, w_r]
        "extra_inputs": False,  # as published: no labels among the inputs
    },
    "state": {
        # a rate effect scales the force, so the bias relative to the CAE deceleration; chosen by
        # grouped leave-one-test-out density on the training tests (docs/decisions.md)
        "target": "relative",
        # simple kriging (the Kennedy-O'Hagan zero-mean discrepancy): where no test informs the bias,
        # the correction fades to zero and the prediction to the CAE model's (docs/method-rollout.md, "Trend")
        "trend": "zero",
        # cluster GPs on the residual of one pooled GP: a sparse cluster falls back on the pooled
        # model, not on its few tests (docs/bias-model.md, "Pooled clusters")
        "pooled": True,
        # off: the onset transients locked in time are the mount's ringing, which the chain now carries; re-judged
        # with the chain, the correction moved `paper` by 0.011 at most and followed the noise controls' noise
        # at 0-20 ms (docs/decisions.md, section 79)
        "onset": False,
        # where the other tests' bias does not predict a left-out test's (bumps of one or two tests),
        # the mean defers to the CAE model: on 19 matrix campaigns of both worlds it lost fewer test-windows
        # to CAE, none more (docs/bias-model.md, "Held-out shrinkage"; decisions.md, section 40)
        "shrink": True,
        # a held-out test is predicted on its own CAE run, the one its CAE row scores: the fold then
        # measures the correction, not the surrogate's error there too (docs/decisions.md, section 39)
        "use_companion": True,
        # the tests ring on their accelerometer mount, locked in time, which the bias (learnt in crush)
        # cannot carry between speeds: the bias of the tests' body decelerations, the rollout read through
        # the mount (docs/decisions.md, sections 65-66)
        "chain": True,
        # the GPs' correlation lengths at most ~2.2 standard deviations of each input: fitted by likelihood
        # to smooth bias data (the body decelerations), unbounded lengths took a near-infinite variance and
        # a mean that swung to slow tests and late crush like a polynomial (docs/decisions.md, section 66)
        "theta_min": 0.1,
        # the GPs' noise at least 1 % of their variance: each test's own bias path (its scatter about the others)
        # is noise to the GP, not a function of the inputs. With the floor at 1e-8, a fit threaded that scatter along
        # each test's CAE deceleration at a nugget of 3e-6 and predicted a held-out control test wrong by 0.2-0.35 of
        # its deceleration (docs/decisions.md, sections 74-76)
        "nugget_min": 1e-2,
        # the CAE's deceleration is the unloading's stage (it falls monotonically to the CAE's separation):
        # without it the unloading GP told the tests apart by their speed and predicted no correction at a
        # held-out test; on loading it is not monotone and cost test-windows (docs/decisions.md, sections 38, 69)
        "cae_decel": "unloading",
        # the tests' powertrain and drive labels (one-hot) are inputs, their theta free of theta_min: where the
        # labels tell the tests' bias apart (an engine of one type striking earlier) the GP separates them,
        # elsewhere the likelihood lets them drop out (docs/decisions.md, section 78)
        "extra_inputs": True,
    },
}

# GMMGPBias settings a fit passes through; their defaults are the bias model's own.
BIAS_SETTINGS = ("n_restarts", "max_fit_points", "max_condition_points", "min_cluster_points",
                 "theta_max_candidates", "calibrate_variance", "estimate_scatter")
_BIAS_DEFAULTS = GMMGPBias().get_params()


@dataclasses.dataclass(frozen=True)
class MethodConfig:
    """The settings of one fit (:func:`crashfuse.method.model.fit_model`).

    ``target``, ``trend``, ``pooled``, ``onset``, ``shrink``, ``use_companion``, ``chain``, ``theta_min``,
    ``nugget_min``, ``cae_decel`` and ``extra_inputs`` left as None take the input mode's value (``MODE_DEFAULTS``),
    so a config always holds the values the fit used. To change the input mode of a config, build a new one
    (``dataclasses.replace`` keeps the old mode's values).

    Parameters
    ----------
    k : int
        Mixture components K of each branch's bias model (>= 1). Clusters the data cannot support
        are merged into their nearest neighbour: the model keeps fewer GPs, it does not fail.
    inputs : {"paper", "state"}
        Bias inputs ``[x, v0, w_f, w_r]`` or ``[x, v, v0, w_f, w_r]``.
    assignment : {"select", "blend"}
        Cluster rule of :class:`crashfuse.method.mixture.GMMGPBias`.
    extra_inputs : bool or None
        Append one-hot powertrain and drive to the bias inputs. Their ``theta`` is bounded below by the bias
        model's own bound, not ``theta_min``: a label cannot swing like a polynomial between tests, and the
        likelihood may drop it entirely.
    cae_decel : {"none", "unloading", "both"} or None
        The branches whose bias inputs end with the CAE deceleration at the bias point (g): the crush
        stage, and the force an additive effect is a fraction of (docs/bias-model.md, "The CAE
        deceleration as an input").
    n_grid : int or None
        Bias points per test per branch after thinning (>= 2; None: no thinning;
        :func:`crashfuse.method.projection.bias_data`).
    use_companion : bool or None
        At prediction, use a test's companion CAE run directly when the condition is that test's
        (the bias data always pair each test with its companion run); a condition no test has keeps
        the surrogate's curve.
    random_state : int
        Seeds the surrogate (when the fit makes one) and both bias models (>= 0).
    target : {"absolute", "relative"} or None
        What the GPs learn: the bias in m/s^2, or the bias relative to the CAE deceleration
        (:func:`crashfuse.method.projection.bias_scale`); the rollout adds ``scale(a_cae) * bias``.
    trend : {"zero", "constant", "linear"} or None
        The GPs' trend (:class:`crashfuse.gp.kriging.KrigingGP`).
    pooled : bool or None
        With K > 1, fit the cluster GPs on the residual of one GP over all the fold's bias data
        (:class:`crashfuse.method.mixture.GMMGPBias` ``pooled``).
    onset : bool or None
        Correct the loading branch's held-out error over the time since contact early in the pulse
        (:class:`crashfuse.method.onset.OnsetCorrectedBias`; ``state`` inputs only).
    shrink : bool or None
        Scale the loading branch's bias mean, over the time since contact, by how well the training
        tests' leave-one-test-out predictions predict them (:class:`crashfuse.method.onset.OnsetCorrectedBias`
        ``shrink_width``; ``state`` inputs only).
    theta_min : float or None
        Lower bound of the bias model's GP correlation parameters ``theta`` but the labels' (> 0; the upper is
        chosen among ``theta_max_candidates``): in standardised inputs, a correlation length of at most
        ``1 / sqrt(2 theta_min)`` standard deviations (:class:`crashfuse.gp.kriging.KrigingGP`).
    nugget_min : float or None
        Lower bound of every bias GP's nugget (> 0, below the upper bound 10): the least noise variance
        the GPs fit, as a fraction of their process variance (:class:`crashfuse.gp.kriging.KrigingGP`).
    chain : bool or None
        Fit the tests' measurement chain (an accelerometer mount resonance,
        :class:`crashfuse.method.chain.MountResonance`) between the training tests and their companion
        runs, learn the bias of the tests' body decelerations (the mount taken out), and read the
        rollout through the mount.
    weights : bool
        Axle masses among the bias inputs.
    velocity : {"linear", "sqrt"}
        The ``state`` mode's velocity coordinate; ``sqrt``: sign(v) sqrt(|v|), a concave rate
        coordinate (docs/method-rollout.md).
    effects : "auto" or tuple of str
        The physics-first hybrid (:mod:`crashfuse.method.hybrid`): catalogue effects whose laws are
        fitted to the training tests and added to the CAE model before the bias is learnt; ``auto``
        chooses them on the training tests; empty (default): the GMM-GPR model alone.
    n_restarts, max_fit_points, max_condition_points, min_cluster_points, theta_max_candidates, calibrate_variance, estimate_scatter
        :class:`crashfuse.method.mixture.GMMGPBias` settings (``BIAS_SETTINGS``), defaults its own.

    Raises
    ------
    InputError
        A value of the wrong type or out of range, naming the setting; ``onset`` or ``shrink`` with the
        ``paper`` inputs.
    """

    k: int = 1
    inputs: str = "paper"
    assignment: str = "select"
    extra_inputs: bool | None = None
    cae_decel: str | None = None
    n_grid: int | None = 200
    use_companion: bool | None = None
    random_state: int = 0
    target: str | None = None
    trend: str | None = None
    pooled: bool | None = None
    onset: bool | None = None
    shrink: bool | None = None
    chain: bool | None = None
    theta_min: float | None = None
    nugget_min: float | None = None
    weights: bool = True
    velocity: str = "sqrt"
    effects: tuple | str = ()
    n_restarts: int = _BIAS_DEFAULTS["n_restarts"]
    max_fit_points: int | None = _BIAS_DEFAULTS["max_fit_points"]
    max_condition_points: int | None = _BIAS_DEFAULTS["max_condition_points"]
    min_cluster_points: int | None = _BIAS_DEFAULTS["min_cluster_points"]
    theta_max_candidates: tuple = tuple(_BIAS_DEFAULTS["theta_max_candidates"])
    calibrate_variance: bool = _BIAS_DEFAULTS["calibrate_variance"]
    estimate_scatter: bool = _BIAS_DEFAULTS["estimate_scatter"]

    def __post_init__(self):
        self._set("k", _integer("k", self.k, 1, "K"))
        _one_of("inputs", self.inputs, INPUTS)
        for name, value in MODE_DEFAULTS[self.inputs].items():
            if getattr(self, name) is None:
                self._set(name, value)
        _one_of("assignment", self.assignment, ASSIGNMENTS)
        _one_of("target", self.target, TARGETS)
        _one_of("trend", self.trend, TRENDS)
        _one_of("velocity", self.velocity, tuple(VELOCITY))
        _one_of("cae_decel", self.cae_decel, CAE_DECEL)
        for name in ("extra_inputs", "use_companion", "pooled", "onset", "shrink", "chain", "weights",
                     "calibrate_variance", "estimate_scatter"):
            self._set(name, _boolean(name, getattr(self, name)))
        self._set("effects", check_effects(self.effects))
        self._set("n_grid", _integer("n_grid", self.n_grid, 2, "n_grid", optional=True))
        self._set("random_state", _integer("random_state", self.random_state, 0, "seed"))
        self._set("n_restarts", _integer("n_restarts", self.n_restarts, 0, "n_restarts"))
        for name in ("max_fit_points", "max_condition_points", "min_cluster_points"):
            self._set(name, _integer(name, getattr(self, name), 1, name, optional=True))
        self._set("theta_max_candidates", _positive_floats("theta_max_candidates", self.theta_max_candidates))
        self._set("theta_min", _positive_float("theta_min", self.theta_min))
        self._set("nugget_min", _positive_float("nugget_min", self.nugget_min))
        if self.nugget_min >= _NUGGET_MAX:
            raise InputError(f"expected nugget_min below the bias GPs' upper bound {_NUGGET_MAX}, "
                             f"got {self.nugget_min}", field="nugget_min")
        if self.theta_min >= min(self.theta_max_candidates):
            raise InputError(f"expected theta_min below every theta_max_candidates {self.theta_max_candidates}, "
                             f"got {self.theta_min}", field="theta_min")
        for name in ("onset", "shrink"):
            if getattr(self, name) and self.inputs != "state":
                raise InputError(f"{name} needs the state inputs (the velocity gives the time since contact)",
                                 field=name)

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)  # normalising a frozen instance's own field, once

    def bias_params(self, columns=()) -> dict:
        """The :class:`crashfuse.method.mixture.GMMGPBias` settings besides K, assignment and the seed, for
        inputs named ``columns`` (:func:`crashfuse.method.projection.bias_columns`): a one-hot label's theta
        bounded below by the bias model's own bound, the other inputs' by ``theta_min``."""
        labels = [is_label(c) for c in columns]
        theta_min = tuple(_THETA_MIN if lab else self.theta_min for lab in labels) if any(labels) else self.theta_min
        return {"trend": self.trend, "pooled": self.pooled, "theta_bounds": (theta_min, _THETA_MAX),
                "nugget_bounds": (self.nugget_min, _NUGGET_MAX),
                **{name: getattr(self, name) for name in BIAS_SETTINGS}}

    def changed_bias_settings(self) -> dict:
        """The ``BIAS_SETTINGS`` whose value is not the bias model's default."""
        return {name: getattr(self, name) for name in BIAS_SETTINGS
                if getattr(self, name) != _default(name)}

    def as_dict(self) -> dict:
        """Every setting by name (tuples stay tuples)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def _default(name: str):
    return MethodConfig.__dataclass_fields__[name].default


def _one_of(name: str, value, allowed: tuple) -> None:
    if not isinstance(value, str) or value not in allowed:
        raise InputError(f"expected one of {allowed}, got {value!r}", field=name)


def _boolean(name: str, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"expected True or False, got {value!r}", field=name)
    return bool(value)


def _integer(name: str, value, low: int, what: str, optional: bool = False):
    if optional and value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
        raise InputError(f"expected an integer {what} >= {low}{' or None' if optional else ''}, got {value!r}",
                         field=name)
    return int(value)


def _positive_float(name: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = np.nan
    if isinstance(value, bool) or not (np.isfinite(out) and out > 0):
        raise InputError(f"expected a positive number, got {value!r}", field=name)
    return out


def _positive_floats(name: str, values) -> tuple:
    if isinstance(values, (str, bytes)) or not np.iterable(values) or not len(values := tuple(values)):
        raise InputError(f"expected a non-empty sequence of positive numbers, got {values!r}", field=name)
    return tuple(_positive_float(name, v) for v in values)
