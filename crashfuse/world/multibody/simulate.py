"""Vectorised simulators of the second world: the three-mass vehicle, the test lab and the CAE output.

Equations of motion (forward positive, every mass starting at v0 when the front touches the
barrier at t = 0; :mod:`.structure` for the forces, :mod:`.effects` for the effect terms)::

    m_f v_f' = P - B                      front structure against the barrier
    m_b v_b' = -P + F_m + F_a             body (accelerometer)
    m_e v_e' = -F_m - C                   engine on its mounts (C: ``powertrain`` contact)
    m_a v_a' = -F_a                       attached mass (``mass`` effect only)

with the crush-zone force ``P = max(0, P_branch + F_d)`` (loading branch ``P(c)`` times the rate
factor, or the unloading law below ``c_max``; ``F_d`` the ``damping`` term), the engine-mount force
``F_m`` and the attached-mass link force ``F_a`` (both spring-dampers pulling their mass towards
the body). The body's deceleration ``(P - F_m - F_a) / m_b`` is the pulse. All runs are advanced
together with the semi-implicit Euler step ``v <- v + v' dt; x <- x + v dt`` at :data:`RAW_RATE`.

Outputs:

* tests (:func:`measure_tests`): accelerometer mounting resonance (bilinear base-excited SDOF),
  pink noise band-limited to ``f_lo``-``f_hi`` Hz, a per-test zero offset, SAE J211 CFC 60 with a
  pre-trigger lead-in, sampled at :data:`TEST_RATE` over 0 .. :data:`DURATION`;
* CAE (:func:`cae_output`): the body deceleration as a CAE code writes its history output - raw,
  unfiltered, every ``RAW_RATE / CAE_RATE``-th step, from :data:`CAE_LEAD` before contact (zeros) to
  :data:`CAE_DURATION`. The campaign marks these rows ``cfc = raw``; the reader filters them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import signal

from crashfuse.errors import InputError
from crashfuse.signals.filters import cfc_filter
from crashfuse.world.multibody.structure import block_onset, crush_force, strength

RAW_RATE = 20_000.0  # Hz, integration rate and the lab's raw acquisition rate
TEST_RATE = 10_000.0  # Hz, tests as delivered (CFC 60)
CAE_RATE = 10_000.0  # Hz, CAE history output interval 0.1 ms
DURATION = 0.100  # s, test record after contact
CAE_DURATION = 0.120  # s, CAE termination time
CAE_LEAD = 0.010  # s, CAE output before contact (at rest relative to the barrier: zero deceleration)
PRETRIGGER = 0.020  # s, the lab's lead-in before contact for the filter
TAIL = 0.020  # s, simulated beyond the test record, cropped after filtering
DAMPING_RAMP = 0.10  # m, crush over which the crush damping builds up (the bumper beam)

MEASUREMENT = {
    "measurement.f_res": 160.0,  # Hz, accelerometer mounting resonance
    "measurement.zeta_res": 0.05,  # -, its damping ratio
    "measurement.noise": 1.2,  # m/s^2 rms, pink noise at the raw rate
    "measurement.f_lo": 2.0,  # Hz, pink noise band
    "measurement.f_hi": 4000.0,  # Hz
    "measurement.offset": 0.15,  # m/s^2, rms of a test's zero offset
}


@dataclasses.dataclass(frozen=True)
class Runs:
    """Impact conditions of n runs (arrays of shape (n,), SI): speed m/s, axle masses kg, configuration."""

    v0: np.ndarray
    front: np.ndarray
    rear: np.ndarray
    type2: np.ndarray
    awd: np.ndarray

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, np.atleast_1d(np.asarray(getattr(self, f.name))))


class _State:
    """Positions (m) and velocities (m/s) of the masses, and the crush history, for n runs."""

    def __init__(self, v0: np.ndarray):
        zero = np.zeros(v0.size)
        self.x_f, self.x_b, self.x_e, self.x_a = zero.copy(), zero.copy(), zero.copy(), zero.copy()
        self.v_f, self.v_b, self.v_e, self.v_a = (v0.astype(float).copy() for _ in range(4))
        self.c_max, self.p_max = zero.copy(), zero.copy()


def _engine_mass(runs: Runs, p: dict) -> np.ndarray:
    mass = np.where(runs.type2, p["engine.mass_type2"], p["engine.mass_type1"])
    return mass + np.where(runs.awd, p["engine.mass_awd"], 0.0)


def _gap(runs: Runs, p: dict) -> np.ndarray:
    gap = np.where(runs.type2, p["powertrain.gap_type2"], p["powertrain.gap_type1"])
    return gap - np.where(runs.awd, p["powertrain.gap_awd"], 0.0)


def body_decel(runs: Runs, effects, params: dict, t_end: float, rate: float = RAW_RATE) -> np.ndarray:
    """Integrate the vehicle from contact to ``t_end``.

    Parameters
    ----------
    runs : Runs
        n impact conditions.
    effects : collection of str
        Catalogue effects this side carries (empty: the base three-mass model).
    params : dict
        ``structure.*``, ``front.*``, ``engine.*`` and ``effect.param`` values in SI.
    t_end : float
        End time in s.
    rate : float
        Integration rate in Hz.

    Returns
    -------
    ndarray, shape (n, m)
        Body deceleration in m/s^2 (positive while slowing) at t = k / rate, k = 0..m-1.
    """
    p, dt = params, 1.0 / rate
    m_e, m_f = _engine_mass(runs, p), p["front.mass"]
    m_b = runs.front + runs.rear - m_f - m_e
    if np.any(m_b < 0.5 * (runs.front + runs.rear)):
        raise InputError("expected front and engine masses below half the vehicle mass", field="engine.mass_type1/2")
    gap = _gap(runs, p) if "powertrain" in effects else None
    if gap is not None and np.any(gap <= 0):
        raise InputError("expected gap_type1/2 > gap_awd (a positive engine gap)", field="powertrain.gap_awd")
    lam, c_block = strength(runs.front, p), block_onset(runs.type2, p)
    st = _State(runs.v0)
    out = np.empty((runs.v0.size, int(round(t_end * rate)) + 1))
    for k in range(out.shape[1]):
        crush = _crush_zone(st, lam, c_block, effects, p)
        barrier = np.where(st.x_f > 0, np.maximum(p["front.k_barrier"] * st.x_f + p["front.c_barrier"] * st.v_f, 0.0),
                           0.0)
        mount = _mount(st, p)
        contact = _engine_contact(st, gap, p) if gap is not None else 0.0
        link = _link(st, p) if "mass" in effects else 0.0
        out[:, k] = (crush - mount - link) / m_b
        st.v_f = st.v_f + (crush - barrier) / m_f * dt
        st.v_b = st.v_b - out[:, k] * dt
        st.v_e = st.v_e - (mount + contact) / m_e * dt
        if "mass" in effects:
            st.v_a = st.v_a - link / p["mass.m"] * dt
        for x, v in (("x_f", "v_f"), ("x_b", "v_b"), ("x_e", "v_e"), ("x_a", "v_a")):
            setattr(st, x, getattr(st, x) + getattr(st, v) * dt)
    return out


def _crush_zone(st: _State, lam, c_block, effects, p: dict) -> np.ndarray:
    """Crush-zone force P in N (compressive >= 0); updates the crush history."""
    c, rate = st.x_b - st.x_f, st.v_b - st.v_f
    static = crush_force(c, lam, c_block, p)
    loading = c >= st.c_max
    st.c_max = np.where(loading, c, st.c_max)
    st.p_max = np.where(loading, static, st.p_max)
    force = np.where(loading, static * _rate_factor(rate, effects, p), _unloading(st.c_max - c, st.p_max, effects, p))
    if "damping" in effects:
        force = force + p["damping.c2"] * rate * np.abs(rate) * np.clip(c / DAMPING_RAMP, 0.0, 1.0)
    return np.maximum(force, 0.0)


def _rate_factor(rate: np.ndarray, effects, p: dict):
    """Power-law rate hardening 1 + a (c' / v_ref)^p on the loading branch (1 without the effect)."""
    if "strain_rate" not in effects:
        return 1.0
    return 1.0 + p["strain_rate.a"] * (np.maximum(rate, 0.0) / p["strain_rate.v_ref"]) ** p["strain_rate.p"]


def _unloading(r: np.ndarray, p_max: np.ndarray, effects, p: dict) -> np.ndarray:
    """Force in N at spring-back ``r = c_max - c`` >= 0 below the largest crush."""
    if "unloading" not in effects:
        return np.maximum(p_max - p["structure.k_unload"] * r, 0.0)
    delta = p["unloading.d0"] + p_max / p["unloading.k"]
    floor = np.exp(-p["unloading.set_ratio"])
    return p_max * np.maximum(np.exp(-r / delta) - floor, 0.0) / (1.0 - floor)


def _mount(st: _State, p: dict) -> np.ndarray:
    """Progressive engine-mount force in N pulling the engine towards the body (+ when it leads)."""
    d = st.x_e - st.x_b
    return p["engine.k_mount"] * d * (1.0 + (d / p["engine.d_mount"]) ** 2) + p["engine.c_mount"] * (st.v_e - st.v_b)


def _engine_contact(st: _State, gap: np.ndarray, p: dict) -> np.ndarray:
    """Compression-only engine-to-barrier contact force in N once the engine has travelled its gap."""
    pen = st.x_e - gap
    push = p["powertrain.k_contact"] * pen + p["powertrain.c_contact"] * st.v_e
    return np.where(pen > 0, np.maximum(push, 0.0), 0.0)


def _link(st: _State, p: dict) -> np.ndarray:
    """Attached-mass link force in N pulling that mass towards the body (+ when it leads)."""
    return p["mass.k"] * (st.x_a - st.x_b) + p["mass.c"] * (st.v_a - st.v_b)


def _resonance(fs: float, p: dict):
    """Digital (bilinear) base-excited SDOF accelerometer seat: ``(b, a)`` for ``lfilter``."""
    w, z = 2 * np.pi * p["measurement.f_res"], p["measurement.zeta_res"]
    return signal.bilinear([2 * z * w, w * w], [1.0, 2 * z * w, w * w], fs=fs)


def pink_noise(rng: np.random.Generator, n: int, rms: float, band: tuple, rate: float) -> np.ndarray:
    """Pink (1/f power) noise of ``rms`` over ``band`` Hz, ``n`` samples at ``rate`` Hz."""
    spectrum = np.fft.rfft(rng.standard_normal(n))
    f = np.fft.rfftfreq(n, 1.0 / rate)
    inside = (f >= band[0]) & (f <= band[1])
    spectrum = np.where(inside, spectrum / np.sqrt(np.where(inside, f, 1.0)), 0.0)
    x = np.fft.irfft(spectrum, n)
    return x * (rms / max(float(np.sqrt(np.mean(x * x))), 1e-300))


def measure_tests(raw: np.ndarray, params: dict, rngs, rate: float = RAW_RATE) -> np.ndarray:
    """The lab's chain from body deceleration to delivered test pulses.

    Parameters
    ----------
    raw : ndarray, shape (n, m)
        Body deceleration in m/s^2 from contact at ``rate`` Hz (:func:`body_decel`).
    params : dict
        ``measurement.*`` values.
    rngs : sequence of numpy Generator
        One per run: its noise and zero offset.
    rate : float
        Raw rate in Hz, a multiple of :data:`TEST_RATE`.

    Returns
    -------
    ndarray, shape (n, DURATION * TEST_RATE + 1)
        CFC 60 deceleration in m/s^2 at :data:`TEST_RATE` over t = 0 .. DURATION inclusive.
    """
    p, lead = params, int(round(PRETRIGGER * rate))
    x = np.concatenate([np.zeros((raw.shape[0], lead)), raw], axis=1)
    x = signal.lfilter(*_resonance(rate, p), x, axis=1)
    band = (p["measurement.f_lo"], p["measurement.f_hi"])
    for row, g in zip(x, rngs):
        row += pink_noise(g, row.size, p["measurement.noise"], band, rate) + p["measurement.offset"] * g.standard_normal()
    x = cfc_filter(x, 1.0 / rate, 60, axis=1)[:, lead:]
    step = int(round(rate / TEST_RATE))
    return x[:, ::step][:, : int(round(DURATION * TEST_RATE)) + 1]


def cae_output(raw: np.ndarray, rate: float = RAW_RATE) -> tuple[np.ndarray, np.ndarray]:
    """CAE history output: raw decelerations every ``rate / CAE_RATE`` steps with the pre-contact lead.

    Returns
    -------
    time : ndarray, shape (m,)
        s, from ``-CAE_LEAD`` to ``CAE_DURATION``.
    decel : ndarray, shape (n, m)
        m/s^2, unfiltered.
    """
    step, lead = int(round(rate / CAE_RATE)), int(round(CAE_LEAD * CAE_RATE))
    decel = raw[:, ::step][:, : int(round(CAE_DURATION * CAE_RATE)) + 1]
    decel = np.concatenate([np.zeros((raw.shape[0], lead)), decel], axis=1)
    return (np.arange(decel.shape[1]) - lead) / CAE_RATE, decel


def simulate_tests(runs: Runs, effects, params: dict, rngs) -> np.ndarray:
    """Delivered test pulses: CFC 60 m/s^2, shape (n, 1001), 10 kHz over 0-100 ms."""
    return measure_tests(body_decel(runs, effects, params, DURATION + TAIL), params, rngs)


def simulate_cae(runs: Runs, effects, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """Raw CAE pulses ``(time, decel)`` as :func:`cae_output` gives them."""
    return cae_output(body_decel(runs, effects, params, CAE_DURATION))
