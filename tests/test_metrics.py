"""Pulse metrics against closed-form pulses and the real NHTSA test 10146, recomputed plainly."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, signal

from crashfuse import Pulse
from crashfuse.cli import main
from crashfuse.io.nhtsa import read_nhtsa
from crashfuse.signals.metrics import occupant_load_criterion, pulse_metrics
from crashfuse.units import G0, KMH

SHARED = Path(__file__).resolve().parents[2] / "shared"
V10146 = SHARED / "data" / "nhtsa" / "v10146"
needs_nhtsa = pytest.mark.skipif(not (V10146 / "v10146.093").exists(), reason="NHTSA test 10146 data absent")
V0_10146 = 57.09 * KMH


def _constant_pulse(amp, v0, duration=0.3, **meta):
    t = np.arange(int(duration / 1e-4) + 1) * 1e-4
    return Pulse(time=t, decel=np.full(t.size, amp), v0=v0, front_weight=900.0, rear_weight=700.0,
                 run_id="const", meta=meta)


def test_constant_deceleration_closed_form():
    # A campaign pulse already at CFC 60 is used as it is; with constant deceleration A every
    # metric has a closed form: stop at v0/A after v0^2/(2A), rearward speed A t - v0 after, and
    # OLC = A * 0.300 / 0.235 (free flight t1 = sqrt(2 * 0.065 / A); restraint lasts
    # 0.47 / (A t1), so OLC = A t2 / (t2 - t1) = A (1 + 0.13 / 0.47)).
    amp, v0 = 20 * G0, 15.0
    m = pulse_metrics(_constant_pulse(amp, v0, cfc=60))
    assert m["peak_decel_g"] == pytest.approx(20.0)
    assert m["t_zero_velocity_ms"] == pytest.approx(v0 / amp * 1e3, abs=1e-6)
    assert m["dynamic_crush_mm"] == pytest.approx(v0**2 / (2 * amp) * 1e3, abs=1e-3)
    assert m["rebound_kmh"] == pytest.approx((amp * 0.2 - v0) / KMH, rel=1e-9)
    assert m["restitution"] == pytest.approx((amp * 0.2 - v0) / v0, rel=1e-9)
    assert m["olc_g"] == pytest.approx(20.0 * 0.300 / 0.235, rel=1e-5)  # linear root of a quadratic


def _olc_sample_search(t, v, s, v0):
    """OLC the way pyisomme finds it, sample by sample: t1 is the first sample where the free
    occupant is 65 mm ahead; for each later sample t2, OLC = (v0 - v2) / (t2 - t1) until the
    occupant's relative travel s_rel(t2) - OLC (t2 - t1)^2 / 2 reaches 300 mm."""
    s_rel = v0 * t - s
    i1 = np.flatnonzero(s_rel >= 0.065)[0]
    for i2 in range(i1 + 1, t.size):
        olc = (v0 - v[i2]) / (t[i2] - t[i1])
        if s_rel[i2] - olc * (t[i2] - t[i1]) ** 2 / 2 >= 0.300:
            return olc
    raise AssertionError("the occupant never completes 300 mm")


def test_olc_of_a_sled_pulse_matches_a_sample_level_search():
    t = np.arange(15001) * 1e-5
    v0 = 15.6
    v = np.clip(v0 - 200.0 * t - 3000 * t**2, 0, None)
    s = integrate.cumulative_trapezoid(v, t, initial=0)
    assert occupant_load_criterion(t, v, s, v0) == pytest.approx(_olc_sample_search(t, v, s, v0), rel=1e-3)


def test_missing_quantities_are_none_and_json_safe():
    m = pulse_metrics(_constant_pulse(10 * G0, 30.0, duration=0.25, cfc=60))  # still moving at the end
    assert m["t_zero_velocity_ms"] is None and m["dynamic_crush_mm"] is None and m["olc_g"] is not None
    assert m["rebound_kmh"] == 0.0 and m["restitution"] == 0.0
    json.dumps(m, allow_nan=False)
    short = pulse_metrics(_constant_pulse(5 * G0, 30.0, duration=0.005, cfc=60))
    assert short["olc_g"] is None


def test_raw_pulse_is_filtered_over_the_full_record_then_cropped():
    # A sharp 30 g spike centred on t = 0 over a 10 g plateau: filtering only the t >= 0 part would
    # see a different signal around the peak than filtering the record with its pre-impact samples.
    t = np.arange(-300, 1200) * 1e-4
    decel = G0 * (10 * ((t > -0.005) & (t < 0.1)) + 30 * np.clip(1 - np.abs(t) / 0.003, 0, None))
    m = pulse_metrics(Pulse(time=t, decel=decel, v0=15.0, front_weight=900.0, rear_weight=700.0))
    fs = 1 / (t[1] - t[0])
    want = signal.filtfilt(*signal.butter(2, 2.0775 * 60, fs=fs), decel)[t >= 0].max() / G0
    assert m["peak_decel_g"] == pytest.approx(want, abs=1e-6)


def _v10146_raw():
    ch93, ch94 = (np.loadtxt(V10146 / f"v10146.{c:03d}") for c in (93, 94))
    t = ch93[:, 0]
    accel_g = (ch93[:, 1] + ch94[:, 1]) / 2
    accel_g -= accel_g[t < 0].mean()
    return t, -accel_g * G0


def _independent_metrics(t, decel, v0):
    """The metrics written out plainly: scipy's Butterworth design and filtfilt (its own default
    padding), trapezoidal integration of velocity and then of displacement, crop at t = 0."""
    fs = 1 / (t[1] - t[0])
    keep = t >= 0
    a60 = signal.filtfilt(*signal.butter(2, 2.0775 * 60, fs=fs), decel)[keep]
    a180 = signal.filtfilt(*signal.butter(2, 2.0775 * 180, fs=fs), decel)[keep]
    tc = t[keep]
    v = v0 - integrate.cumulative_trapezoid(a180, tc, initial=0)
    s = integrate.cumulative_trapezoid(v, tc, initial=0)
    j = np.flatnonzero(v <= 0)[0]
    t_zero = tc[j - 1] + (tc[j] - tc[j - 1]) * v[j - 1] / (v[j - 1] - v[j])
    rebound = -v[tc <= 0.2].min()
    return {"peak_decel_g": a60.max() / G0, "t_peak_ms": tc[np.argmax(a60)] * 1e3,
            "t_zero_velocity_ms": t_zero * 1e3, "dynamic_crush_mm": s.max() * 1e3,
            "rebound_kmh": rebound / KMH, "restitution": rebound / v0,
            "olc_g": _olc_sample_search(tc, v, s, v0) / G0}


# Absolute tolerances: the filters differ only in end padding, the integrators by O(dt^2), the OLC
# searches by picking samples instead of interpolating (one sample is 0.1 ms).
TOLERANCE = {"peak_decel_g": 0.001, "t_peak_ms": 0.01, "t_zero_velocity_ms": 0.01, "dynamic_crush_mm": 0.05,
             "rebound_kmh": 0.005, "restitution": 1e-4, "olc_g": 0.1}
SANITY = {"peak_decel_g": (30, 50), "dynamic_crush_mm": (500, 800), "t_zero_velocity_ms": (60, 80),
          "restitution": (0.05, 0.25), "olc_g": (15, 45), "t_peak_ms": (10, 100)}


@needs_nhtsa
def test_real_test_10146_matches_an_independent_computation():
    t, decel = _v10146_raw()
    pulse = Pulse(time=t, decel=decel, v0=V0_10146, front_weight=961.0, rear_weight=758.0, run_id="10146")
    got = pulse_metrics(pulse)
    want = _independent_metrics(t, decel, V0_10146)
    for key, tol in TOLERANCE.items():
        assert got[key] == pytest.approx(want[key], abs=tol), key
    for key, (lo, hi) in SANITY.items():
        assert lo <= got[key] <= hi, (key, got[key])
    assert got["run_id"] == "10146"


@needs_nhtsa
def test_real_test_10146_through_the_ev5_reader():
    t, decel = _v10146_raw()
    want = pulse_metrics(Pulse(time=t, decel=decel, v0=V0_10146, front_weight=961.0, rear_weight=758.0))
    got = pulse_metrics(read_nhtsa(V10146))
    for key, tol in TOLERANCE.items():
        assert got[key] == pytest.approx(want[key], abs=tol), key


@needs_nhtsa
def test_cli_pulse_metrics_rates_the_full_raw_record(capsys, monkeypatch):
    # The CLI must hand pulse_metrics the record as read (pre-impact lead-in included), not a
    # record cropped at contact before filtering. Run from the repo root, as a user would.
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    assert main(["pulse-metrics", "../shared/data/nhtsa/v10146", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == [pulse_metrics(read_nhtsa(V10146))]
