"""The vehicle's static force-crush characteristic F(s) = K(s) s and its elastic unloading line.

Crush ``s`` (m) is the body's forward travel since first contact with the rigid barrier. The
loading branch is staged, as a unibody car's front end collapses in sequence::

    F(s) = lam * [ F_can * ramp(s / s_bump)                          bumper beam, then crash cans
                 + (F_rail + k_rail (s - s_can) - F_can) * ramp((s - s_can) / s_blend)   main rails
                 + k_stack * max(0, s - s_stack)^2 ]                  stack-up stiffening (engine,
                                                                      dash, wheels block up)

with ``ramp(x) = 3x^2 - 2x^3`` on [0, 1] (0 below, 1 above), ``lam = (w_f / w_f_ref)^beta`` the
strength of the front structure growing with front axle mass w_f (kg), and the stack-up onset
``s_stack`` earlier for a Type II powertrain (a longer engine package). So an 8 mph test only
crushes the bumper and crash cans while a 35 mph test reaches the stiff stack-up: low-speed pulses
are not scaled copies of high-speed ones.

Units: forces N, lengths m, ``k_rail`` N/m, ``k_stack`` N/m^2, masses kg.

After the maximum crush ``s_max`` the base model unloads along a straight elastic line
``F = max(0, F(s_max) - k_unload (s_max - s))`` and reloads along it up to ``s_max`` (hysteresis:
the energy under the loading curve minus the triangle under the line is dissipated).
"""

from __future__ import annotations

import numpy as np

# Calibrated against NHTSA test 10146 by `crashfuse world calibrate` (see crashfuse.world.calibrate);
# the geometry (lengths) is fixed, the force levels are fitted.
VEHICLE = {
    "vehicle.f_can": 1.359e5,  # N, crash-can plateau
    "vehicle.s_bump": 0.20,  # m, bumper ramp length
    "vehicle.s_can": 0.28,  # m, end of crash cans / start of main rails
    "vehicle.s_blend": 0.08,  # m, blend length from crash cans to rails
    "vehicle.f_rail": 1.411e5,  # N, rail force at s_can
    "vehicle.k_rail": 6.902e4,  # N/m, rail hardening
    "vehicle.s_stack_type1": 0.52,  # m, stack-up onset, Type I powertrain
    "vehicle.s_stack_type2": 0.47,  # m, stack-up onset, Type II powertrain
    "vehicle.k_stack": 6.521e6,  # N/m^2, stack-up stiffening
    "vehicle.k_unload": 1.2e8,  # N/m, base elastic unloading stiffness
    "vehicle.front_ref": 961.0,  # kg, front axle mass of the reference (calibration) vehicle
    "vehicle.beta": 0.5,  # -, strength exponent on front axle mass
}


def _ramp(x: np.ndarray) -> np.ndarray:
    """Smooth step 3x^2 - 2x^3 clipped to [0, 1] (continuous slope at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def strength(front_weight: np.ndarray, p: dict) -> np.ndarray:
    """Structure strength factor lam = (w_f / w_f_ref)^beta, shape like ``front_weight`` (kg)."""
    return (np.asarray(front_weight, float) / p["vehicle.front_ref"]) ** p["vehicle.beta"]


def stack_onset(type2: np.ndarray, p: dict) -> np.ndarray:
    """Stack-up onset s_stack in m per run (``type2`` boolean array: Type II powertrain)."""
    return np.where(type2, p["vehicle.s_stack_type2"], p["vehicle.s_stack_type1"])


def loading_force(s: np.ndarray, lam: np.ndarray, s_stack: np.ndarray, p: dict) -> np.ndarray:
    """Static loading force F(s) in N.

    Parameters
    ----------
    s : ndarray, shape (n,)
        Crush in m.
    lam : ndarray, shape (n,)
        Strength factor (see :func:`strength`).
    s_stack : ndarray, shape (n,)
        Stack-up onset in m (see :func:`stack_onset`).
    p : dict
        Parameters ``vehicle.*`` (SI).

    Returns
    -------
    ndarray, shape (n,)
    """
    s = np.maximum(s, 0.0)
    can = p["vehicle.f_can"] * _ramp(s / p["vehicle.s_bump"])
    rail = p["vehicle.f_rail"] + p["vehicle.k_rail"] * (s - p["vehicle.s_can"]) - p["vehicle.f_can"]
    rail = rail * _ramp((s - p["vehicle.s_can"]) / p["vehicle.s_blend"])
    stack = p["vehicle.k_stack"] * np.maximum(s - s_stack, 0.0) ** 2
    return lam * (can + rail + stack)
