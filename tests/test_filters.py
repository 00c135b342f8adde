"""SAE J211-1 CFC filters against the standard's frequency-response corridor and design."""

import numpy as np
import pytest
from scipy import signal

from crashfuse import InputError, Pulse
from crashfuse.signals.filters import cfc_filter, filter_pulse, filtered_noise, j211_coefficients
from crashfuse.units import G0

# Frequency-response corridor of a data channel, SAE J211-1 Figure 1 = ISO 6487 Figure 1, as
# reproduced in UN Regulation No. 94 Rev. 4, Annex 8 (table: CFC, F_L <= 0.1 Hz, F_H, F_N and
# the limit lines a: +/-0.5 dB; b: +0.5/-1 dB; c: +0.5/-4 dB; d: -9 dB/octave; e: -24 dB/octave;
# f: no lower limit; g: floor N = -30 dB for CFC 60/180, -40 dB for CFC 600/1000).
# The corridor used here: upper +0.5 dB up to F_N, then line d (-9 dB/octave from F_N) down to
# the floor N; lower -0.5 dB below F_H, from -1 dB at F_H falling linearly in log f to -4 dB at
# F_N, none beyond F_N. Line e only tightens the upper limit far above F_N, where a 4-pole filter
# is tens of dB below line d, so it is not needed to make this test bite.
CORRIDOR = {60: (60.0, 100.0, -30.0), 180: (180.0, 300.0, -30.0),
            600: (600.0, 1000.0, -40.0), 1000: (1000.0, 1650.0, -40.0)}


def _limits(f, cfc):
    fh, fn, floor = CORRIDOR[cfc]
    upper = np.where(f <= fn, 0.5, np.maximum(floor, 0.5 - 9.0 * np.log2(f / fn)))
    ramp = -1.0 - 3.0 * np.log(f / fh) / np.log(fn / fh)
    lower = np.where(f < fh, -0.5, np.where(f <= fn, ramp, -np.inf))
    return lower, upper


def _gain_db(fs, cfc, f):
    """Steady-state gain of cfc_filter at frequencies f, from filtering sines (least-squares fit
    of sin and cos over the middle half of a 0.5 s record, away from the ends)."""
    dt = 1.0 / fs
    t = np.arange(int(0.5 * fs)) * dt
    y = cfc_filter(np.sin(2 * np.pi * f[:, None] * t), dt, cfc)
    mid = slice(t.size // 4, 3 * t.size // 4)
    gains, phases = [], []
    for fi, yi in zip(f, y):
        basis = np.column_stack([np.sin(2 * np.pi * fi * t[mid]), np.cos(2 * np.pi * fi * t[mid])])
        s, c = np.linalg.lstsq(basis, yi[mid], rcond=None)[0]
        gains.append(np.hypot(s, c))
        phases.append(np.arctan2(c, s))
    return 20 * np.log10(gains), np.array(phases)


@pytest.mark.parametrize("fs", [10_000.0, 12_500.0, 20_000.0])
@pytest.mark.parametrize("cfc", [60, 180, 600, 1000])
def test_magnitude_response_inside_j211_corridor(fs, cfc):
    fh, fn, _ = CORRIDOR[cfc]
    f = np.unique(np.r_[np.geomspace(1.0, 0.45 * fs, 60), fh, fn, 0.9 * fh, 1.2 * fh])
    gain, phase = _gain_db(fs, cfc, f)
    lower, upper = _limits(f, cfc)
    assert np.all(gain <= upper), f[gain > upper]
    assert np.all(gain >= lower), f[gain < lower]
    # Zero phase wherever the signal passes (forward-backward cancels the lag).
    passing = gain > -20
    assert np.abs(phase[passing]).max() < 1e-3


@pytest.mark.parametrize("fs", [10_000.0, 12_500.0, 20_000.0])
@pytest.mark.parametrize("cfc", [60, 180, 600, 1000])
def test_coefficients_equal_a_bilinear_butterworth_at_the_design_frequency(fs, cfc):
    # scipy designs the same 2-pole Butterworth by its own route (analog prototype, pre-warped
    # bilinear transform); J211's closed-form constants must agree with it.
    b, a = j211_coefficients(cfc, 1.0 / fs)
    b_ref, a_ref = signal.butter(2, 2.0775 * cfc, fs=fs)
    np.testing.assert_allclose(b, b_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(a, a_ref, rtol=1e-12, atol=1e-15)


def test_vectorised_over_signals_and_axis():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 400))
    y = cfc_filter(x, 1e-4, 180)
    y0 = cfc_filter(x.T, 1e-4, 180, axis=0)
    for row, out in zip(x, y):
        np.testing.assert_array_equal(cfc_filter(row, 1e-4, 180), out)
    np.testing.assert_allclose(y0.T, y, rtol=0, atol=1e-12)


def test_constant_passes_unchanged_including_the_ends():
    # The odd reflection and steady-state start leave no start-up transient on a constant.
    np.testing.assert_allclose(cfc_filter(np.full(300, 7.0), 1e-4, 60), 7.0, rtol=1e-12)


@pytest.mark.parametrize("cfc, dt, field", [(100, 1e-4, "cfc"), ("60", 1e-4, "cfc"), (1000, 2e-4, "time"),
                                            (60, 0.0, "time")])
def test_bad_class_or_too_slow_sampling(cfc, dt, field):
    with pytest.raises(InputError) as err:
        cfc_filter(np.zeros(100), dt, cfc)
    assert err.value.field == field


def test_non_finite_samples_are_refused():
    with pytest.raises(InputError, match="finite"):
        cfc_filter(np.r_[np.zeros(50), np.nan], 1e-4, 60)


def _pulse(**kw):
    t = np.arange(-100, 1000) * 1e-4
    rng = np.random.default_rng(1)
    decel = 30 * G0 * np.sin(np.pi * np.clip(t, 0, 0.08) / 0.08) + rng.normal(0, 2 * G0, t.size)
    args = dict(time=t, decel=decel, v0=15.0, front_weight=900.0, rear_weight=700.0, where="run.csv")
    args.update(kw)
    return Pulse(**args)


def test_filter_pulse_filters_raw_once_and_records_the_class():
    raw = _pulse()
    p60 = filter_pulse(raw, 60)
    assert p60.meta["cfc"] == 60 and raw.meta.get("cfc") is None
    np.testing.assert_array_equal(p60.decel, cfc_filter(raw.decel, raw.dt, 60))
    assert filter_pulse(p60, 60) is p60
    assert filter_pulse(p60, 180) is p60  # already more heavily filtered: never double-filter


def test_filter_pulse_brings_a_lighter_class_down():
    p180 = filter_pulse(_pulse(), 180)
    p60 = filter_pulse(p180, 60)
    assert p60.meta["cfc"] == 60
    np.testing.assert_array_equal(p60.decel, cfc_filter(p180.decel, p180.dt, 60))


def test_an_already_filtered_slow_record_is_not_refused():
    # Nothing to filter, so a 1 kHz campaign pulse at CFC 60 passes even when CFC 180 is asked.
    slow = _pulse(time=np.arange(1100) * 1e-3, meta={"cfc": 60})
    assert filter_pulse(slow, 180) is slow


@pytest.mark.parametrize("changes, cfc, field", [
    (dict(meta={"cfc": "abc"}), 60, "cfc"),
    ({}, 90, "cfc"),
    (dict(time=np.arange(1100) * 2e-4), 1000, "time"),  # 5 kHz is too slow for CFC 1000
])
def test_filter_pulse_errors_name_the_file_and_field(changes, cfc, field):
    with pytest.raises(InputError) as err:
        filter_pulse(_pulse(**changes), cfc)
    assert err.value.file == "run.csv" and err.value.field == field


def test_filtered_noise_is_the_middle_of_a_longer_filtered_draw():
    got = filtered_noise(np.random.default_rng(1), (2, 300), 1e-4, 60, std=2.0, pad=50)
    expected = cfc_filter(np.random.default_rng(1).normal(0.0, 2.0, (2, 400)), 1e-4, 60)[:, 50:-50]
    assert got.shape == (2, 300)
    np.testing.assert_array_equal(got, expected)
    assert filtered_noise(np.random.default_rng(1), 300, 1e-4, 60).shape == (300,)
