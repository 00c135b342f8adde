"""Physical effects a CAE model may miss, as force laws added to the CAE dynamics in a rollout.

These are the diagnosis's own laws of the catalogue effects (:mod:`crashfuse.catalogue`): textbook
laws written in terms of the rollout's state, independent of how any simulator produced the
campaign. Parameters are ``effect.param`` in SI; :data:`QUANTITIES` says which catalogue quantity
each one is.

The force balance of one sample (vehicle of nominal mass ``M``, the test's axle masses) at a step
with displacement ``s``, velocity ``v`` (m/s, positive forward), maximum crush ``s_max`` and
unloading coordinate ``u = s_max - s``::

    a = (F_crush + F_extra) / M_eff

* ``F_crush`` is the CAE model's crush force: ``M a_CAE(s, v)`` on loading; on unloading the CAE
  run's unloading curve with its stiffness kept, started from the force reached at the rollout's
  own maximum crush (which moves when an effect changes the pulse): with
  ``r = a_CAE(s_max) / a_CAE,u(0)``, ``F_crush = M r a_CAE,u(u / r)`` - force and elastic
  spring-back both scale with the peak force, as for a linear elastic unloading.
* ``a_CAE(s, v) = a_CAE(s) + [F_v(s, v) - F_v(s, v_CAE(s))] / M``: the CAE run's own deceleration
  along its own trajectory ``v_CAE(s)``, moved to the rollout's velocity along the CAE model's
  force-speed dependence at fixed crush ``F_v = b1 v + b2 v^2`` (:func:`crush_force_rate`, a
  regression over all CAE runs; 0 when none are given). A CAE model with rate effects of its own (material rate
  hardening, damping) then responds to an effect that changes the velocity - an extra mass
  arrives faster at every crush - instead of replaying its force-crush curve. ``F_crush >= 0``.
* ``F_extra`` collects added forces (0 for the CAE model); ``M_eff`` starts at ``M``.

The laws (each one modifies the balance; their order does not matter):

``strain_rate``  Cowper-Symonds rate hardening of the static crush strength on loading,
    ``F_crush += M a_CAE(s, 0) (v / D)^(1/q)`` (``d`` m/s: the crush speed at which the static
    strength doubles; ``q``). Only the strength hardens: the CAE model's own viscous and inertial
    forces are not multiplied (without ``da/dv`` the whole CAE force counts as static).
``damping``      Crush damping on both branches, a power of the crush speed:
    ``F_extra += c V_REF sign(v) |v / V_REF|^n`` (``c`` N s/m: the force per crush speed at
    :data:`~crashfuse.catalogue.V_REF`; ``n`` 1 viscous (Kelvin-Voigt), 2 quadratic: fluids and
    foam squeezed out).
``unloading``    Hysteretic power-law unloading, replacing the CAE unloading: with the static force
    at maximum crush ``F_m = M a_CAE(s_max, 0)`` and the initial decay length
    ``lam = l0 + F_m / k`` (the force falls at first by ``F_m / lam`` per metre: ``k`` is the
    initial unloading stiffness at a large peak force), ``F_crush = F_m (1 - u / (n lam))^n`` for
    ``u < n lam`` (the elastic spring-back), else 0 (``k`` N/m, ``l0`` m, ``n``). Parametrised by
    the initial fall, the family holds the exponential ``F_m exp(-u / lam)`` as ``n`` grows: an
    unloading that falls fast and then tails off (a residual set reached slowly) is ``n`` at its
    upper bound, not beyond what is physical.
``powertrain``   A second mass ``m_p`` (per powertrain label) riding in the body is arrested by the
    barrier once the crush closes its gap ``g``: from then on it leaves the decelerating mass
    (``M_eff -= m_p``; its momentum goes into the barrier) and the body drives into it through
    mounts of stiffness ``k_mount``, elastic up to a yield force ``f_mount`` and perfectly plastic
    beyond: ``F_extra += min(f_mount, k_mount (s - g))`` on loading, unloading elastically from
    its peak. Both are fitted: stiff mounts that yield early return little on the spring-back,
    soft mounts that never yield push the body back over the whole travel (rubber mounts).
``mass``         An extra mass ``m`` (kg) beyond the nominal test weight rides on a link of stiffness
    ``k`` (N/m) and damping ratio :data:`LINK_DAMPING_RATIO`: the body feels the link force
    ``L = k z + c z'`` (``z`` the extra mass's travel relative to the body, ``c = 2 zeta sqrt(k m)``),
    ``F_extra -= L``, while ``z'' = a - L / m``. A stiff link is the rigid limit ``M_eff += m``
    (ballast, bolted equipment), where the fit starts; a soft one engages the mass late and gives
    part of its momentum back (a battery or cargo on compliant mounts). Each step is implicit in
    the link (backward Euler of ``z, z'`` with the body): stable and exactly rigid as ``k`` grows.

Every effect lists its parameters with physical bounds and starting points (:class:`Param`);
:func:`headline` computes the catalogue's headline quantities from them.
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from crashfuse.catalogue import F_REF, V_REF, check_effect, key, quantity
from crashfuse.signals.domain import displacement_branches, position_increment, velocity_decrement
from crashfuse.errors import InputError
from crashfuse.signals.dynamics import State, Trajectory

# Each parameter of the laws as the catalogue quantity it is (``powertrain.mass`` and
# ``powertrain.gap`` stand for their per-label parameters ``powertrain.mass[label]``...).
QUANTITIES = {
    "damping.c": "c",
    "damping.n": "speed_exponent",
    "strain_rate.d": "doubling_speed",
    "strain_rate.q": "inverse_rate_exponent",
    "powertrain.mass": "mass",
    "powertrain.gap": "gap",
    "powertrain.f_mount": "mount_yield_force",
    "powertrain.k_mount": "mount_stiffness",
    "unloading.k": "initial_unloading_stiffness",
    "unloading.l0": "initial_decay_floor",
    "unloading.n": "unloading_exponent",
    "mass.extra": "extra",
    "mass.k_link": "link_stiffness",
}
LINK_DAMPING_RATIO = 0.2  # the extra mass's link: a lightly damped mount, fixed (its stiffness is what the pulse shows)
RUNS_PER_COEF = 3  # moving CAE runs per regression coefficient before a crush's force-speed fit is used

N_S, N_U = 2048, 512  # loading and unloading table points of a Plant

@dataclasses.dataclass(frozen=True)
class Param:
    """One fitted parameter of an effect (SI).

    Attributes
    ----------
    name : str
        ``effect.param`` (``effect.param[label]`` for a parameter per powertrain label).
    unit : str
        The unit of its catalogue quantity (:func:`_param`).
    lower, upper : float
        Physical bounds (> 0; fitted in log space).
    start : tuple of float
        Starting points of the fit (multi-start).
    upper_is_limit : bool
        A fit at ``upper`` needs more of the effect than is physical (an extra mass above half
        the car), so the law cannot explain the gap. False where ``upper`` only closes the search
        box on the weak side (the rate reference ``d``: a larger ``d`` hardens less) or is a limit
        inside the family (a rigid link or unloading start, a sharp mount step, an exponential).
    off : float or None
        A value at which the law (nearly) does not act, with its law's other parameters at theirs
        (their first start where None): the nested law set a fit can always fall back to
        (:func:`crashfuse.method.effect_fit.fit_beyond`). None on every parameter of a law without
        such a value (the unloading replaces the CAE's own).
    """

    name: str
    unit: str
    lower: float
    upper: float
    start: tuple
    upper_is_limit: bool = True
    off: float | None = None


@dataclasses.dataclass(frozen=True)
class Plant:
    """The CAE model of every sample's condition, tabulated for fast lookup in a rollout.

    Attributes
    ----------
    s_step, u_step : float
        Uniform grid steps in m of the loading (from s = 0) and unloading (from u = 0) tables.
    load_table : ndarray, shape (3, n_c, n_s)
        The loading tables ``a_rest``, ``dadv``, ``dadv2`` (properties; stacked, so that a
        rollout step looks all three up at once):
        ``a_rest``: CAE loading deceleration (m/s^2) of each of ``n_c`` conditions on the s grid at
        zero crush speed, ``a_CAE(s) - dadv v_CAE(s) - dadv2 v_CAE(s)^2`` (the CAE curve itself
        without a speed dependence; continued beyond the run's data as :func:`_reference` says);
        ``dadv``, ``dadv2``: its dependence on crush speed at fixed crush,
        ``a_CAE(s, v) = a_rest + dadv v + dadv2 v^2`` (1/s and 1/m).
    a_unload : ndarray, shape (n_c, n_u)
        CAE unloading deceleration (m/s^2) on the u grid (0 beyond the spring-back).
    row : ndarray of int, shape (n,)
        The condition (table row) of each of the ``n`` samples. Samples share their condition's
        tables: a batch of many samples of a few conditions looks up tables that stay in cache.
    mass : ndarray, shape (n,)
        Nominal vehicle mass in kg.
    v0 : ndarray, shape (n,)
        Impact speed in m/s.
    group : ndarray of int, shape (n,)
        Index into ``labels`` (the powertrain label of each condition).
    labels : tuple of str
    """

    s_step: float
    u_step: float
    load_table: np.ndarray
    a_unload: np.ndarray
    row: np.ndarray
    mass: np.ndarray
    v0: np.ndarray
    group: np.ndarray
    labels: tuple

    @classmethod
    def from_curves(cls, curves, mass, group, labels, s_hi: float, faster=None, force_rate=None,
                    n_s: int = N_S, n_u: int = N_U) -> "Plant":
        """Tabulate CAE curves (:class:`crashfuse.method.surrogate.CAECurve`) up to crush ``s_hi`` (m).

        ``faster``, if given, holds per curve a CAE curve of the same vehicle at a higher impact
        speed (or None): the reference beyond the curve's maximum crush (:func:`_reference`).
        ``force_rate``, if given, gives the CAE model's crush force as a quadratic in crush speed
        at fixed crush (:func:`crush_force_rate`: a callable from the crush grid in m to its two
        coefficients, over the nominal mass in the deceleration); the CAE curve moves along it
        from the reference trajectory's own speed. Without it the CAE force depends on crush only.
        """
        s = np.linspace(0.0, s_hi, n_s)
        u_hi = max(c.u_end for c in curves) * 1.05
        u = np.linspace(0.0, u_hi, n_u)
        mass = np.asarray(mass, float)
        faster = [None] * len(curves) if faster is None else faster
        a, v = (np.array(x) for x in zip(*(_reference(c, f, s) for c, f in zip(curves, faster))))
        b1, b2 = (0.0, 0.0) if force_rate is None else force_rate(s)
        dadv, dadv2 = (b / mass[:, None] + np.zeros_like(a) for b in (b1, b2))
        return cls(s[1], u[1], np.stack([a - dadv * v - dadv2 * v ** 2, dadv, dadv2]),
                   np.array([c.unloading(u) for c in curves]), np.arange(len(curves)), mass,
                   np.array([c.v0 for c in curves]),
                   np.asarray(group, int), tuple(labels))

    @property
    def a_rest(self) -> np.ndarray:
        """Per sample, shape (n, n_s)."""
        return self.load_table[0, self.row]

    @property
    def dadv(self) -> np.ndarray:
        """Per sample, shape (n, n_s)."""
        return self.load_table[1, self.row]

    @property
    def dadv2(self) -> np.ndarray:
        """Per sample, shape (n, n_s)."""
        return self.load_table[2, self.row]

    @property
    def s_hi(self) -> float:
        """Crush (m) the loading tables reach."""
        return self.s_step * (self.load_table.shape[2] - 1)

    def subset(self, rows) -> "Plant":
        """The plant of the samples ``rows`` (in that order, repeats allowed), sharing this one's tables."""
        rows = np.asarray(rows, int)
        return dataclasses.replace(self, row=self.row[rows], mass=self.mass[rows], v0=self.v0[rows],
                                   group=self.group[rows])

    def loading(self, s: np.ndarray, v) -> tuple[np.ndarray, np.ndarray]:
        """CAE loading deceleration (m/s^2) of every sample at its own crush ``s`` (m) and crush speed
        ``v`` (m/s), and the same at rest: two arrays of shape (n,), both >= 0."""
        rest, dadv, dadv2 = _take(self.load_table, self.row, *_cell(s / self.s_step, self.load_table.shape[2]))
        speed = dadv * v + dadv2 * v ** 2
        return np.maximum(rest + speed, 0.0), np.maximum(rest, 0.0)


def _reference(curve, faster, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Loading deceleration (m/s^2) and velocity (m/s) of the reference trajectory on ``s`` (m).

    The CAE run's own until it stops; beyond, the ``faster`` curve's (if given) while that still
    moves - a rollout that crushes further than the CAE run meets the structure a faster CAE run
    crushed, not the run's last stiffness continued.
    """
    a, v = curve.loading(s), crush_speed(curve, s)
    if faster is not None:
        beyond = (v == 0.0) & (s > curve.s_max)
        a = np.where(beyond, faster.loading(s), a)
        v = np.where(beyond, crush_speed(faster, s), v)
    return a, v


def crush_speed(curve, s: np.ndarray) -> np.ndarray:
    """Velocity (m/s) of a CAE curve's own rollout at crush ``s`` (m), 0 after it stops.

    From the energy balance ``v^2 = v0^2 - 2 int_0^s a ds`` (trapezoids on ``s``).
    """
    a = curve.loading(s)
    work = np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * np.diff(s))])
    v2 = curve.v0 ** 2 - 2.0 * work
    return np.sqrt(np.maximum(v2, 0.0)) * (np.minimum.accumulate(v2) > 0.0)


def crush_force_rate(runs, s: np.ndarray) -> np.ndarray:
    """The CAE model's crush force as a function of crush speed at fixed crush, from its own runs.

    At each crush ``s`` every run still moving there gives its force ``F_j = M_j a_j(s)`` and its
    crush speed ``v_j(s)`` (its own kinematics). The least-squares fit
    ``F_j = alpha_c + beta_f (front_j - mean) + beta_r (rear_j - mean) + b1(s) v_j + b2(s) v_j^2``
    (one intercept per powertrain/drive configuration, whose packages stack up at different
    crush; the axle masses carry the strength's scaling with the vehicle) separates the speed
    effect from the vehicle's, because a CAE design varies the impact speed independently of the
    vehicle. Every run enters, so the slope is far less noisy than differences of surrogate
    curves; the quadratic term lets the sensitivity change with speed (material rate hardening
    is steepest at low rates), so a rollout slower or faster than its CAE run moves along the
    curve, not along the tangent at the run's speed. Where fewer than :data:`RUNS_PER_COEF` runs per coefficient still
    move (deep crush, reached by fast runs only), the last supported values are held.

    Parameters
    ----------
    runs : sequence of Pulse
        CAE runs (decel in m/s^2, ``meta['powertrain']``, ``meta['drive']`` where known).
    s : ndarray, shape (n_s,)
        Increasing crush grid in m.

    Returns
    -------
    ndarray, shape (2, n_s)
        ``b1`` in N s/m and ``b2`` in N s^2/m^2 (0 where no crush is supported).
    """
    force, speed = np.full((len(runs), s.size), np.nan), np.full((len(runs), s.size), np.nan)
    for j, run in enumerate(runs):
        load = displacement_branches(run).loading
        inside = s <= load.x[-1]
        force[j, inside] = run.mass * np.interp(s[inside], load.x, load.decel)
        speed[j, inside] = np.interp(s[inside], load.x, load.velocity)
    config = [(r.meta.get("powertrain"), r.meta.get("drive")) for r in runs]
    dummies = np.array([[c == k for k in dict.fromkeys(config)] for c in config], float)
    axles = np.array([[r.front_weight, r.rear_weight] for r in runs])
    design = np.hstack([dummies, axles - axles.mean(axis=0)])
    out = np.full((2, s.size), np.nan)
    for i in range(s.size):
        moving = np.isfinite(force[:, i]) & (speed[:, i] > 0.0)
        if moving.sum() >= RUNS_PER_COEF * (design.shape[1] + 2):
            x = np.column_stack([design[moving], speed[moving, i], speed[moving, i] ** 2])
            out[:, i] = np.linalg.lstsq(x, force[moving, i], rcond=None)[0][-2:]
    supported = np.isfinite(out[0])
    if not supported.any():
        return np.zeros((2, s.size))
    last = np.maximum.accumulate(np.where(supported, np.arange(s.size), np.flatnonzero(supported)[0]))
    return out[:, last]


def _cell(pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid index and weight of fractional positions ``pos`` on a table of ``n`` columns (held at the ends)."""
    pos = np.minimum(np.maximum(pos, 0.0), n - 1.000001)  # np.clip: the same, at twice the cost per call
    i = pos.astype(int)
    return i, pos - i


def _take(table: np.ndarray, row: np.ndarray, i: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Linear interpolation of rows ``row`` (n,) of ``table`` (n_c, n_cols), or of each of a stack of
    them (k, n_c, n_cols), at cells ``i`` with weights ``w`` (n,): shape (n,) or (k, n)."""
    n_cols = table.shape[-1]
    flat = table.reshape(*table.shape[:-2], -1)  # a flat take: half the cost of 2-D fancy indexing
    at = row * n_cols + i
    return flat.take(at, axis=-1) * (1.0 - w) + flat.take(at + 1, axis=-1) * w


def parameters(effect: str, labels=("all",), mass_hint: float = 1500.0) -> tuple[Param, ...]:
    """The fitted parameters of ``effect`` with bounds and starting points.

    Parameters
    ----------
    effect : str
        A catalogue name.
    labels : sequence of str
        Powertrain labels of the campaign (``powertrain`` gets a mass and a gap per label).
    mass_hint : float
        Smallest nominal vehicle mass in kg (bounds the powertrain mass at 45 % of it and the
        extra mass at 50 %).
    """
    check_effect(effect)
    if effect == "damping":
        return (_param("damping.c", 10.0, 1e5, (1e3, 1e4), off=30.0), _param("damping.n", 0.5, 3.0, (1.0, 1.0)))
    if effect == "strain_rate":  # off: (v / d)^(1 / q) 1.3e-4 at 15 m/s
        return (_param("strain_rate.d", 1e-2, 1e8, (1e2, 1e4), upper_is_limit=False, off=1e7),
                _param("strain_rate.q", 1.0, 12.0, (3.0, 6.0), off=1.5))
    if effect == "unloading":
        return (_param("unloading.k", 1e5, 1e10, (1e7, 1e8), upper_is_limit=False),  # 1e10: rigid, l0 alone
                _param("unloading.l0", 1e-4, 0.1, (0.003, 0.01)),
                _param("unloading.n", 0.3, 30.0, (1.5, 1.0), upper_is_limit=False))  # 30: an exponential
    if effect == "mass":
        return (_param("mass.extra", 1.0, 0.5 * mass_hint, (50.0, 200.0), off=2.0),
                _param("mass.k_link", 1e4, 1e12, (1e12, 1e6), upper_is_limit=False))  # 1e12: rigid
    per_label = [p for lab in labels for p in (
        _param(f"powertrain.mass[{lab}]", 5.0, 0.45 * mass_hint, (150.0, 250.0)),
        _param(f"powertrain.gap[{lab}]", 0.05, 1.2, (0.35, 0.5), off=1.1))]  # off: beyond any crush
    return (*per_label, _param("powertrain.f_mount", 1e3, 5e5, (5e4, 1e5)),
            _param("powertrain.k_mount", 1e5, 1e8, (5e6, 1e7), upper_is_limit=False))  # stiffer: a sharper step


def _param(name: str, lower: float, upper: float, start: tuple, upper_is_limit: bool = True,
           off: float | None = None) -> Param:
    """A :class:`Param` in the unit of the catalogue quantity :data:`QUANTITIES` declares for ``name``."""
    unit = quantity(name.split("[", 1)[0], QUANTITIES).unit
    return Param(name, unit, lower, upper, start, upper_is_limit, off)


# The compiled rollout reads the laws' parameters from one (n, len(COLUMNS)) matrix and their on/off
# switches from one flag per law, in these orders (``powertrain.mass``/``gap``: the sample's label's).
COLUMNS = ("strain_rate.d", "strain_rate.q", "unloading.k", "unloading.l0", "unloading.n", "damping.c", "damping.n",
           "powertrain.mass", "powertrain.gap", "powertrain.f_mount", "powertrain.k_mount", "mass.extra", "mass.k_link")
LAWS = ("strain_rate", "unloading", "damping", "powertrain", "mass")
# Where a law's parameters first reach a rollout (a rollout with other values is the same up to there):
# from contact, once it unloads (the unloading law), once the crush closes the powertrain's gap (its arrest).
_FROM_START, _FROM_UNLOADING, _FROM_STRIKE = 0, 1, 2
ONSET = {"strain_rate": _FROM_START, "unloading": _FROM_UNLOADING, "damping": _FROM_START,
         "powertrain": _FROM_STRIKE, "mass": _FROM_START}
_COLUMN_ONSET = np.array([ONSET[name.split(".")[0]] for name in COLUMNS], np.int8)
_GAP = COLUMNS.index("powertrain.gap")
_UNLOADING, _SEPARATED = Trajectory.UNLOADING, Trajectory.SEPARATED  # branch codes, as constants compiled in
# Compiled once and cached beside the module; a division by zero gives inf (then a non-finite deceleration
# error), as numpy's arithmetic did, instead of raising inside the loop. The step's parts are inlined.
_compiled = numba.njit(cache=True, error_model="numpy")
_inlined = numba.njit(cache=True, error_model="numpy", inline="always")
_advance, _slowing = _inlined(position_increment), _inlined(velocity_decrement)  # the integrator's own formulas


def simulate(plant: Plant, effects, theta: dict, dt: float, n_steps: int) -> Trajectory:
    """Roll out every row of ``plant`` with CAE + ``effects`` from its impact speed.

    The scheme of :func:`crashfuse.signals.dynamics.rollout` (velocity Verlet, branch switching,
    separation, the barrier's constraints), compiled for these laws and stepped one sample at a time:
    the same numbers as ``rollout(decel_fn(...))`` at a fraction of the cost of a Python loop of small
    array operations.

    Parameters
    ----------
    plant : Plant
        One row per sample.
    effects : collection of str
    theta : dict of str to ndarray, shape (n,)
        Every parameter of ``effects`` (names from :func:`parameters`) per sample, SI.
    dt : float
        Step in s.
    n_steps : int

    Returns
    -------
    crashfuse.signals.dynamics.Trajectory
        ``n`` samples, ``n_steps + 1`` times from contact, step ``dt`` (s).

    Raises
    ------
    InputError
        If the deceleration of a sample is not finite at some step.
    """
    on, p = _law_inputs(plant, effects, theta)
    s, v, a, branch, s_max, bad = _rollout(plant.load_table, plant.a_unload, plant.s_step, plant.u_step, plant.row,
                                           plant.mass, np.asarray(plant.v0, float), on, p, float(dt), int(n_steps))
    if bad >= 0:
        raise InputError(f"the CAE + effects rollout gave a non-finite deceleration at step {bad}", field="theta")
    return Trajectory(np.arange(int(n_steps) + 1) * dt, s, v, a, branch, s_max)


def simulate_shifted(plant: Plant, effects, theta: dict, shifted, dt: float, n_steps: int) -> np.ndarray:
    """The decelerations of :func:`simulate` with each of ``shifted``'s parameters in place of ``theta``
    (a finite-difference Jacobian's columns), at a fraction of as many rollouts: a variant follows the
    ``theta`` rollout, stepped alongside, until a law whose parameters it changes first acts
    (:data:`ONSET`): a per-label powertrain parameter of another label never, one of the arrest once the
    crush closes the gap, one of the unloading once the pulse unloads. The same numbers as
    ``simulate(plant, effects, shifted[c], dt, n_steps).decel``.

    Parameters
    ----------
    plant, effects, theta, dt, n_steps
        As :func:`simulate`.
    shifted : sequence of dict of str to ndarray, shape (n,)
        ``k`` parameter sets like ``theta``.

    Returns
    -------
    ndarray, shape (n, k, n_steps + 1)
        Deceleration in m/s^2 of every sample under every parameter set.

    Raises
    ------
    InputError
        If the deceleration of a sample is not finite at some step.
    """
    on, p = _law_inputs(plant, effects, theta)
    q = np.stack([_law_inputs(plant, effects, t)[1] for t in shifted], axis=1)
    out, bad = _rollout_shifted(plant.load_table, plant.a_unload, plant.s_step, plant.u_step, plant.row, plant.mass,
                                np.asarray(plant.v0, float), on, p, q, _COLUMN_ONSET, float(dt), int(n_steps))
    if bad >= 0:
        raise InputError(f"the CAE + effects rollout gave a non-finite deceleration at step {bad}", field="theta")
    return out


def decel_fn(plant: Plant, effects, theta: dict, dt: float):
    """The deceleration of CAE + ``effects`` at any state, for :func:`crashfuse.signals.dynamics.rollout`
    (the law at chosen states; :func:`simulate` is the fast rollout of the same law).

    Returns
    -------
    callable
        ``State -> ndarray, shape (n,)`` deceleration in m/s^2, called once per step in order (the
        ``mass`` link carries its state from step to step; the same step again repeats it).
    """
    on, p = _law_inputs(plant, effects, theta)
    linked = on[LAWS.index("mass")]
    prev, cur = np.zeros((plant.row.size, 2)), np.zeros((plant.row.size, 2))  # the link's state per sample
    last = -1

    def decel(st: State) -> np.ndarray:
        nonlocal last
        if st.step == 0:
            prev[:] = 0.0
        elif st.step == last + 1:
            prev[:] = cur
        elif st.step != last and linked:
            raise ValueError(f"the mass link is stepped in order; got step {st.step} after {last}")
        last = st.step
        cur[:] = prev
        return np.array([_decel_at(plant.load_table, plant.a_unload, plant.s_step, plant.u_step, plant.row[j],
                                   plant.mass[j], on, p[j], st.s[j], st.v[j], st.u[j], st.s_max[j],
                                   bool(st.loading[j]), cur[j], float(dt)) for j in range(plant.row.size)])
    return decel


def _law_inputs(plant: Plant, effects, theta: dict) -> tuple[np.ndarray, np.ndarray]:
    """The laws' switches (len(LAWS),) and per-sample parameter matrix (n, len(COLUMNS)) (0: law off)."""
    effects = set(effects)
    p = np.zeros((plant.row.size, len(COLUMNS)))
    for j, name in enumerate(COLUMNS):
        if name.split(".")[0] not in effects:
            continue
        per_label = name in ("powertrain.mass", "powertrain.gap")
        p[:, j] = (np.choose(plant.group, [theta[f"{name}[{lab}]"] for lab in plant.labels]) if per_label
                   else theta[name])
    return np.array([law in effects for law in LAWS]), p


@_compiled
def _rollout(load, unload, s_step, u_step, row, mass, v0, on, p, dt, n_steps):
    """:func:`crashfuse.signals.dynamics.rollout` of :func:`_decel_at`, one sample after another (every
    sample's steps in turn: the faster order, tried against all samples at each step).

    Returns s, v, decel, branch (n, n_steps + 1), s_max (n,) and the first step with a non-finite
    deceleration (-1: none).
    """
    m, n = row.size, n_steps + 1
    out_s, out_v, out_a = np.empty((m, n)), np.empty((m, n)), np.empty((m, n))
    out_b, out_max = np.zeros((m, n), np.int8), np.empty(m)
    link = np.zeros(2)
    bad = -1
    for j in range(m):
        s, v, s_max, loading, separated = 0.0, v0[j], 0.0, True, False
        link[:] = 0.0
        a = _decel_at(load, unload, s_step, u_step, row[j], mass[j], on, p[j], 0.0, v, 0.0, 0.0, True, link, dt)
        bad = _earliest(bad, 0, np.isfinite(a))
        out_s[j, 0], out_v[j, 0], out_a[j, 0] = s, v, a
        for i in range(1, n):
            s, v, a, s_max, loading, separated, finite = _step(load, unload, s_step, u_step, row[j], mass[j], on,
                                                               p[j], s, v, a, s_max, loading, separated, link, dt)
            bad = _earliest(bad, i, finite)
            out_s[j, i], out_v[j, i], out_a[j, i] = s, v, a
            if not loading:
                out_b[j, i] = _SEPARATED if separated else _UNLOADING
        out_max[j] = s_max
    return out_s, out_v, out_a, out_b, out_max, bad


@_compiled
def _rollout_shifted(load, unload, s_step, u_step, row, mass, v0, on, p, q, onset, dt, n_steps):
    """The decelerations (n, k, n_steps + 1) of :func:`_rollout` with each sample's parameters ``p[j]``
    replaced by each of ``q[j]`` (k, len(COLUMNS)), and the first step with a non-finite one (-1: none).

    Each sample's ``p`` rollout is stepped alongside: a variant follows it until a law whose parameters
    it changes first acts (:data:`ONSET`) and steps on its own from there, from the state that rollout
    had; up to then every one of its operations is the ``p`` rollout's, so the numbers are the same.
    """
    m, k, n = q.shape[0], q.shape[1], n_steps + 1
    out = np.empty((m, k, n))
    link, var_link = np.zeros(2), np.zeros((k, 2))
    var = np.zeros((k, 4))  # s, v, a, s_max of each variant on its own
    var_flags = np.zeros((k, 2), np.bool_)  # loading, separated
    own, waits = np.zeros(k, np.bool_), np.zeros((k, 2), np.bool_)  # stepping on its own; waiting to unload / strike
    bad = -1
    for j in range(m):
        r, mj, pj = row[j], mass[j], p[j]
        s, v, s_max, loading, separated = 0.0, v0[j], 0.0, True, False
        link[:] = 0.0
        a = _decel_at(load, unload, s_step, u_step, r, mj, on, pj, 0.0, v, 0.0, 0.0, True, link, dt)
        bad = _earliest(bad, 0, np.isfinite(a))
        for c in range(k):
            own[c], waits[c, 0], waits[c, 1] = _onsets(pj, q[j, c], onset)
            out[j, c, 0] = a
            if own[c]:
                var_link[c, :] = 0.0
                var[c, 0], var[c, 1], var[c, 3], var_flags[c, 0], var_flags[c, 1] = 0.0, v, 0.0, True, False
                var[c, 2] = out[j, c, 0] = _decel_at(load, unload, s_step, u_step, r, mj, on, q[j, c], 0.0, v, 0.0,
                                                     0.0, True, var_link[c], dt)
                bad = _earliest(bad, 0, np.isfinite(var[c, 2]))
        following = k - own.sum()
        for i in range(1, n):
            before = (s, v, a, s_max, loading, separated, link[0], link[1])
            if following > 0:  # the p rollout only leads variants: not stepped once none follows it
                s, v, a, s_max, loading, separated, finite = _step(load, unload, s_step, u_step, r, mj, on, pj, s, v,
                                                                   a, s_max, loading, separated, link, dt)
                bad = _earliest(bad, i, finite)
            for c in range(k):
                if not own[c]:
                    struck = waits[c, 1] and s_max > min(pj[_GAP], q[j, c, _GAP])  # by either's powertrain
                    if not (struck or (waits[c, 0] and not loading)):
                        out[j, c, i] = a
                        continue
                    own[c] = True  # leaves the p rollout at this step, from its state before it
                    following -= 1
                    var[c, 0], var[c, 1], var[c, 2], var[c, 3] = before[0], before[1], before[2], before[3]
                    var_flags[c, 0], var_flags[c, 1] = before[4], before[5]
                    var_link[c, 0], var_link[c, 1] = before[6], before[7]
                (var[c, 0], var[c, 1], var[c, 2], var[c, 3], var_flags[c, 0], var_flags[c, 1],
                 finite) = _step(load, unload, s_step, u_step, r, mj, on, q[j, c], var[c, 0], var[c, 1], var[c, 2],
                                 var[c, 3], var_flags[c, 0], var_flags[c, 1], var_link[c], dt)
                bad = _earliest(bad, i, finite)
                out[j, c, i] = var[c, 2]
    return out, bad


@_inlined
def _earliest(bad, i, finite):
    """The first step with a non-finite deceleration so far (-1: none), given step ``i``'s."""
    return i if not finite and (bad < 0 or i < bad) else bad


@_inlined
def _onsets(p, q, onset):
    """Where parameters ``q`` first act differently from ``p`` (one sample's, :data:`COLUMNS`): from the
    start, and whether once it unloads, or once the powertrain strikes (False, False, False: never)."""
    start = unloads = strikes = False
    for col in range(p.size):
        if q[col] != p[col]:
            start = start or onset[col] == _FROM_START
            unloads = unloads or onset[col] == _FROM_UNLOADING
            strikes = strikes or onset[col] == _FROM_STRIKE
    return start, unloads, strikes


@_inlined
def _step(load, unload, s_step, u_step, r, mass, on, p, s, v, a, s_max, loading, separated, link, dt):
    """One step of :func:`_rollout` from ``s, v, a, s_max, loading, separated`` (``link`` advanced in
    place): the same six after it, and whether the deceleration was finite before the barrier's
    constraints."""
    s_new = s + _advance(v, a, dt)
    loading = loading and s_new > s_max  # it stops loading where the displacement does not advance
    if loading:
        s_max = s_new
    a_new = _decel_at(load, unload, s_step, u_step, r, mass, on, p, s_new, v - a * dt,
                      max(s_max - s_new, 0.0), s_max, loading, link, dt)
    finite = np.isfinite(a_new)
    if not loading:  # the barrier cannot pull, and lets go for good
        a_new = 0.0 if separated else max(a_new, 0.0)
    v = v - _slowing(a, a_new, dt)
    if not loading:
        separated = separated or (a_new <= 0.0 and v < 0.0)
    return s_new, v, a_new, s_max, loading, separated, finite


@_inlined
def _decel_at(load, unload, s_step, u_step, r, mass, on, p, s, v, u, s_max, loading, link, dt):
    """One sample's CAE + effects deceleration (m/s^2) at one state: the balance of the module docstring.

    ``r``: the sample's table row; ``p``: its parameters (:data:`COLUMNS`); ``on``: the laws'
    switches (:data:`LAWS`); ``link`` (2,): the extra mass's travel (m) and speed (m/s) relative to
    the body after the previous step, advanced in place to this step's.
    """
    k, w = _at_cell(s / s_step, load.shape[2])
    rest = load[0, r, k] * (1.0 - w) + load[0, r, k + 1] * w
    speed = ((load[1, r, k] * (1.0 - w) + load[1, r, k + 1] * w) * v
             + (load[2, r, k] * (1.0 - w) + load[2, r, k + 1] * w) * (v * v))
    force = mass * max(rest + speed, 0.0)
    if on[0]:  # strain_rate
        force = force + mass * max(rest, 0.0) * (max(v, 0.0) / p[0]) ** (1.0 / p[1])
    if not loading:
        k, w = _at_cell(s_max / s_step, load.shape[2])
        f_max = mass * max(load[0, r, k] * (1.0 - w) + load[0, r, k + 1] * w, 0.0)  # static force at maximum crush
        if on[1]:  # unloading
            force = f_max * min(max(1.0 - u / (p[4] * _decay_length(p[3], p[2], f_max)), 0.0), 1.0) ** p[4]
        else:
            unl0 = max(unload[r, 0], 1e-9)
            k, w = _at_cell(u / max(f_max / (mass * unl0), 1e-6) / u_step, unload.shape[1])
            force = f_max * (unload[r, k] * (1.0 - w) + unload[r, k + 1] * w) / unl0
    body = mass
    if on[2]:  # damping
        force = force + _damping_force(p[5], p[6], v)
    if on[3]:  # powertrain
        struck = s_max > p[8]
        peak = min(p[9], p[10] * max(s_max - p[8], 0.0))
        force = force + ((peak if loading else max(peak - p[10] * u, 0.0)) if struck else 0.0)
        body = body - (p[7] if struck else 0.0)
    if on[4]:  # mass
        force = force - _link_force(p[11], p[12], body, force, link, dt)
    return force / body


@_inlined
def _link_force(m, k, body, f, link, dt):
    """The ``mass`` law's link force on the body (N, forward; it lowers the deceleration) for an extra
    mass ``m`` (kg) on a link of stiffness ``k`` (N/m), with the body of mass ``body`` under the other
    forces ``f`` (N); ``link`` = (travel z, speed w) relative to the body, advanced in place.

    The link force ``L = k z + c w`` is implicit: with the body's deceleration ``a = (F - L) / M``,
    ``w1 = w0 + dt (F / M - L / mu)`` (``1 / mu = 1 / m + 1 / M``) and ``z1 = z0 + dt w1`` solve to
    ``L = mu [z0 + g (w0 + dt F / M)] / [mu / k + g dt]``, ``g = dt + c / k``. As ``k`` grows
    ``L -> mu F / M`` from rest: the rigid ``a = F / (M + m)``.
    """
    g = dt + 2.0 * LINK_DAMPING_RATIO * np.sqrt(m / k)  # dt + c / k
    mu = m * body / (m + body)
    drive = link[1] + dt * f / body
    pull = (link[0] + g * drive) / (mu / k + g * dt)  # L / mu: finite for m = 0
    w1 = drive - dt * pull
    link[0], link[1] = link[0] + dt * w1, w1
    return mu * pull


@_inlined
def _at_cell(pos, n):
    """:func:`_cell` of one position."""
    pos = min(max(pos, 0.0), n - 1.000001)
    i = int(pos)
    return i, pos - i


@_inlined
def _damping_force(c, n, v):
    return c * V_REF * np.sign(v) * np.abs(v / V_REF) ** n


@_inlined
def _decay_length(l0, k, peak_force):
    return l0 + peak_force / k


def damping_force(params: dict, v):
    """The ``damping`` law's force in N at crush speed ``v`` (m/s, negative on unloading):
    ``c V_REF sign(v) |v / V_REF|^n``, ``c v`` for ``n = 1``."""
    return _damping_force(params["damping.c"], params["damping.n"], v)


def decay_length(params: dict, peak_force):
    """The ``unloading`` law's initial decay length ``l0 + F_m / k`` in m after a peak force ``F_m`` (N):
    the crush over which the force would reach zero at the rate it starts to fall."""
    return _decay_length(params["unloading.l0"], params["unloading.k"], peak_force)


def curve_plant(curves, masses, labels_of, s_hi: float, faster=None, force_rate=None) -> Plant:
    """A :class:`Plant` from CAE curves, nominal masses (kg), each curve's powertrain label and,
    optionally, faster curves and the CAE force's rate sensitivity (:meth:`Plant.from_curves`)."""
    labels = tuple(sorted(set(labels_of)))
    group = [labels.index(lab) for lab in labels_of]
    return Plant.from_curves(list(curves), masses, group, labels, s_hi, faster, force_rate)


def headline(effect: str, params: dict) -> dict:
    """The catalogue's headline quantities of ``effect`` from its fitted parameters.

    Where two parameters trade off against each other, the headline is the combination the data
    fix: ``strain_rate``: the force increase at the crush speed :data:`~crashfuse.catalogue.V_REF`,
    ``(V_REF / d)^(1/q)``; ``unloading``: the elastic spring-back from a peak force
    :data:`~crashfuse.catalogue.F_REF`, ``n (l0 + F_REF / k)``. Others: the effect's defining
    parameter (``powertrain``: the arrested mass of each label).

    Returns
    -------
    dict
        ``{reported name: value}`` (:func:`crashfuse.catalogue.key`).
    """
    check_effect(effect)
    if effect == "strain_rate":
        return {key(effect, "gain_at_15mps"): (V_REF / params["strain_rate.d"]) ** (1.0 / params["strain_rate.q"])}
    if effect == "unloading":
        return {key(effect, "springback_at_500kN"): params["unloading.n"] * decay_length(params, F_REF)}
    if effect == "powertrain":
        return {k: v for k, v in params.items() if k.startswith("powertrain.mass[")}
    name = {"damping": "c", "mass": "extra"}[effect]
    return {key(effect, name): params[f"{effect}.{name}"]}
