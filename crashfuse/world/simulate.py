"""Vectorised full-frontal rigid-barrier simulators: the CAE model and the physical test.

Both integrate the paper's Eq. 4, ``M dv/dt = -F``, for many runs at once (numpy arrays of runs
advanced together with one fixed step) with the semi-implicit Euler scheme
``v <- v - (F / M) dt; s <- s + v dt``. The CAE side is one mass on the staged crush spring of
:mod:`crashfuse.world.vehicle`; the physical-test side adds the catalogue effects of
:mod:`crashfuse.world.effects` that the side carries. The state per run is

``s, v``      body crush (m) and forward velocity (m/s);
``s_max``     maximum crush so far (m) and ``f_max`` the static force there (N) - the history the
              unloading rules need;
``x_p, v_p``  powertrain travel (m) and velocity (m/s), and ``u_pl`` the plastic set of its mounts
              (m) - the powertrain's own state (``powertrain`` effect only).

The contact force is ``F = max(0, F_crush + F_damping)`` (a rigid barrier can push, not pull).
The body deceleration is ``(F + F_mount) / M_body`` where ``F_mount`` is the force the powertrain
mounts take from the body (zero without the ``powertrain`` effect, where ``M_body = M``).

Measurement (tests only, :func:`measure`): the body deceleration passes through the accelerometer's
mounting resonance (base-excited single-degree-of-freedom seat,
``H(s) = (2 zeta w s + w^2) / (s^2 + 2 zeta w s + w^2)``, w = 2 pi f_res), gets white noise of
``noise`` m/s^2 rms at the raw rate, and is CFC 60 filtered with pre-trigger lead-in, then
decimated to the campaign rate. CAE pulses get the same CFC 60 processing without resonance and
noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import signal

from crashfuse.errors import InputError
from crashfuse.signals.filters import cfc_filter
from crashfuse.world.vehicle import loading_force, stack_onset, strength

RAW_RATE = 25_000.0  # Hz, integration and raw acquisition rate
OUT_RATE = 12_500.0  # Hz, campaign sampling rate
DURATION = 0.100  # s, campaign record length after contact
PRETRIGGER = 0.020  # s, zero-motion lead-in before contact for the filter
TAIL = 0.020  # s, simulated beyond the record so the filter's end effects are cropped away
DAMPING_RAMP = 0.02  # m, crush over which viscous damping builds up

MEASUREMENT = {
    "measurement.noise": 1.4,  # m/s^2 rms white noise at the raw rate: 10146 shows 0.90 at 10 kHz before impact
    "measurement.f_res": 110.0,  # Hz, accelerometer mounting resonance (seat crossmember)
    "measurement.zeta_res": 0.10,  # -, its damping ratio
}


@dataclasses.dataclass(frozen=True)
class Runs:
    """Impact conditions of n runs (arrays of shape (n,), SI).

    Attributes
    ----------
    v0 : ndarray
        Impact speed in m/s.
    front, rear : ndarray
        Front and rear axle masses in kg (nominal test weight).
    type2 : ndarray of bool
        Type II powertrain (else Type I).
    awd : ndarray of bool
        All-wheel drive (else FWD).
    """

    v0: np.ndarray
    front: np.ndarray
    rear: np.ndarray
    type2: np.ndarray
    awd: np.ndarray

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, np.atleast_1d(np.asarray(getattr(self, f.name))))


def body_decel(runs: Runs, effects, params: dict, t_end: float, rate: float = RAW_RATE) -> np.ndarray:
    """Integrate the vehicle body from contact to ``t_end``.

    Parameters
    ----------
    runs : Runs
        n impact conditions.
    effects : collection of str
        Catalogue effects this side carries (empty: the CAE model, Eq. 4).
    params : dict
        ``vehicle.*`` and ``effect.param`` values in SI.
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
    n, m = runs.v0.size, int(round(t_end * rate)) + 1
    extra = p["mass.extra"] if "mass" in effects else 0.0
    mass = runs.front + runs.rear + extra
    lam = strength(runs.front, p)
    s_stack = stack_onset(runs.type2, p)
    pt = _Powertrain(runs, p) if "powertrain" in effects else None
    m_body = mass - (pt.mass if pt else 0.0)
    if np.any(m_body < 0.5 * mass):
        raise InputError("expected a powertrain mass below half the vehicle mass", field="powertrain.mass_type1/2")
    if pt and np.any(pt.gap <= 0):
        raise InputError("expected gap_type1/2 > gap_awd (a positive powertrain gap)", field="powertrain.gap_awd")
    s, v = np.zeros(n), runs.v0.astype(float).copy()
    s_max, f_max = np.zeros(n), np.zeros(n)
    out = np.empty((n, m))
    for k in range(m):
        f_static = loading_force(s, lam, s_stack, p)
        loading = s >= s_max
        f_max = np.where(loading, f_static, f_max)
        f = np.where(loading, f_static * _rate_factor(v, effects, p), _unloading(s, s_max, f_max, effects, p))
        if "damping" in effects:
            f = f + p["damping.c"] * v * np.clip(s / DAMPING_RAMP, 0.0, 1.0)
        f = np.maximum(f, 0.0) + (pt.step(s, v, dt) if pt else 0.0)
        out[:, k] = f / m_body
        v = v - out[:, k] * dt
        s = s + v * dt
        s_max = np.maximum(s_max, s)
    return out


def _rate_factor(v: np.ndarray, effects, p: dict):
    """Cowper-Symonds-like factor 1 + (sdot / D)^(1/q) on the loading branch (1 without the effect)."""
    if "strain_rate" not in effects:
        return 1.0
    return 1.0 + (np.maximum(v, 0.0) / p["strain_rate.d"]) ** (1.0 / p["strain_rate.q"])


def _unloading(s, s_max, f_max, effects, p: dict) -> np.ndarray:
    """Force in N on the unloading/reloading branch below the maximum crush ``s_max``."""
    if "unloading" not in effects:
        return np.maximum(f_max - p["vehicle.k_unload"] * (s_max - s), 0.0)
    delta = p["unloading.d0"] + f_max / p["unloading.k"]
    frac = np.clip((s - s_max + delta) / np.maximum(delta, 1e-12), 0.0, 1.0)
    return f_max * frac ** p["unloading.n"]


class _Powertrain:
    """The powertrain as a second mass on elastic-plastic mounts (the ``powertrain`` effect).

    Positions are forward travel since contact, like the body crush; the powertrain starts
    with the body's speed and no mount load.
    """

    def __init__(self, runs: Runs, p: dict):
        self.p = p
        self.mass = np.where(runs.type2, p["powertrain.mass_type2"], p["powertrain.mass_type1"])
        self.mass = self.mass + np.where(runs.awd, p["powertrain.mass_awd"], 0.0)
        gap = np.where(runs.type2, p["powertrain.gap_type2"], p["powertrain.gap_type1"])
        self.gap = gap - np.where(runs.awd, p["powertrain.gap_awd"], 0.0)
        self.x = np.zeros(runs.v0.size)
        self.v = runs.v0.astype(float).copy()
        self.u_pl = np.zeros(runs.v0.size)

    def step(self, s: np.ndarray, v: np.ndarray, dt: float) -> np.ndarray:
        """Advance the powertrain one step; return the mount force on the body in N (rearward +)."""
        p = self.p
        trial = p["powertrain.k_mount"] * (s - self.x - self.u_pl)
        elastic = np.clip(trial, -p["powertrain.f_mount"], p["powertrain.f_mount"])
        self.u_pl = s - self.x - elastic / p["powertrain.k_mount"]
        # The damped mount force is capped too: a yielded bracket carries no more than f_mount.
        cap = p["powertrain.f_mount"]
        mount = np.clip(elastic + p["powertrain.c_mount"] * (v - self.v), -cap, cap)
        pen = self.x - self.gap
        contact = np.where(pen > 0, np.maximum(p["powertrain.k_contact"] * pen + p["powertrain.c_contact"] * self.v,
                                               0.0), 0.0)
        self.v = self.v + (mount - contact) / self.mass * dt
        self.x = self.x + self.v * dt
        return mount


def _resonance(fs: float, p: dict):
    """Digital (bilinear) base-excited SDOF seat: coefficients (b, a) for ``lfilter``."""
    w = 2 * np.pi * p["measurement.f_res"]
    z = p["measurement.zeta_res"]
    return signal.bilinear([2 * z * w, w * w], [1.0, 2 * z * w, w * w], fs=fs)


def measure(raw: np.ndarray, params: dict, rngs, rate: float = RAW_RATE) -> np.ndarray:
    """A lab's processing of raw body decelerations into campaign pulses.

    Parameters
    ----------
    raw : ndarray, shape (n, m)
        Body deceleration in m/s^2 from contact at ``rate`` Hz (see :func:`body_decel`).
    params : dict
        ``measurement.*`` values.
    rngs : sequence of numpy Generator or None
        One generator per run for the accelerometer noise; None means a noise-free CAE output
        (no resonance, no noise, CFC 60 only).
    rate : float
        Raw rate in Hz (a multiple of :data:`OUT_RATE`).

    Returns
    -------
    ndarray, shape (n, DURATION * OUT_RATE + 1)
        CFC 60 deceleration in m/s^2 at :data:`OUT_RATE` over t = 0 .. DURATION inclusive.
    """
    lead = int(round(PRETRIGGER * rate))
    x = np.concatenate([np.zeros((raw.shape[0], lead)), raw], axis=1)
    if rngs is not None:
        x = signal.lfilter(*_resonance(rate, params), x, axis=1)
        x = x + params["measurement.noise"] * np.stack([g.standard_normal(x.shape[1]) for g in rngs])
    x = cfc_filter(x, 1.0 / rate, 60, axis=1)[:, lead:]
    step = int(round(rate / OUT_RATE))
    return x[:, ::step][:, : int(round(DURATION * OUT_RATE)) + 1]


def simulate(runs: Runs, effects, params: dict, rngs=None) -> np.ndarray:
    """Campaign pulses: CFC 60 deceleration in m/s^2, shape (n, 1251), 12.5 kHz over 0-100 ms.

    ``rngs`` (one Generator per run) switches on the test's measurement chain; None gives CAE output.
    """
    raw = body_decel(runs, effects, params, DURATION + TAIL)
    return measure(raw, params, rngs)
