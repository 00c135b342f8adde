"""The vehicle of the second world: three masses and a folding-wave crush zone (SI throughout).

Masses, all moving forward from first contact (t = 0) at the impact speed v0:

* the **front** (bumper beam, crash boxes, front rail tips) of mass ``front.mass``, pressed
  against the rigid barrier through a stiff, damped, compression-only contact
  ``B = max(0, k_barrier x_f + c_barrier v_f)`` for ``x_f > 0``;
* the **engine** (powertrain) of mass ``engine.mass_type1/2`` (+ ``engine.mass_awd``) on
  progressive rubber mounts ``F_m = k_mount d (1 + (d / d_mount)^2) + c_mount d'``, ``d`` its
  travel relative to the body;
* the **body**, the rest of the nominal test mass, carrying the accelerometer.

Between front and body sits the crush zone, compressed by ``c = x_b - x_f``. Its static
loading force is a piecewise-linear plateau family with superimposed folding waves::

    P(c) = lam * L(c) * (1 + a_fold sin(2 pi c / lambda_fold))
    L    = linear interpolation through the knots
           (0, 0), (C_BUMPER, f_bumper), (C_BOX, f_bumper), (C_RAIL, f_rail),
           (c_block, f_rail_end), (c_block + BLOCK_LENGTH, f_block),
           and f_block + k_block (c - c_block - BLOCK_LENGTH) beyond
    lam  = (w_f / front_ref)^beta

the bumper and crash boxes fold at a plateau, the main rails at a rising plateau, and the
engine bay blocks up over ``BLOCK_LENGTH`` from ``c_block`` (earlier for a Type II powertrain).
The folding waves (progressive buckling of thin-walled rails, one wave per fold of length
``lambda_fold``) are seen as a ripple at low crush speed and are filtered out by CFC 60 at high
speed. Unloading below the largest crush ``c_max`` follows the straight line of stiffness
``structure.k_unload`` in the base model (the ``unloading`` effect replaces it).
"""

from __future__ import annotations

import numpy as np

# Geometry (m), fixed: knot crushes of the plateau family.
C_BUMPER = 0.10  # bumper beam and foam crushed, crash boxes at their plateau
C_BOX = 0.22  # end of the crash boxes
C_RAIL = 0.30  # main rails fully folding
BLOCK_LENGTH = 0.10  # crush over which the engine bay blocks up

# Force levels fitted to NHTSA 10146 by `crashfuse world calibrate --world multibody
# --max-evals 80` (crashfuse.world.multibody.calibrate); geometry, masses and mounts are chosen values.
VEHICLE = {
    "structure.f_bumper": 1.956e5,  # N, crash-box plateau
    "structure.f_rail": 1.959e5,  # N, rail plateau at C_RAIL
    "structure.f_rail_end": 1.989e5,  # N, rail force at the block-up onset
    "structure.f_block": 4.393e5,  # N, blocked engine bay, BLOCK_LENGTH after onset
    "structure.k_block": 1.297e5,  # N/m, stiffening beyond
    "structure.c_block_type1": 0.52,  # m, block-up onset, Type I powertrain
    "structure.c_block_type2": 0.47,  # m, block-up onset, Type II powertrain (longer package)
    "structure.fold_amplitude": 0.10,  # -, folding-wave ripple amplitude
    "structure.fold_wavelength": 0.07,  # m, crush per fold
    "structure.k_unload": 1.5e8,  # N/m, base elastic unloading line
    "structure.front_ref": 961.0,  # kg, front axle mass of the reference (calibration) vehicle
    "structure.beta": 0.7,  # -, strength exponent on front axle mass
    "front.mass": 45.0,  # kg, front structure ahead of the crush zone
    "front.k_barrier": 4.0e8,  # N/m, front-to-barrier contact stiffness
    "front.c_barrier": 8.0e4,  # N s/m, its damping (damping ratio ~0.3)
    "engine.mass_type1": 170.0,  # kg, Type I powertrain
    "engine.mass_type2": 210.0,  # kg, Type II powertrain
    "engine.mass_awd": 35.0,  # kg, added for AWD (transfer case, front drive shafts)
    "engine.k_mount": 1.2e6,  # N/m, mount stiffness at small travel
    "engine.d_mount": 0.05,  # m, mount travel at which the secant stiffness has doubled
    "engine.c_mount": 1.0e4,  # N s/m, mount damping
}


def strength(front_weight: np.ndarray, p: dict) -> np.ndarray:
    """Structure strength factor lam = (w_f / front_ref)^beta, shape like ``front_weight`` (kg)."""
    return (np.asarray(front_weight, float) / p["structure.front_ref"]) ** p["structure.beta"]


def block_onset(type2: np.ndarray, p: dict) -> np.ndarray:
    """Block-up onset c_block in m per run (``type2`` boolean array: Type II powertrain)."""
    return np.where(type2, p["structure.c_block_type2"], p["structure.c_block_type1"])


def _plateaus(c: np.ndarray, c_block: float, p: dict) -> np.ndarray:
    """Piecewise-linear envelope L(c) in N for runs sharing one block-up onset."""
    knots = [0.0, C_BUMPER, C_BOX, C_RAIL, c_block, c_block + BLOCK_LENGTH]
    forces = [0.0, p["structure.f_bumper"], p["structure.f_bumper"], p["structure.f_rail"],
              p["structure.f_rail_end"], p["structure.f_block"]]
    beyond = p["structure.k_block"] * np.maximum(c - knots[-1], 0.0)
    return np.interp(c, knots, forces) + beyond


def crush_force(c: np.ndarray, lam: np.ndarray, c_block: np.ndarray, p: dict) -> np.ndarray:
    """Static loading force P(c) in N.

    Parameters
    ----------
    c : ndarray, shape (n,)
        Crush-zone compression in m (negative is treated as 0).
    lam : ndarray, shape (n,)
        Strength factor (see :func:`strength`).
    c_block : ndarray, shape (n,)
        Block-up onset in m (see :func:`block_onset`); at most two distinct values.
    p : dict
        ``structure.*`` parameters (SI).

    Returns
    -------
    ndarray, shape (n,)
    """
    c = np.maximum(c, 0.0)
    envelope = np.empty_like(c)
    for onset in np.unique(c_block):
        rows = c_block == onset
        envelope[rows] = _plateaus(c[rows], float(onset), p)
    waves = 1.0 + p["structure.fold_amplitude"] * np.sin(2.0 * np.pi * c / p["structure.fold_wavelength"])
    return lam * envelope * waves
