"""Time <-> displacement: the one integrator, and the loading/unloading branches of a pulse.

The integrator (paper Eq. 7, used again by the rollout of Eq. 23) is velocity Verlet with the
deceleration ``a`` positive while slowing, ``s_0 = 0`` and ``v_0`` the impact speed::

    s_i = s_{i-1} + v_{i-1} dt - a_{i-1} dt^2 / 2
    v_i = v_{i-1} - (a_{i-1} + a_i) dt / 2

Why this one: the paper's Eq. 7 is explicit Euler, first order: on NHTSA test 10146 (CFC 180,
10 kHz) its maximum crush is 1.6 mm longer than Verlet's and moves by another 1.6 mm when the
step is doubled, where Verlet's moves by 0.0003 mm. And the paper's Eq. 5/23 index the
update differently from Eq. 7 (Eq. 23 uses the new acceleration for the velocity, Eq. 7 the old),
so data converted with one and predictions rolled out with the other would disagree before any
model error: one integrator serves both. Velocity Verlet is second order, its
velocity is exactly the trapezoidal integral of the sampled deceleration (the usual way to
integrate a sampled pulse), its displacement is consistent with that velocity, and it stays explicit in
a rollout because the new deceleration ``a_i = G(s_i, ...)`` depends on the new position only.

:func:`kinematics` (a whole record, vectorised) and :func:`position_step` /
:func:`velocity_step` (one step over an array of Monte Carlo samples) evaluate the same
increments in the same order, so they agree bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from crashfuse.errors import InputError
from crashfuse.signals.pulse import Pulse


def position_increment(v, a_prev, dt):
    """``v dt - a_prev dt^2 / 2`` (m): the displacement of one step (also compiled, crashfuse.method.laws)."""
    return v * dt - a_prev * (0.5 * dt * dt)


def velocity_decrement(a_prev, a_new, dt):
    """``(a_prev + a_new) dt / 2`` (m/s): the velocity lost in one step (also compiled, crashfuse.method.laws)."""
    return (a_prev + a_new) * (0.5 * dt)


def position_step(s, v, a_prev, dt: float):
    """Displacement one step on: ``s + v dt - a_prev dt^2 / 2``.

    Parameters
    ----------
    s, v, a_prev : float or ndarray, shape (m,)
        Displacement (m), velocity (m/s) and deceleration (m/s^2, positive slowing) now, for one
        or ``m`` Monte Carlo samples.
    dt : float
        Time step in s.

    Returns
    -------
    float or ndarray, shape (m,)
        Displacement in m at the next step.
    """
    return s + position_increment(v, a_prev, dt)


def velocity_step(v, a_prev, a_new, dt: float):
    """Velocity one step on: ``v - (a_prev + a_new) dt / 2`` (trapezoidal).

    Parameters
    ----------
    v, a_prev, a_new : float or ndarray, shape (m,)
        Velocity now (m/s) and the decelerations now and at the next step (m/s^2).
    dt : float
        Time step in s.

    Returns
    -------
    float or ndarray, shape (m,)
        Velocity in m/s at the next step.
    """
    return v - velocity_decrement(a_prev, a_new, dt)


def kinematics(decel, dt: float, v0) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and displacement of whole records by velocity Verlet (``s_0 = 0``, ``v_0 = v0``).

    Parameters
    ----------
    decel : array_like, shape (..., n)
        Deceleration samples in m/s^2, positive while slowing, every ``dt`` from contact on.
    dt : float
        Sampling interval in s.
    v0 : float or array_like, shape (...)
        Impact speed(s) in m/s, broadcast against ``decel.shape[:-1]``.

    Returns
    -------
    velocity : ndarray, shape (..., n)
        Forward velocity in m/s.
    displacement : ndarray, shape (..., n)
        Forward travel since contact in m (the crush while the vehicle is on the barrier).
    """
    a = np.asarray(decel, dtype=float)
    if a.ndim == 0 or a.shape[-1] < 1:
        raise InputError(f"expected at least one deceleration sample, got shape {a.shape}", field="decel")
    v0 = np.broadcast_to(np.asarray(v0, dtype=float)[..., None], a.shape[:-1] + (1,))
    # cumsum adds left to right, in the order the step functions do, so both agree bit for bit.
    v = np.cumsum(np.concatenate([v0, -velocity_decrement(a[..., :-1], a[..., 1:], dt)], axis=-1), axis=-1)
    ds = position_increment(v[..., :-1], a[..., :-1], dt)
    s = np.cumsum(np.concatenate([np.zeros_like(v0), ds], axis=-1), axis=-1)
    return v, s


@dataclasses.dataclass(frozen=True)
class Branch:
    """One monotonic branch of a pulse in the displacement domain.

    Attributes
    ----------
    x : ndarray, shape (k,)
        Strictly increasing branch coordinate in m: the displacement ``s`` on the loading branch,
        ``u = s_max - s`` on the unloading branch.
    decel : ndarray, shape (k,)
        Deceleration at those samples in m/s^2.
    time : ndarray, shape (k,)
        Their times in s.
    velocity : ndarray, shape (k,)
        Their velocities in m/s.
    """

    x: np.ndarray
    decel: np.ndarray
    time: np.ndarray
    velocity: np.ndarray


@dataclasses.dataclass(frozen=True)
class Branches:
    """Loading and unloading branches of a pulse (see :func:`displacement_branches`).

    Attributes
    ----------
    loading : Branch
        Contact to maximum crush, coordinate ``s`` from 0 to ``s_max``.
    unloading : Branch or None
        Rebound after maximum crush, coordinate ``u = s_max - s``; None if the vehicle never stops.
    s_max : float
        Maximum displacement reached (m); if ``stopped`` is False, the last displacement only.
    t_stop : float or None
        Time of zero velocity in s (linear interpolation between samples), None if never reached.
    stopped : bool
        Whether the velocity reached zero within the record.
    """

    loading: Branch
    unloading: Branch | None
    s_max: float
    t_stop: float | None
    stopped: bool


def displacement_branches(pulse: Pulse) -> Branches:
    """Split a pulse into its loading and unloading branches in the displacement domain.

    The pulse is cropped at contact (:meth:`Pulse.after_contact`) and integrated with
    :func:`kinematics`. The loading branch runs from contact to the sample of maximum
    displacement before the first velocity zero; the unloading branch from there to the next
    velocity reversal (the vehicle moving forward again, a second reversal) or the end of the
    record. Noise can make a few samples step back along a branch; only samples that advance
    beyond all earlier ones (a running maximum of the coordinate) are kept, so each branch's
    coordinate is strictly increasing and safe to interpolate on. A pulse that never reaches
    zero velocity has a loading branch only and ``stopped=False``.

    Parameters
    ----------
    pulse : Pulse
        The pulse, filtered as the caller wants it (decel in m/s^2).

    Returns
    -------
    Branches
    """
    p = pulse.after_contact()
    v, s = kinematics(p.decel, p.dt, p.v0)
    below = np.flatnonzero(v <= 0)
    if below.size == 0:
        return Branches(_branch(s, p.time, p.decel, v), None, float(s[-1]), None, False)
    i0 = int(below[0])
    t_stop = _zero_crossing_time(p.time, v, i0)
    k = int(np.argmax(s[: i0 + 1]))
    s_max = float(s[k])
    forward_again = np.flatnonzero(v[i0:] > 0)
    end = i0 + int(forward_again[0]) if forward_again.size else v.size
    unload = slice(k, end)
    loading = _branch(s[: k + 1], p.time[: k + 1], p.decel[: k + 1], v[: k + 1])
    unloading = _branch(s_max - s[unload], p.time[unload], p.decel[unload], v[unload])
    return Branches(loading, unloading, s_max, t_stop, True)


def _branch(x, time, decel, velocity) -> Branch:
    """A Branch keeping only samples whose coordinate exceeds all earlier ones."""
    prev_max = np.maximum.accumulate(np.r_[-np.inf, x[:-1]])
    keep = x > prev_max
    return Branch(x[keep], decel[keep], time[keep], velocity[keep])


def _zero_crossing_time(time, v, i0: int) -> float:
    """Time where v crosses zero between samples i0 - 1 (v > 0) and i0 >= 1 (v <= 0)."""
    t0, t1, v0, v1 = time[i0 - 1], time[i0], v[i0 - 1], v[i0]
    return float(t0 + (t1 - t0) * v0 / (v0 - v1))


def rebound_work(u, decel):
    """Work per unit mass the spring-back returns before the deceleration stops pushing (J/kg).

    ``max over u of int_0^u a du'`` (trapezoids) along an unloading branch: the car leaves the
    barrier at the rebound speed ``sqrt(2 W)``, where the cumulative work peaks.

    Parameters
    ----------
    u : ndarray, shape (n,)
        Unloading coordinate ``s_max - s`` in m, increasing from the turnaround.
    decel : ndarray, shape (..., n)
        Deceleration along it in m/s^2 (leading axes: e.g. Monte Carlo samples).

    Returns
    -------
    work : ndarray, shape (...)
    peak : ndarray of int, shape (...)
        Index where the cumulative work peaks; ``n - 1`` when it still grows at the branch's end
        (the record stops before separation, so ``work`` is a lower bound).
    """
    a = np.asarray(decel, dtype=float)
    steps = 0.5 * (a[..., 1:] + a[..., :-1]) * np.diff(np.asarray(u, dtype=float))
    cumulative = np.concatenate([np.zeros(a.shape[:-1] + (1,)), np.cumsum(steps, axis=-1)], axis=-1)
    return cumulative.max(axis=-1), cumulative.argmax(axis=-1)
