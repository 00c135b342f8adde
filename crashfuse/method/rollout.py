"""Bias-corrected rollout with Monte Carlo bands (paper Eq. 22-23).

At a new condition (v0, axle masses, optionally powertrain and drive) the deceleration is the
CAE curve of that condition (surrogate, or the companion run) plus the bias, per branch::

    loading    a = CAE_loading(s)   + bias_loading(x = s, ...)
    unloading  a = CAE_unloading(u) + bias_unloading(x = u = s_max - s, ...)

stepped by :func:`crashfuse.signals.dynamics.rollout` (velocity Verlet, barrier constraints). With a
relative target (``model.relative``) the bias is ``bias_scale(CAE) * b`` instead of ``b``.

Monte Carlo. The condition is fixed for a prediction, so in ``paper`` mode each branch's bias is
a function of the branch coordinate only: it is drawn jointly (latent, no nugget) on a uniform
1-D grid of that coordinate and every sample reads its own draw by linear interpolation.
In ``state`` mode the bias also depends on the current velocity. Its mean ``mu(x, v)`` is
tabulated on a 2-D (x, v) grid and read at each sample's own (x, v); the random part is drawn
jointly along the path ``(x, v_bar(x))`` of the deterministic mean-function rollout and added as
a function of x alone::

    f_j(x, v) = mu(x, v) + [g_j(x, v_bar(x)) - mu(x, v_bar(x))]

exact for the mean; it approximates the deviation of a draw at a velocity away from the mean
path by the deviation on that path (the draws' spread changes slowly with v where data exist).

Two rollouts are reported: the deterministic *mean-function* rollout (bias = GP mean) and the
Monte Carlo ensemble. The scored prediction, ``Prediction.decel``, is the **Monte Carlo mean**:
the mean over samples of the deceleration at each time.

Two deceleration bands. The *latent* band (``decel_latent_lo/hi``) is the ensemble's 2.5/97.5 %
percentiles, for a condition beyond the training tests' range widened by the bias function's std the draws
do not carry (:func:`extrapolation_std`): the bias function's uncertainty only. A new physical test
also scatters about the bias function (near-replicate tests differ by 0.3-1 g), so the reported band
for ``band='test'`` (default) widens the latent one by the bias model's test-to-test scatter
(:meth:`crashfuse.method.mixture.GMMGPBias.scatter_std`, calibrated on grouped leave-one-test-out
residuals), in quadrature on each side of the Monte Carlo mean. ``band='latent'`` reports the latent band.
The draws, the mean and every other band are the same either way.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
from scipy.stats import norm

from crashfuse.signals.dynamics import Trajectory, rollout
from crashfuse.signals.domain import rebound_work
from crashfuse.errors import InputError
from crashfuse.signals.metrics import REBOUND_WINDOW, occupant_load_criterion
from crashfuse.method.projection import BRANCHES, bias_scale
from crashfuse.units import G0, KMH, MM, MS

BAND = (2.5, 97.5)  # percent: the 95 % band
BANDS = ("test", "latent")  # reported deceleration band: a new test's, or the bias function's alone
N_X = 160  # grid points per branch coordinate for the joint draws
N_V = 16  # velocity grid points of the state-mode mean table
GRID_MARGIN = 1.3  # branch grids reach this factor beyond the data and CAE ranges


@dataclasses.dataclass(frozen=True)
class Prediction:
    """A bias-corrected prediction at one condition.

    Attributes
    ----------
    time : ndarray, shape (n,)
        Time since contact in s.
    decel, velocity, displacement : ndarray, shape (n,)
        Monte Carlo means (m/s^2, m/s, m): ``decel`` is the scored prediction.
    decel_lo, decel_hi : ndarray, shape (n,)
        The reported 95 % deceleration band (m/s^2): ``band='test'``, where a new test is expected
        (latent band widened by the test-to-test scatter), or ``band='latent'`` (equal to the next).
    decel_latent_lo, decel_latent_hi : ndarray, shape (n,)
        2.5 and 97.5 percentiles of the Monte Carlo decelerations: the bias function's uncertainty.
    decel_scatter : ndarray, shape (n,)
        Test-to-test scatter std of the deceleration along the mean-function rollout (m/s^2; 0 for
        ``band='latent'``, which does not need it).
    velocity_lo, velocity_hi, displacement_lo, displacement_hi : ndarray, shape (n,)
        2.5 and 97.5 percentiles over the samples (latent).
    mean_function_decel : ndarray, shape (n,)
        Deceleration of the deterministic rollout with the bias set to its GP mean (m/s^2).
    mean_path : Trajectory
        That deterministic rollout in full (one sample: s, v, branch ...).
    cae_decel : ndarray, shape (n,)
        Deceleration of the rollout with no bias: the CAE curve alone (m/s^2).
    metrics : dict
        Pulse metrics (report units, see :func:`trajectory_metrics`) -> dict with ``mean``, ``lo``,
        ``hi`` over the samples and ``mean_function``.
    extrapolation : dict of str to bool
        True where the condition or the mean rollout's crush/rebound lies outside the bias data;
        there the GP reverts to its trend and the band widens.
    n_samples : int
    condition : dict
        The condition predicted, SI.
    band : str
        Which band ``decel_lo/hi`` is: ``test`` or ``latent``.
    """

    time: np.ndarray
    decel: np.ndarray
    decel_lo: np.ndarray
    decel_hi: np.ndarray
    decel_latent_lo: np.ndarray
    decel_latent_hi: np.ndarray
    decel_scatter: np.ndarray
    velocity: np.ndarray
    velocity_lo: np.ndarray
    velocity_hi: np.ndarray
    displacement: np.ndarray
    displacement_lo: np.ndarray
    displacement_hi: np.ndarray
    mean_function_decel: np.ndarray
    mean_path: Trajectory
    cae_decel: np.ndarray
    metrics: dict
    extrapolation: dict
    n_samples: int
    condition: dict
    band: str

    def frame(self) -> pd.DataFrame:
        """The CSV table in report units (g for decelerations; m/s and m as named).

        Returns
        -------
        DataFrame, shape (n, 14)
            ``time_s, decel_g, decel_lo_g, decel_hi_g, cae_decel_g, mean_function_decel_g,
            velocity_mps, velocity_lo_mps, velocity_hi_mps, displacement_m, displacement_lo_m,
            displacement_hi_m, decel_latent_lo_g, decel_latent_hi_g``.
        """
        return pd.DataFrame({
            "time_s": self.time,
            "decel_g": self.decel / G0, "decel_lo_g": self.decel_lo / G0, "decel_hi_g": self.decel_hi / G0,
            "cae_decel_g": self.cae_decel / G0, "mean_function_decel_g": self.mean_function_decel / G0,
            "velocity_mps": self.velocity, "velocity_lo_mps": self.velocity_lo,
            "velocity_hi_mps": self.velocity_hi,
            "displacement_m": self.displacement, "displacement_lo_m": self.displacement_lo,
            "displacement_hi_m": self.displacement_hi,
            "decel_latent_lo_g": self.decel_latent_lo / G0, "decel_latent_hi_g": self.decel_latent_hi / G0,
        })


class _BranchBias:
    """One branch's bias for one prediction: mean table plus per-sample deviations.

    Parameters
    ----------
    x_hi : float
        Grid end of the branch coordinate in m (the grid starts at 0).
    mean_table : ndarray, shape (N_X, nv)
        GP mean (m/s^2) on the x grid times the velocity grid (``nv = 1``: no v dependence).
    v_grid : ndarray, shape (nv,)
    dev : ndarray, shape (m, N_X) or None
        Per-sample deviation of the drawn function from the mean along the grid.
    gain : ndarray, shape (m,) or None
        Per-sample factor on the whole bias (the rebound bound, :func:`_rebound_bounded`); None: 1.
    """

    def __init__(self, x_hi, mean_table, v_grid, dev=None, gain=None):
        self.x_hi, self.mean_table, self.v_grid, self.dev, self.gain = x_hi, mean_table, v_grid, dev, gain

    @property
    def n_functions(self) -> int:
        """Functions held: the samples' draws, or 1 (the mean)."""
        return 1 if self.dev is None else self.dev.shape[0]

    def with_gain(self, gain):
        """The same functions, each multiplied by its ``gain`` (shape (n_functions,))."""
        return _BranchBias(self.x_hi, self.mean_table, self.v_grid, self.dev, gain)

    def __call__(self, x, v, rows=None):
        """Bias in m/s^2 at (x, v), shape (k,), for the samples ``rows`` (default all, k = m)."""
        ix, wx = _cell(x, 0.0, self.x_hi, self.mean_table.shape[0])
        if self.mean_table.shape[1] == 1:
            out = self.mean_table[ix, 0] * (1 - wx) + self.mean_table[ix + 1, 0] * wx
        else:
            iv, wv = _cell(v, self.v_grid[0], self.v_grid[-1], self.v_grid.size)
            t = self.mean_table
            out = ((t[ix, iv] * (1 - wv) + t[ix, iv + 1] * wv) * (1 - wx)
                   + (t[ix + 1, iv] * (1 - wv) + t[ix + 1, iv + 1] * wv) * wx)
        if self.dev is not None:
            rows = np.arange(self.dev.shape[0]) if rows is None else rows
            out = out + self.dev[rows, ix] * (1 - wx) + self.dev[rows, ix + 1] * wx
        if self.gain is not None:
            out = out * (self.gain[0] if self.dev is None else self.gain[rows])
        return out


def _cell(x, lo, hi, n):
    """Cell index (clipped, so values beyond the grid hold its end) and weight on a uniform grid."""
    if n == 1 or hi <= lo:
        return np.zeros(np.shape(x), dtype=int), np.zeros(np.shape(x))
    z = np.clip((x - lo) * ((n - 1) / (hi - lo)), 0.0, n - 1)
    i = np.minimum(z.astype(int), n - 2)
    return i, z - i


class _Tabulated:
    """A CAE curve's loading branch tabulated once, for fast evaluation in the stepping loop.

    The knots are the curve's own displacements (so values there are unchanged) plus a fine
    uniform extension up to ``s_hi`` where the curve continues beyond its data.
    """

    def __init__(self, curve, s_hi: float):
        s = np.asarray(curve.s, dtype=float)
        knots = np.union1d(s, np.linspace(s[-1], s_hi, 512)) if s_hi > s[-1] else s
        self.s, self.a = knots, curve.loading(knots)
        self.unloading = curve.unloading

    def loading(self, s):
        """Loading deceleration (m/s^2) at ``s`` (m); the last value held beyond the table."""
        return np.interp(s, self.s, self.a)


def _decel_fn(curve, biases, relative=False):
    """decel_fn for :func:`crashfuse.signals.dynamics.rollout`: CAE curve plus the branch biases.

    With ``relative`` the biases are fractions of :func:`crashfuse.method.projection.bias_scale` of the
    CAE deceleration at the same point.
    """
    def decel(state):
        a = np.empty(state.s.shape)
        for mask, x, cae_at, name in ((state.loading, state.s, curve.loading, "loading"),
                                      (~state.loading, state.u, curve.unloading, "unloading")):
            if mask.any():
                a_cae = cae_at(x[mask])
                bias = _sub(biases[name], x, state.v, mask)
                a[mask] = a_cae + (bias_scale(a_cae) * bias if relative else bias)
        return a
    return decel


def _sub(bias, x, v, mask):
    """A branch bias evaluated for the masked samples only (zero where the branch has no model)."""
    if bias is None:
        return 0.0
    return bias(x[mask], v[mask], np.flatnonzero(mask))


def predict(model, v0, front_weight, rear_weight, powertrain=None, drive=None, n_samples=1000,
            random_state=None, duration=0.1, dt=8e-5, band="test") -> Prediction:
    """Bias-corrected pulse with a Monte Carlo band at one condition.

    Parameters
    ----------
    model : crashfuse.method.model.FittedModel
    v0 : float
        Impact speed in m/s.
    front_weight, rear_weight : float
        Axle masses in kg.
    powertrain, drive : str, optional
        Labels, needed when the model uses them (``extra_inputs``) or the surrogate does.
    n_samples : int
        Monte Carlo samples (functions drawn per branch).
    random_state : int, RandomState or None
        Seeds the draws.
    duration, dt : float
        Length and step of the rollout in s (default 100 ms at 12.5 kHz, the campaign's rate).
    band : {"test", "latent"}
        The reported deceleration band: where a new test is expected (latent band plus the
        test-to-test scatter), or the bias function's uncertainty alone. Nothing else changes.

    Returns
    -------
    Prediction

    Raises
    ------
    InputError
        On a bad condition or setting, or a condition the CAE curve cannot be given for.
    """
    cond = model.condition(v0, front_weight, rear_weight, powertrain, drive)
    n_samples = _positive_int(n_samples, "n_samples")
    if not (np.isfinite(dt) and dt > 0 and np.isfinite(duration) and duration >= 16 * dt):
        raise InputError(f"expected dt > 0 and a duration of at least 16 steps, got dt={dt}, duration={duration}",
                         field="duration")
    if band not in BANDS:
        raise InputError(f"expected one of {BANDS}, got {band!r}", field="band")
    n_steps = int(round(duration / dt))
    rng = np.random.RandomState(random_state) if not isinstance(random_state, np.random.RandomState) \
        else random_state
    curve, draws, mean_traj, cae = _prepare(model, cond, n_samples, rng, dt, n_steps)
    mc = rollout(_decel_fn(curve, draws, model.relative), np.full(n_samples, cond.v0), dt, n_steps)
    mc, mean_traj = (_read_through(model, traj) for traj in (mc, mean_traj))
    scatter = decel_scatter(model, curve, mean_traj, cond) if band == "test" else np.zeros(mean_traj.time.size)
    beyond = extrapolation_std(model, curve, mean_traj, cond)
    return _summarise(mc, mean_traj, cae, cond, model.extrapolation(cond, mean_traj), scatter, beyond, band)


def _prepare(model, cond, n_samples: int, rng, dt: float, n_steps: int):
    """Everything before the Monte Carlo rollout.

    Returns
    -------
    curve : _Tabulated
        The CAE curve of the condition.
    draws : dict of str to _BranchBias or None
        Per branch, the bias of every sample.
    mean_traj, cae : Trajectory
        The mean-function rollout and the zero-bias (CAE-only) rollout, one sample each.
    """
    raw = model.cae_curve(cond)
    curve = _Tabulated(raw, 2 * GRID_MARGIN * max(model.x_max("loading"), float(raw.s_max), float(raw.s[-1])))
    cae = rollout(_decel_fn(curve, {b: None for b in BRANCHES}), cond.v0, dt, n_steps)
    x_hi = _grid_ends(model, raw, cae)
    means = {b: _mean_bias(model, b, cond, x_hi[b], curve) for b in BRANCHES}
    mean_traj = rollout(_decel_fn(curve, means, model.relative), cond.v0, dt, n_steps)
    bounded = _rebound_bounded(model, curve, means["unloading"], mean_traj)
    if bounded is not means["unloading"]:
        means["unloading"] = bounded
        mean_traj = rollout(_decel_fn(curve, means, model.relative), cond.v0, dt, n_steps)
    draws = {b: _drawn_bias(model, b, cond, means[b], mean_traj, n_samples, rng, curve) for b in BRANCHES}
    draws["unloading"] = _rebound_bounded(model, curve, draws["unloading"], mean_traj)
    return curve, draws, mean_traj, cae


def _read_through(model, traj: Trajectory) -> Trajectory:
    """The rollout as the tests' accelerometer reads it: every sample's deceleration read through the
    model's measurement chain (unchanged without one). The bias was learnt from the tests' body
    decelerations, so CAE and bias ring together, where each sample reaches its crush stages; the
    motion - velocity, displacement - stays the body's."""
    if model.chain is None:
        return traj
    return dataclasses.replace(traj, decel=model.chain.apply(traj.time, traj.decel))


def _positive_int(value, field):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputError(f"expected an integer >= 1, got {value!r}", field=field)
    return int(value)


def _grid_ends(model, curve, cae: Trajectory) -> dict:
    """End of each branch's grid (m): beyond the bias data, the CAE curve and the CAE rollout."""
    s_reach = max(model.x_max("loading"), float(curve.s_max), float(cae.s_max[0]))
    contact = cae.branch[0] == Trajectory.UNLOADING  # after separation u grows in free flight
    u_cae = float(np.max(cae.s_max[0] - cae.s[0][contact], initial=0.0))
    u_curve = 0.0 if curve.u is None else float(curve.u[-1])
    u_reach = max(model.x_max("unloading"), u_curve, u_cae)
    return {"loading": GRID_MARGIN * s_reach, "unloading": GRID_MARGIN * max(u_reach, 1e-3)}


def _velocity_grid(branch: str, v0: float) -> np.ndarray:
    """Velocities the state-mode mean table spans (m/s): forward on loading, rebound on unloading."""
    lo, hi = (-0.05 * v0, 1.05 * v0) if branch == "loading" else (-0.6 * v0, 0.05 * v0)
    return np.linspace(lo, hi, N_V)


def _mean_bias(model, branch, cond, x_hi, curve) -> _BranchBias | None:
    """The GP mean of one branch on its grid (x, and v in state mode)."""
    est = model.bias_.get(branch)
    if est is None:
        return None
    x = np.linspace(0.0, x_hi, N_X)
    v_grid = _velocity_grid(branch, cond.v0) if model.inputs == "state" else np.zeros(1)
    xx, vv = np.meshgrid(x, v_grid, indexing="ij")
    table = est.predict(model.features(branch, xx.ravel(), vv.ravel(), cond, curve)).reshape(xx.shape)
    return _BranchBias(x_hi, np.clip(table, *_mean_range(model, branch)), v_grid)


def _mean_range(model, branch) -> tuple[float, float]:
    """Where a relative target's mean may go: the span of the training tests' bias
    (:meth:`~crashfuse.method.model.FittedModel.bias_range`); the ``paper`` inputs' none.

    Simple kriging with the Gaussian correlation overshoots beyond its data before it fades to zero:
    where no training test was slow at a crush its mean reached a relative bias of -0.66 among tests
    whose bias there was +0.2 to +0.7 (docs/method-validation.md, eighth slice).
    """
    return model.bias_range(branch) if model.relative else (-np.inf, np.inf)


def _drawn_bias(model, branch, cond, mean: _BranchBias | None, path: Trajectory, n_samples, rng, curve):
    """Joint latent draws of one branch's bias along the mean-function rollout's path.

    For a relative target, where the draws' std in m/s^2 exceeds :func:`_bound` at the nearest
    condition inside the training tests' range they are shrunk towards the mean to it (beyond the
    range the rest of the GP's std is the band's: :func:`extrapolation_std`).
    """
    if mean is None:
        return None
    x = np.linspace(0.0, mean.x_hi, N_X)
    v = _path_velocity(branch, path, x) if model.inputs == "state" else np.zeros_like(x)
    X = model.features(branch, x, v, cond, curve)
    est = model.bias_[branch]
    g = est.sample_functions(X, n_samples, rng.randint(2**31 - 1))
    dev = g - est.predict(X)[None, :]
    scale = _scale(model, curve, branch, x)
    sd = dev.std(axis=0) * scale
    bound = _bound(model, branch, scale, model.features(branch, x, v, model.nearest_inside(cond), curve))
    dev *= np.minimum(1.0, bound / np.maximum(sd, np.finfo(float).tiny))
    return _BranchBias(mean.x_hi, mean.mean_table, mean.v_grid, dev)


def _bound(model, branch, scale, X) -> np.ndarray:
    """The most the draws' std may spread the bias of ``branch`` at inputs ``X`` (m, d) of a condition
    inside the training tests' range (:meth:`~crashfuse.method.model.FittedModel.nearest_inside`), where
    the learnt bias has ``scale`` (m/s^2 per unit, :func:`_scale`): for a relative target the smallest of
    :func:`_spread` and the std the training tests' held-out errors need near ``X``
    (:meth:`~crashfuse.method.mixture.GMMGPBias.held_out_std`) times ``scale``; else none.

    A relative target's GP serves the small CAE decelerations, where noise is a large fraction, and
    the peak alike; its std times a 30 g pulse spread a model fitted to noise over a 20 g wide band.
    Held to :func:`_spread`, the same GP still spread a mid-speed test's band to +-10 g around errors
    within 3 g (its latent std 10-40 times its held-out errors): the held-out bound is the band those
    errors need. The ``paper`` inputs learn the bias in m/s^2, as published, and are left alone.
    """
    if not model.relative:
        return np.full(np.shape(scale), np.inf)
    return np.minimum(_spread(model, branch, scale), model.bias_[branch].held_out_std(X) * scale)


def _spread(model, branch, scale) -> np.ndarray:
    """The training tests' bias rms, in m/s^2 (:meth:`~crashfuse.method.model.FittedModel.bias_spread`)
    and in the target's units times ``scale`` (:meth:`~crashfuse.method.model.FittedModel.target_spread`),
    the smaller: the m/s^2 rms is the fast tests' bias, which at a slow test's 2 g onset is the whole
    pulse; a GP fitted to smooth bias data took a near-infinite variance there and spread an 8 mph
    test's draws by +-10 g at contact."""
    return np.minimum(model.bias_spread(branch), model.target_spread(branch) * scale)


def extrapolation_std(model, curve, path: Trajectory, cond) -> np.ndarray:
    """The bias function's std (m/s^2) the draws do not carry, along a one-sample rollout, shape (n,).

    Zero for a condition inside the training tests' range. Beyond it (a test slower, faster, lighter
    or heavier than every training test) the held-out errors, errors among the tests, do not say how
    far off the bias model is: the GP's own latent std (at most :func:`_spread`) does. The draws keep
    :func:`_bound` at the nearest condition inside the range, and this is the rest of the GP's std,
    in quadrature, which the band adds about the Monte Carlo mean (:func:`_widened`). Draws spread as
    wide as :func:`_spread` stopped an 8 mph test anywhere between 36 and 55 ms (the test: 44 ms); their mean
    falls through the unloading as no pulse does (docs/decisions.md, section 81).
    """
    out = np.zeros(path.time.size)
    if not model.relative or not any(model.condition_outside(cond).values()):
        return out
    for branch, est, on, scale, X, bound in _along(model, curve, path, cond):
        latent = np.minimum(est.predict(X, return_std=True)[1] * scale, _spread(model, branch, scale))
        out[on] = np.sqrt(latent**2 - np.minimum(latent, bound) ** 2)
    return out


def _rebound_bounded(model, curve, bias: _BranchBias | None, path: Trajectory) -> _BranchBias | None:
    """``bias`` (unloading) with each function scaled down where it would take the rebound speed out of
    the span, relative to the CAE's, that the training tests show
    (:meth:`~crashfuse.method.model.FittedModel.rebound_range`).

    The rebound speed is ``sqrt(2 W)`` of the spring-back's work ``W`` (:func:`rebound_work`) along
    the unloading grid, at the mean path's velocity. Outside the span, the function's factor is the
    largest in [0, 1) that keeps it inside (bisection: the work is convex in the factor, so the
    factors inside form an interval from 0). As :func:`_bound`, for a relative target only: its GP
    fitted to noise moved a rebound by 25 % where the tests and the CAE differ by 3 %.
    """
    lo, hi = model.rebound_range() if model.relative else (0.0, np.inf)
    if bias is None or (lo <= 0.0 and np.isinf(hi)):
        return bias
    u = np.linspace(0.0, bias.x_hi, N_X)
    a_cae = curve.unloading(u)
    cae_work = rebound_work(u, a_cae)[0]
    if cae_work <= 0.0:
        return bias
    m = bias.n_functions
    v = _path_velocity("unloading", path, u) if model.inputs == "state" else np.zeros_like(u)
    b = bias(np.tile(u, m), np.tile(v, m), np.repeat(np.arange(m), u.size)).reshape(m, u.size)
    b = b * _scale(model, curve, "unloading", u)

    def inside(gain):
        ratio2 = rebound_work(u, a_cae + gain[:, None] * b)[0] / cae_work
        return (ratio2 >= lo**2) & (ratio2 <= hi**2)

    good = inside(np.ones(m))
    if good.all():
        return bias
    gain, out = good.astype(float), np.ones(m)  # inside at ``gain``, outside at ``out``
    for _ in range(30):
        mid = 0.5 * (gain + out)
        ok = inside(mid)
        gain, out = np.where(ok, mid, gain), np.where(ok, out, mid)
    return bias.with_gain(np.where(good, 1.0, gain))


def _scale(model, curve, branch, x):
    """m/s^2 per unit of the learnt bias at branch coordinate ``x``: the CAE curve's
    :func:`~crashfuse.method.projection.bias_scale` for a relative target, else 1."""
    if not model.relative:
        return np.ones_like(x)
    return bias_scale(curve.loading(x) if branch == "loading" else curve.unloading(x))


def _path_velocity(branch, path: Trajectory, x) -> np.ndarray:
    """Velocity of the mean rollout as a function of the branch coordinate, at ``x`` (held beyond)."""
    on, xb, vb = path.on_branch(branch)
    if not on.any():
        return np.zeros_like(x) if branch == "unloading" else np.full_like(x, path.v[0, 0])
    keep = xb > np.maximum.accumulate(np.r_[-np.inf, xb[:-1]])  # strictly increasing for interp
    return np.interp(x, xb[keep], vb[keep])


def decel_scatter(model, curve, path: Trajectory, cond) -> np.ndarray:
    """Test-to-test scatter std of the deceleration (m/s^2) along a one-sample rollout, shape (n,).

    The bias model's :meth:`~crashfuse.method.mixture.GMMGPBias.scatter_std` at the path's inputs, in
    deceleration units (times :func:`crashfuse.method.projection.bias_scale` of the CAE deceleration
    there for a relative target, then at most :func:`_bound` at the nearest condition inside the
    training tests' range); 0 after separation and on a branch without a model.
    """
    out = np.zeros(path.time.size)
    for _, est, on, scale, X, bound in _along(model, curve, path, cond):
        out[on] = np.minimum(est.scatter_std(X) * scale, bound)
    return out


def _along(model, curve, path: Trajectory, cond):
    """Per branch with a bias model that ``path`` (a one-sample rollout) reaches: the branch, its model, the
    path's samples on it (bool, shape (n,)), :func:`_scale` there, the inputs ``X`` at ``cond`` and
    :func:`_bound` at the nearest condition inside the training tests' range."""
    inside = model.nearest_inside(cond)
    for branch in BRANCHES:
        est, (on, x, v) = model.bias_.get(branch), path.on_branch(branch)
        if est is None or not on.any():
            continue
        scale = _scale(model, curve, branch, x)
        bound = _bound(model, branch, scale, model.features(branch, x, v, inside, curve))
        yield branch, est, on, scale, model.features(branch, x, v, cond, curve), bound


def _widened(mean, lo, hi, std):
    """The band (lo, hi) widened by ``std``, in quadrature with each side's distance from the mean.

    Never narrower than the band given (min/max guard the rounding of sqrt(d^2) where the std is 0).
    """
    z = norm.ppf(BAND[1] / 100)
    widen = (z * std) ** 2
    return (np.minimum(lo, mean - np.sqrt(np.maximum(mean - lo, 0.0) ** 2 + widen)),
            np.maximum(hi, mean + np.sqrt(np.maximum(hi - mean, 0.0) ** 2 + widen)))


def _summarise(mc: Trajectory, mean_traj: Trajectory, cae: Trajectory, cond, flags, scatter, beyond,
               band) -> Prediction:
    lo, hi = BAND
    pct = {name: np.percentile(arr, [lo, hi], axis=0) for name, arr in
           (("decel", mc.decel), ("velocity", mc.v), ("displacement", mc.s))}
    mean = mc.decel.mean(axis=0)
    latent = _widened(mean, *pct["decel"], beyond)
    shown = _widened(mean, *latent, scatter) if band == "test" else latent
    return Prediction(
        time=mc.time,
        decel=mean, decel_lo=shown[0], decel_hi=shown[1],
        decel_latent_lo=latent[0], decel_latent_hi=latent[1], decel_scatter=scatter,
        velocity=mc.v.mean(axis=0), velocity_lo=pct["velocity"][0], velocity_hi=pct["velocity"][1],
        displacement=mc.s.mean(axis=0), displacement_lo=pct["displacement"][0],
        displacement_hi=pct["displacement"][1],
        mean_function_decel=mean_traj.decel[0], mean_path=mean_traj, cae_decel=cae.decel[0],
        metrics=_metric_bands(mc, mean_traj, cond.v0), extrapolation=flags,
        n_samples=mc.s.shape[0], condition=dataclasses.asdict(cond), band=band,
    )


def trajectory_metrics(traj: Trajectory, v0: float) -> dict[str, np.ndarray]:
    """Pulse metrics of every sample of a rollout, in report units.

    The definitions are those of :func:`crashfuse.signals.metrics.pulse_metrics` applied to the rolled-out
    deceleration (already CFC 60-like: the CAE curve and a smooth bias), its Verlet velocity and
    displacement.

    Parameters
    ----------
    traj : Trajectory
        ``m`` samples.
    v0 : float
        Impact speed in m/s.

    Returns
    -------
    dict of str to ndarray, shape (m,)
        ``peak_decel_g``, ``t_peak_ms``, ``t_zero_velocity_ms``, ``dynamic_crush_mm``,
        ``rebound_kmh``, ``olc_g``; NaN where a sample does not reach the quantity.
    """
    t, v = traj.time, traj.v
    i_peak = np.argmax(traj.decel, axis=1)
    rows = np.arange(v.shape[0])
    stopped = (v <= 0).any(axis=1)
    i0 = np.where(stopped, np.argmax(v <= 0, axis=1), 1)
    v_a, v_b = v[rows, i0 - 1], v[rows, i0]
    t_stop = t[i0 - 1] + (t[i0] - t[i0 - 1]) * v_a / np.where(v_a - v_b == 0, 1.0, v_a - v_b)
    olc = [occupant_load_criterion(t, v[k], traj.s[k], v0) for k in rows]
    return {
        "peak_decel_g": traj.decel[rows, i_peak] / G0,
        "t_peak_ms": t[i_peak] / MS,
        "t_zero_velocity_ms": np.where(stopped, t_stop / MS, np.nan),
        "dynamic_crush_mm": np.where(stopped, traj.s_max / MM, np.nan),
        "rebound_kmh": np.maximum(0.0, -v[:, t <= REBOUND_WINDOW].min(axis=1)) / KMH,
        "olc_g": np.array([np.nan if o is None else o / G0 for o in olc]),
    }


def _metric_bands(mc: Trajectory, mean_traj: Trajectory, v0: float) -> dict:
    lo, hi = BAND
    det = trajectory_metrics(mean_traj, v0)
    out = {}
    for name, vals in trajectory_metrics(mc, v0).items():
        ok = vals[np.isfinite(vals)]
        band = np.percentile(ok, [lo, hi]) if ok.size else (None, None)
        out[name] = {"mean": _num(ok.mean()) if ok.size else None, "lo": _num(band[0]), "hi": _num(band[1]),
                     "mean_function": _num(det[name][0]), "fraction_reached": ok.size / vals.size}
    return out


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)
