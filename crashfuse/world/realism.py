"""Realism bars of a generated campaign: the CAE-vs-test gap and physically plausible tests.

Bars, checked on the ``paper`` preset by ``tests/test_world.py`` and printed by
``crashfuse world realism DIR``:

* ISO/TS 18571 overall rating of each test's companion CAE run against the test over 0-60 ms
  within the paper's CAE range 0.45-0.85 for at least 9 of the 11 tests;
* every test physically plausible: peak deceleration 5-60 g, dynamic crush 50-900 mm, stopped
  within 40-100 ms, restitution 0.05-0.40;
* low-speed tests are not scaled copies of high-speed ones: the shape factor
  ``peak / mean deceleration`` (mean = v0^2 / (2 crush)) spreads by more than 20 % over the table.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from crashfuse.io.campaign import Campaign
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.metrics import pulse_metrics
from crashfuse.units import G0, MM, MPH, MS

ISO_RANGE = (0.45, 0.85)
ISO_WINDOW = (0.0, 0.060)  # s
MIN_IN_RANGE = 9
PLAUSIBLE = {"peak_decel_g": (5.0, 60.0), "dynamic_crush_mm": (50.0, 900.0), "t_zero_velocity_ms": (40.0, 100.0),
             "restitution": (0.05, 0.40)}
MIN_SHAPE_SPREAD = 0.20


def realism_table(campaign: Campaign) -> pd.DataFrame:
    """One row per test: condition, ISO 0-60 ms against its CAE companion, test and CAE metrics.

    Columns: ``run_id, speed_mph, powertrain, drive, iso_0_60, iso_in_range``, the test's
    ``peak_decel_g, t_zero_velocity_ms, dynamic_crush_mm, rebound_kmh, restitution, shape_factor,
    plausible`` and the CAE's ``cae_peak_decel_g, cae_t_zero_velocity_ms, cae_dynamic_crush_mm``.
    """
    rows = []
    cond = campaign.conditions.set_index("run_id")
    for tid in campaign.tests:
        test, cae = campaign.pulses[tid], campaign.companion(tid)
        iso = iso_score(test.time, test.decel, cae.time, cae.decel, *ISO_WINDOW)["overall"]
        m, mc = pulse_metrics(test), pulse_metrics(cae)
        row = {"run_id": tid, "speed_mph": test.v0 / MPH, "powertrain": cond.at[tid, "powertrain"],
               "drive": cond.at[tid, "drive"], "iso_0_60": iso, "iso_in_range": ISO_RANGE[0] <= iso <= ISO_RANGE[1]}
        row.update({k: m[k] for k in ("peak_decel_g", "t_zero_velocity_ms", "dynamic_crush_mm", "rebound_kmh",
                                      "restitution")})
        row["shape_factor"] = _shape_factor(m, test.v0)
        row["plausible"] = all(v is not None and lo <= v <= hi for k, (lo, hi) in PLAUSIBLE.items()
                               for v in [m[k]])
        row.update({f"cae_{k}": mc[k] for k in ("peak_decel_g", "t_zero_velocity_ms", "dynamic_crush_mm")})
        rows.append(row)
    return pd.DataFrame(rows)


def _shape_factor(metrics: dict, v0: float) -> float:
    """Peak over mean deceleration, mean = v0^2 / (2 crush) (NaN if the test did not stop)."""
    crush = metrics["dynamic_crush_mm"]
    return np.nan if crush is None else metrics["peak_decel_g"] * G0 / (v0 ** 2 / (2 * crush * MM))


def bars(table: pd.DataFrame) -> dict:
    """Whether each realism bar holds: ``iso`` (>= 9 in range), ``plausible`` (all), ``not_scaled``."""
    shape = table["shape_factor"].to_numpy(float)
    return {"iso": int(table["iso_in_range"].sum()) >= MIN_IN_RANGE,
            "plausible": bool(table["plausible"].all()),
            "not_scaled": bool(np.nanmax(shape) / np.nanmin(shape) - 1.0 > MIN_SHAPE_SPREAD)}


def report(campaign: Campaign) -> str:
    """The printed realism table with the verdict on each bar."""
    table = realism_table(campaign)
    verdict = bars(table)
    text = table.to_string(index=False, float_format=lambda x: f"{x:.3f}", na_rep="-")
    n_in = int(table["iso_in_range"].sum())
    status = ", ".join(f"{k}={'met' if v else 'NOT met'}" for k, v in verdict.items())
    return (f"{text}\n\nISO 0-{ISO_WINDOW[1] / MS:.0f} ms in {ISO_RANGE}: {n_in}/{len(table)} "
            f"(bar >= {MIN_IN_RANGE}); bars: {status}")
