"""Calibrate the physical-test simulator to the real NCAP test NHTSA 10146.

At the test's conditions (57.09 km/h, 1719 kg split 961 / 758 kg at its CG, a Type I transverse
four-cylinder with front-wheel drive) the test simulator with the ``paper`` preset's test-side
effects (every catalogue effect, realistic strength) must reproduce the measured pulse metrics -
peak deceleration at CFC 60, time of zero velocity, dynamic crush and rebound - within 10 %.

The geometry of the force-crush characteristic and the effect magnitudes are fixed; the force
levels of the vehicle (``vehicle.f_can, f_rail, k_rail, k_stack``) and the unloading stiffness
(``unloading.k``) are fitted by least squares on the relative metric errors plus a weak term on
the pulse shape (CFC 60 deceleration every 1 ms over 0-100 ms, scaled by the test's peak), so that
the fit is well posed and the pulse looks like the test's, not only its four numbers.

``crashfuse world calibrate`` runs the fit and prints the side-by-side table; the fitted values are
committed as the defaults in :mod:`crashfuse.world.vehicle` and :mod:`crashfuse.world.effects`.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import optimize

from crashfuse.catalogue import EFFECTS
from crashfuse.errors import InputError
from crashfuse.signals.filters import filter_pulse
from crashfuse.io.nhtsa import read_nhtsa
from crashfuse.signals.metrics import pulse_metrics
from crashfuse.signals.pulse import Pulse
from crashfuse.world.effects import REALISTIC
from crashfuse.world.simulate import MEASUREMENT, PRETRIGGER, RAW_RATE, Runs, body_decel
from crashfuse.world.vehicle import VEHICLE

# Fitted parameters: (start, lower bound, upper bound) in SI. The fit always starts from these
# round values, so `crashfuse world calibrate` reproduces the committed constants exactly.
FITTED = {
    "vehicle.f_can": (1.6e5, 1.0e5, 3.0e5),
    "vehicle.f_rail": (2.0e5, 1.2e5, 4.0e5),
    "vehicle.k_rail": (3.0e5, 1.0e4, 1.0e6),
    "vehicle.k_stack": (6.0e6, 1.0e6, 3.0e7),
    "unloading.k": (4.0e7, 1.0e7, 2.0e8),
}
METRICS = ("peak_decel_g", "t_zero_velocity_ms", "dynamic_crush_mm", "rebound_kmh")
TOLERANCE = 0.10  # relative: every metric within 10 % of the test's
T_END = 0.250  # s: covers the 200 ms rebound window of pulse_metrics, with filter margin
SHAPE_WEIGHT = 0.5  # weight of the shape residuals against the four metric residuals


def nhtsa_conditions(test: Pulse) -> Runs:
    """The test's impact condition as a one-run :class:`Runs` (Type I powertrain, FWD)."""
    return Runs(v0=test.v0, front=test.front_weight, rear=test.rear_weight, type2=False, awd=False)


def simulated_test(params: dict, runs: Runs, t_end: float = T_END) -> Pulse:
    """The simulator's noise-free raw test pulse (every effect on) at 25 kHz, with pre-trigger.

    Raw like the real record (``meta['cfc']`` None), so that :func:`pulse_metrics` filters both
    the same way.
    """
    lead = int(round(PRETRIGGER * RAW_RATE))
    decel = np.concatenate([np.zeros(lead), body_decel(runs, set(EFFECTS), params, t_end)[0]])
    time = (np.arange(decel.size) - lead) / RAW_RATE
    return Pulse(time, decel, float(runs.v0[0]), float(runs.front[0]), float(runs.rear[0]),
                 run_id="simulated", meta={"cfc": None})


def default_params() -> dict:
    """Vehicle, effect (realistic) and measurement parameters as committed."""
    return {**VEHICLE, **REALISTIC, **MEASUREMENT}


def fit(real: Pulse, params: dict | None = None, max_nfev: int = 60) -> tuple[dict, pd.DataFrame]:
    """Fit the vehicle force levels and unloading stiffness to a real test.

    Parameters
    ----------
    real : Pulse
        The real raw test record (as :func:`crashfuse.io.nhtsa.read_nhtsa` gives it).
    params : dict, optional
        Parameters held fixed (default: the committed ones); the fitted ones start from
        :data:`FITTED`.
    max_nfev : int
        Budget of simulator evaluations.

    Returns
    -------
    params : dict
        All parameters with the fitted ones replaced.
    table : pandas.DataFrame
        :func:`comparison` of the fitted simulator against ``real``.
    """
    base = dict(params or default_params())
    runs = nhtsa_conditions(real)
    target = pulse_metrics(real)
    grid = np.arange(0.0, 0.1 + 1e-9, 1e-3)
    real60 = filter_pulse(real, 60)
    real_shape = np.interp(grid, real60.time, real60.decel) / real60.decel.max()
    start, lower, upper = np.log(np.array(list(FITTED.values()))).T

    def residuals(x):
        trial = {**base, **dict(zip(FITTED, np.exp(x)))}
        sim = simulated_test(trial, runs)
        got = pulse_metrics(sim)
        sim60 = filter_pulse(sim, 60)
        shape = np.interp(grid, sim60.time, sim60.decel) / real60.decel.max() - real_shape
        rel = [got[k] / target[k] - 1.0 for k in METRICS]
        return np.concatenate([rel, SHAPE_WEIGHT * shape / np.sqrt(grid.size)])

    sol = optimize.least_squares(residuals, start, bounds=(lower, upper), x_scale=0.3, diff_step=1e-3,
                                 max_nfev=max_nfev)
    fitted = {**base, **dict(zip(FITTED, np.exp(sol.x)))}
    return fitted, comparison(real, fitted)


def comparison(real: Pulse, params: dict) -> pd.DataFrame:
    """Side-by-side metrics of ``real`` and the simulator at its condition, with relative errors."""
    got = pulse_metrics(simulated_test(params, nhtsa_conditions(real)))
    target = pulse_metrics(real)
    rows = [{"metric": k, "nhtsa_10146": target[k], "simulated": got[k], "rel_error": got[k] / target[k] - 1.0}
            for k in METRICS]
    table = pd.DataFrame(rows)
    table["within_10pct"] = table["rel_error"].abs() <= TOLERANCE
    return table


def report(folder, refit: bool = True, max_nfev: int = 60) -> str:
    """The calibration report printed by ``crashfuse world calibrate``.

    Parameters
    ----------
    folder : path
        NHTSA EV5 folder of test 10146.
    refit : bool
        Run the fit; otherwise only compare the committed defaults with the test.
    max_nfev : int
        Budget of simulator evaluations for the fit.

    Returns
    -------
    str
        Side-by-side table(s) and, after a fit, the fitted constants to commit.
    """
    if max_nfev < 1:
        raise InputError(f"expected at least 1 simulator evaluation, got {max_nfev}", field="max_nfev")
    real = read_nhtsa(folder)
    fmt = {"float_format": lambda x: f"{x:.3f}", "index": False}
    lines = ["NHTSA 10146 vs the physical-test simulator (paper preset test side), committed defaults:",
             comparison(real, default_params()).to_string(**fmt)]
    if refit:
        fitted, table = fit(real, max_nfev=max_nfev)
        lines += ["", "after refitting " + ", ".join(FITTED) + ":", table.to_string(**fmt), "",
                  "fitted constants (commit in crashfuse/world/vehicle.py and effects.py):"]
        lines += [f'    "{k}": {fitted[k]:.4g},' for k in FITTED]
    return "\n".join(lines)
