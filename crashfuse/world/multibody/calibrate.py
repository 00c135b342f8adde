"""Calibrate the second world's test simulator to the real NCAP test NHTSA 10146.

At the test's conditions (57.09 km/h, 961 / 758 kg, Type I powertrain, FWD) the test simulator
with every catalogue effect (realistic) must reproduce the measured pulse: peak deceleration at
CFC 60, time of zero velocity, dynamic crush and rebound within 10 %, and the CFC 60 pulse itself
(ISO/TS 18571 overall rating over 0-100 ms, reported). Geometry, masses, mounts and effect
magnitudes are chosen; the crush zone's force levels (``structure.f_bumper, f_rail, f_rail_end,
f_block, k_block``) and the unloading stiffness (``unloading.k``) are fitted by least squares on
the four relative metric errors plus the pulse shape (CFC 60 deceleration every 1 ms over
0-100 ms, relative to the test's peak), from fixed round starting values so that
``crashfuse world calibrate --world multibody`` reproduces the committed constants.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import optimize

from crashfuse.errors import InputError
from crashfuse.io.nhtsa import read_nhtsa
from crashfuse.signals.filters import filter_pulse
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.metrics import pulse_metrics
from crashfuse.signals.pulse import Pulse
from crashfuse.world.multibody.effects import EFFECTS, REALISTIC
from crashfuse.world.multibody.simulate import MEASUREMENT, PRETRIGGER, RAW_RATE, Runs, body_decel
from crashfuse.world.multibody.structure import VEHICLE

# Fitted parameters: (start, lower bound, upper bound) in SI.
FITTED = {
    "structure.f_bumper": (1.6e5, 0.5e5, 4.0e5),
    "structure.f_rail": (2.2e5, 0.8e5, 5.0e5),
    "structure.f_rail_end": (2.8e5, 1.0e5, 6.0e5),
    "structure.f_block": (7.0e5, 2.0e5, 2.0e6),
    "structure.k_block": (2.0e6, 1.0e5, 3.0e7),
    "unloading.k": (8.0e7, 1.0e7, 2.0e9),
}
METRICS = ("peak_decel_g", "t_zero_velocity_ms", "dynamic_crush_mm", "rebound_kmh")
TOLERANCE = 0.10  # relative, on each metric
ISO_WINDOW = (0.0, 0.100)  # s, the pulse-shape comparison
MIN_ISO = 0.70  # bar on the simulated pulse's ISO/TS 18571 rating against the test's (0-100 ms)
T_END = 0.250  # s: covers pulse_metrics' 200 ms rebound window with filter margin
SHAPE_WEIGHT = 0.5  # weight of the shape residuals against the four metric residuals


def nhtsa_conditions(test: Pulse) -> Runs:
    """The test's impact condition as a one-run :class:`Runs` (Type I powertrain, FWD)."""
    return Runs(v0=test.v0, front=test.front_weight, rear=test.rear_weight, type2=False, awd=False)


def simulated_test(params: dict, runs: Runs, t_end: float = T_END) -> Pulse:
    """Noise-free raw body deceleration (every effect on) at 20 kHz with pre-trigger, as a raw Pulse."""
    lead = int(round(PRETRIGGER * RAW_RATE))
    decel = np.concatenate([np.zeros(lead), body_decel(runs, set(EFFECTS), params, t_end)[0]])
    time = (np.arange(decel.size) - lead) / RAW_RATE
    return Pulse(time, decel, float(runs.v0[0]), float(runs.front[0]), float(runs.rear[0]),
                 run_id="simulated", meta={"cfc": None})


def default_params() -> dict:
    """Vehicle, effect (realistic) and measurement parameters as committed."""
    return {**VEHICLE, **REALISTIC, **MEASUREMENT}


def _shape(pulse: Pulse, grid: np.ndarray, scale: float) -> np.ndarray:
    p60 = filter_pulse(pulse, 60)
    return np.interp(grid, p60.time, p60.decel) / scale


def fit(real: Pulse, params: dict | None = None, max_nfev: int = 80) -> tuple[dict, pd.DataFrame]:
    """Fit the force levels and the unloading stiffness to a real raw test record.

    Returns
    -------
    params : dict
        All parameters with the fitted ones replaced.
    table : pandas.DataFrame
        :func:`comparison` of the fitted simulator against ``real``.
    """
    base = dict(params or default_params())
    runs, target = nhtsa_conditions(real), pulse_metrics(real)
    grid = np.arange(0.0, 0.1 + 1e-9, 1e-3)
    scale = filter_pulse(real, 60).decel.max()
    real_shape = _shape(real, grid, scale)
    start, lower, upper = np.log(np.array(list(FITTED.values()))).T

    def residuals(x):
        sim = simulated_test({**base, **dict(zip(FITTED, np.exp(x)))}, runs)
        got = pulse_metrics(sim)
        rel = [got[k] / target[k] - 1.0 if got[k] is not None else 1.0 for k in METRICS]
        return np.concatenate([rel, SHAPE_WEIGHT * (_shape(sim, grid, scale) - real_shape) / np.sqrt(grid.size)])

    sol = optimize.least_squares(residuals, start, bounds=(lower, upper), x_scale=0.3, diff_step=1e-3,
                                 max_nfev=max_nfev)
    fitted = {**base, **dict(zip(FITTED, np.exp(sol.x)))}
    return fitted, comparison(real, fitted)


def comparison(real: Pulse, params: dict) -> pd.DataFrame:
    """Side-by-side metrics of ``real`` and the simulator at its condition, relative errors, ISO rating."""
    sim = simulated_test(params, nhtsa_conditions(real))
    got, target = pulse_metrics(sim), pulse_metrics(real)
    rows = [{"metric": k, "nhtsa_10146": target[k], "simulated": got[k], "rel_error": got[k] / target[k] - 1.0,
             "within_bar": abs(got[k] / target[k] - 1.0) <= TOLERANCE} for k in METRICS]
    r60, s60 = filter_pulse(real, 60).after_contact(), filter_pulse(sim, 60).after_contact()
    iso = iso_score(r60.time, r60.decel, s60.time, s60.decel, *ISO_WINDOW)["overall"]
    rows.append({"metric": "iso18571_0_100ms", "nhtsa_10146": 1.0, "simulated": iso, "rel_error": iso - 1.0,
                 "within_bar": iso >= MIN_ISO})
    return pd.DataFrame(rows)


def report(folder, refit: bool = True, max_nfev: int = 80) -> str:
    """The calibration report: committed defaults vs the test and, with ``refit``, the new fit."""
    if max_nfev < 1:
        raise InputError(f"expected at least 1 simulator evaluation, got {max_nfev}", field="max_nfev")
    real = read_nhtsa(folder)
    fmt = {"float_format": lambda x: f"{x:.3f}", "index": False}
    lines = ["NHTSA 10146 vs the multibody world's test simulator (every effect), committed defaults:",
             comparison(real, default_params()).to_string(**fmt)]
    if refit:
        fitted, table = fit(real, max_nfev=max_nfev)
        lines += ["", "after refitting " + ", ".join(FITTED) + ":", table.to_string(**fmt), "",
                  "fitted constants (commit in crashfuse/world/multibody/structure.py and effects.py):"]
        lines += [f'    "{k}": {fitted[k]:.4g},' for k in FITTED]
    return "\n".join(lines)
