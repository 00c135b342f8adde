"""Pulse metrics: peak deceleration, time of zero velocity, dynamic crush, rebound, OLC.

Filter classes (after SAE J211-1's recommendations): the peak deceleration is
read from the CFC 60 pulse; velocity and displacement come from integrating the CFC 180 pulse.
A raw pulse (``meta['cfc']`` None) is filtered with each class over the FULL record, pre-impact
samples included, and cropped at t = 0 afterwards. A pulse already at CFC 60 (campaign data) is
used as it is for both. Integration is :func:`crashfuse.signals.domain.kinematics` (velocity Verlet,
trapezoidal velocity), the same integrator the displacement domain and the rollout use.
Everything is computed in SI; the returned dict carries report units (g, ms, mm, km/h).
Definitions in full: ``docs/metrics.md``.
"""

from __future__ import annotations

import numpy as np

from crashfuse.signals.domain import displacement_branches, kinematics
from crashfuse.signals.filters import filter_pulse
from crashfuse.signals.pulse import Pulse
from crashfuse.units import G0, KMH, MM, MS

PEAK_CFC = 60
KINEMATICS_CFC = 180
REBOUND_WINDOW = 0.200  # s after contact in which the rebound velocity is sought
OLC_FREE_FLIGHT = 0.065  # m of occupant travel relative to the vehicle before restraint
OLC_RESTRAINT = 0.235  # m of further relative travel while decelerating at the OLC


def pulse_metrics(pulse: Pulse) -> dict:
    """Crash-pulse metrics in report units.

    Parameters
    ----------
    pulse : Pulse
        Raw (``meta['cfc']`` None, full record with pre-impact samples) or already filtered.

    Returns
    -------
    dict
        ``run_id``; ``peak_decel_g`` (max CFC 60 deceleration after contact, g); ``t_peak_ms``
        (its time, ms); ``t_zero_velocity_ms`` (first time the CFC 180 velocity reaches zero,
        linearly interpolated, ms); ``dynamic_crush_mm`` (maximum displacement, reached there,
        mm; both from :func:`crashfuse.signals.domain.displacement_branches`);
        ``rebound_kmh`` (largest rearward velocity within 200 ms of contact, positive, km/h; 0
        if none); ``restitution`` (rebound / impact speed); ``olc_g`` (occupant load criterion,
        g). A quantity the record does not reach (no zero velocity, an occupant that never
        completes the 300 mm) is None, never a guess.
    """
    p60 = filter_pulse(pulse, PEAK_CFC).after_contact()
    p180 = filter_pulse(pulse, KINEMATICS_CFC).after_contact()
    i_peak = int(np.argmax(p60.decel))
    branches = displacement_branches(p180)
    v, s = kinematics(p180.decel, p180.dt, p180.v0)
    rebound = max(0.0, -float(v[p180.time <= REBOUND_WINDOW].min()))
    olc = occupant_load_criterion(p180.time - p180.time[0], v, s, p180.v0)
    return {
        "run_id": pulse.run_id,
        "peak_decel_g": float(p60.decel[i_peak] / G0),
        "t_peak_ms": float(p60.time[i_peak] / MS),
        "t_zero_velocity_ms": branches.t_stop / MS if branches.stopped else None,
        "dynamic_crush_mm": branches.s_max / MM if branches.stopped else None,
        "rebound_kmh": rebound / KMH,
        "restitution": rebound / p180.v0,
        "olc_g": None if olc is None else olc / G0,
    }


def occupant_load_criterion(time, velocity, displacement, v0: float) -> float | None:
    """Occupant load criterion (Kübler et al.), in m/s^2.

    A virtual occupant, unrestrained, keeps the impact speed ``v0`` while the vehicle slows,
    until it has moved 65 mm forward relative to the vehicle (time ``t1``). It then decelerates
    at a constant rate, the OLC, chosen so that it reaches the vehicle's velocity (time ``t2``)
    exactly when it has moved a further 235 mm relative to the vehicle (300 mm in all)::

        v0 t1 - s(t1) = 0.065
        v0 - OLC (t2 - t1) = v(t2)
        v0 t1 + (v0 + v(t2)) (t2 - t1) / 2 - s(t2) = 0.300

    ``t1`` and ``t2`` are the first such times, linearly interpolated between samples.

    Parameters
    ----------
    time : ndarray, shape (n,)
        Time since contact in s (starting at 0).
    velocity, displacement : ndarray, shape (n,)
        Vehicle velocity (m/s) and displacement since contact (m).
    v0 : float
        Impact speed in m/s.

    Returns
    -------
    float or None
        OLC in m/s^2; None if the record ends before ``t1`` or ``t2``.
    """
    t, v, s = (np.asarray(x, dtype=float) for x in (time, velocity, displacement))
    t1 = _first_crossing(t, v0 * t - s, OLC_FREE_FLIGHT, falling=False)
    if t1 is None:
        return None
    s1 = np.interp(t1, t, s)
    after = t > t1
    tt = np.r_[t1, t[after]]
    vv = np.r_[np.interp(t1, t, v), v[after]]
    gap = v0 * t1 + (v0 + vv) * (tt - t1) / 2 - np.r_[s1, s[after]] - (OLC_FREE_FLIGHT + OLC_RESTRAINT)
    t2 = _first_crossing(tt, gap, 0.0, falling=False)
    if t2 is None:
        return None
    return float((v0 - np.interp(t2, tt, vv)) / (t2 - t1))


def _first_crossing(t, y, level: float, falling: bool) -> float | None:
    """First time y reaches ``level`` (from above if ``falling``), linearly interpolated."""
    d = (level - y) if falling else (y - level)
    hit = np.flatnonzero(d >= 0)
    if hit.size == 0:
        return None
    j = int(hit[0])
    if j == 0:
        return float(t[0])
    return float(t[j - 1] + (t[j] - t[j - 1]) * d[j - 1] / (d[j - 1] - d[j]))
