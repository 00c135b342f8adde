"""The second world's forms of the five catalogue effects (same names as the first world's).

Every parameter is ``effect.name`` in SI, finite and >= 0 (> 0 for those in :data:`POSITIVE`).
``c`` is the crush-zone compression (m), ``c'`` its rate (m/s), ``P`` the crush force (N):

``damping``
    Quadratic crush damping ``F_d = c2 c' |c'| min(1, c / 0.10 m)`` added to ``P`` (air and
    fluids squeezed out of the front end, foam). ``damping.c2`` in N s^2/m^2.
``strain_rate``
    Rate hardening as a power law in the crush speed on the loading branch,
    ``P = P_static (1 + a (c' / v_ref)^p)`` for c' > 0. ``strain_rate.a`` (-), ``v_ref`` (m/s),
    ``p`` (-).
``powertrain``
    Engine-to-barrier contact: once the engine's forward travel exceeds the gap (``gap_type1`` /
    ``gap_type2`` m, minus ``gap_awd`` m for AWD) it is pushed back by a compression-only
    spring-damper ``C = max(0, k_contact (x_e - gap) + c_contact v_e)``, and the body drives into
    the stopped engine through its mounts: a secondary pulse in the faster tests only - the slower
    tests never close the gap and are exactly unchanged. ``k_contact`` N/m, ``c_contact`` N s/m.
    Without the effect the engine rides freely on its mounts (the mounts are part of the vehicle).
``unloading``
    Exponential unloading with a residual set: with ``r = c_max - c`` the spring-back below the
    largest crush, ``delta = d0 + P(c_max) / k`` and ``r_set = set_ratio * delta``,
    ``P = P(c_max) (exp(-r/delta) - exp(-r_set/delta)) / (1 - exp(-r_set/delta))`` for
    ``r < r_set``, 0 beyond; reloading follows the same curve. ``unloading.k`` N/m (fitted),
    ``d0`` m, ``set_ratio`` (-). Without it the base straight line ``structure.k_unload``.
``mass``
    Unmodelled attached mass (cargo, battery modules, test equipment) ``mass.m`` kg on a compliant
    link to the body: spring ``mass.k`` N/m and damper ``mass.c`` N s/m.
"""

from __future__ import annotations

import numpy as np

from crashfuse.catalogue import EFFECTS, F_REF, V_REF, check_effect, key, parse_params
from crashfuse.catalogue import params_at_strength as at_strength

# Realistic magnitudes: chosen physical values, except `unloading.k`, fitted with the structure's
# force levels to NHTSA 10146 (crashfuse.world.multibody.calibrate).
REALISTIC = {
    "damping.c2": 300.0,
    "strain_rate.a": 0.20,
    "strain_rate.v_ref": 10.0,
    "strain_rate.p": 0.7,
    "powertrain.gap_type1": 0.62,
    "powertrain.gap_type2": 0.58,
    "powertrain.gap_awd": 0.02,
    "powertrain.k_contact": 1.0e7,
    "powertrain.c_contact": 5.0e4,
    "unloading.k": 1.896e9,
    "unloading.d0": 0.006,
    "unloading.set_ratio": 3.0,
    "mass.m": 150.0,
    "mass.k": 5.9e5,
    "mass.c": 1.9e3,
}

# `--strength subtle`: the magnitudes that change when an effect is made subtle (the rest stay
# realistic), chosen so that withholding one lowers the mean CAE-vs-test ISO by a few hundredths.
SUBTLE = {
    "damping": {"damping.c2": 150.0},
    "strain_rate": {"strain_rate.a": 0.10},
    "powertrain": {"powertrain.k_contact": 3.0e6, "powertrain.c_contact": 2.0e4},
    "unloading": {"unloading.d0": 0.003},
    "mass": {"mass.m": 80.0, "mass.k": 7.1e5, "mass.c": 2.3e3},
}

# Which catalogue quantity each parameter is (crashfuse.catalogue): the laws differ from the first
# world's, the meanings are shared.
QUANTITIES = {
    "damping.c2": "quadratic_coefficient",
    "strain_rate.a": "gain_at_reference_speed",
    "strain_rate.v_ref": "reference_speed",
    "strain_rate.p": "rate_exponent",
    "powertrain.gap_type1": "gap",
    "powertrain.gap_type2": "gap",
    "powertrain.gap_awd": "gap",
    "powertrain.k_contact": "contact_stiffness",
    "powertrain.c_contact": "contact_damping",
    "unloading.k": "springback_stiffness",
    "unloading.d0": "springback_floor",
    "unloading.set_ratio": "zero_force_travel_ratio",
    "mass.m": "extra",
    "mass.k": "link_stiffness",
    "mass.c": "link_damping",
}

# Parameters that divide or set a scale: zero is as invalid as negative.
POSITIVE = ("strain_rate.v_ref", "strain_rate.p", "unloading.k", "unloading.set_ratio", "mass.k")


def params_at_strength(strength: str = "realistic", subtle_effects=()) -> dict:
    """Every catalogue parameter ``{"effect.param": value}`` (SI) at a named strength.

    With ``strength="subtle"`` only ``subtle_effects`` take their subtle magnitudes.
    """
    return at_strength(strength, REALISTIC, SUBTLE, subtle_effects)


def parse_overrides(items) -> dict:
    """``["effect.param=value", ...]`` as ``{"effect.param": float}`` for these laws (:func:`crashfuse.catalogue.parse_params`)."""
    return parse_params(items, REALISTIC, POSITIVE)


def headline(effect: str, params: dict, engine_mass: dict) -> dict:
    """The catalogue's headline quantities of ``effect`` under these laws and parameters, SI.

    Parameters
    ----------
    effect : str
    params : dict
        The effect's parameters ``{"effect.param": value}`` (at least those of ``effect``).
    engine_mass : dict of str to float
        Arrested engine mass (kg) per powertrain label, averaged over the tests of that label
        (the engine belongs to the vehicle here; the effect is its contact with the barrier).

    Returns
    -------
    dict
        ``{reported name: value}`` (:func:`crashfuse.catalogue.key`).
    """
    p = params
    if check_effect(effect) == "damping":  # the quadratic law's force per crush speed at V_REF
        return {key(effect, "c"): p["damping.c2"] * V_REF}
    if effect == "strain_rate":
        gain = p["strain_rate.a"] * (V_REF / p["strain_rate.v_ref"]) ** p["strain_rate.p"]
        return {key(effect, "gain_at_15mps"): gain}
    if effect == "unloading":  # travel to zero force after a peak of F_REF
        return {key(effect, "springback_at_500kN"): p["unloading.set_ratio"] * (p["unloading.d0"] + F_REF / p["unloading.k"])}
    if effect == "powertrain":
        return {key(effect, "mass", label): float(np.mean(m)) for label, m in engine_mass.items()}
    return {key(effect, "extra"): p["mass.m"]}

