"""Gap localisation on constructed campaigns: a known bump is found where it was put, equal pulses give nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crashfuse.diagnosis import gap as gapmod
from crashfuse.reporting import plots
from crashfuse.signals.dynamics import rollout
from crashfuse.errors import InputError
from crashfuse.diagnosis.gap import locate_gap
from crashfuse.io.campaign import Campaign
from crashfuse.signals.pulse import Pulse
from crashfuse.method.surrogate import CAESurrogate

G = 9.80665  # m/s^2 per g, written here independently of crashfuse.units
DT, N_STEPS = 2e-4, 600  # 0-120 ms
PLATEAU, RAMP, K_UNLOAD = 15 * G, 0.05, 2.0e4  # m/s^2, m, m/s^2 per m
SPEEDS = (11.0, 12.0, 13.0, 14.0, 15.0)  # m/s: every test crushes beyond 0.4 m
BUMP = (0.25, 0.35)  # m, where the constructed tests decelerate more than the CAE
ISO_INNER = 0.05  # ISO/TS 18571 inner corridor: 5 % of the reference's peak, the practical floor


def above_floor(lo, hi, amplitude_g, peak_g):
    """Where a sin^2 bump of ``amplitude_g`` on [lo, hi] exceeds 5 % of the test's peak (m, analytic)."""
    z = np.arcsin(np.sqrt(ISO_INNER * peak_g / amplitude_g)) / np.pi
    return lo + z * (hi - lo), hi - z * (hi - lo)


def hann(s, lo, hi, amplitude):
    """A smooth bump of ``amplitude`` m/s^2 on [lo, hi] m, zero elsewhere."""
    z = np.clip((np.asarray(s) - lo) / (hi - lo), 0.0, 1.0)
    return amplitude * np.sin(np.pi * z) ** 2


def crush_law(extra):
    """Deceleration of a ramp-plateau crush law plus ``extra(s)``; elastic unloading from the peak."""
    def decel(state):
        load = np.minimum(state.s / RAMP, 1.0) * PLATEAU + extra(state.s)
        peak = np.minimum(state.s_max / RAMP, 1.0) * PLATEAU + extra(state.s_max)
        return np.where(state.loading, load, np.maximum(peak - K_UNLOAD * state.u, 0.0))
    return decel


def pulse(decel_fn, v0, run_id, source, noise=0.0, seed=0, **meta):
    traj = rollout(decel_fn, v0, DT, N_STEPS)
    a = traj.decel[0] + noise * np.random.default_rng(seed).standard_normal(traj.time.size)
    return Pulse(traj.time, a, v0, 900.0 + 10 * v0, 700.0, run_id, source,
                 {"powertrain": "Type I", "drive": "FWD", "cfc": 60, **meta})


def cae_runs():
    """A companion CAE run per test speed and five more between them (the surrogate needs ten)."""
    speeds = [*SPEEDS, *(v + 0.5 for v in SPEEDS)]
    return [pulse(crush_law(lambda s: 0.0 * s), v, f"C{i}", "cae") for i, v in enumerate(speeds)]


def campaign(bump_g=0.0, bump=BUMP, noise_g=0.02, speeds=SPEEDS, cae=True):
    """Tests = CAE crush law + a bump (in g) on ``bump`` m, plus white noise; one companion CAE run each."""
    extra = (lambda s: hann(s, *bump, bump_g * G))
    runs = [pulse(crush_law(extra), v, f"T{i}", "test", noise_g * G, seed=i, cae_run_id=f"C{i}" if cae else None)
            for i, v in enumerate(speeds)]
    if cae:
        runs += cae_runs()
    return Campaign.from_pulses(runs)


@pytest.fixture(scope="module")
def surrogate():
    """Fitted once: every constructed campaign has the same CAE runs."""
    return CAESurrogate(n_components=3, n_unload_components=2, random_state=0).fit(cae_runs())


@pytest.fixture(scope="module")
def bumped(surrogate):
    return locate_gap(campaign(bump_g=3.0), surrogate=surrogate, k=1, windows_ms=((0, 60),))


def test_a_known_bump_is_found_on_its_displacement_interval_and_ranked_first(bumped):
    top = bumped.intervals[0]
    assert (top.branch, top.sign) == ("loading", 1)
    # The 3 g bump on the 15 g plateau (peak 18 g) exceeds its 0.9 g floor on (0.2685, 0.3315) m.
    lo, hi = above_floor(*BUMP, 3.0, 18.0)
    assert (top.x_lo, top.x_hi) == pytest.approx((lo, hi), abs=0.004)
    assert top.x_peak == pytest.approx(0.30, abs=0.005)
    assert top.share > 0.95 and set(top.tests) == {f"T{i}" for i in range(len(SPEEDS))}
    assert len(bumped.intervals) == 1
    assert [i.share for i in bumped.intervals] == sorted((i.share for i in bumped.intervals), reverse=True)


def test_time_windows_are_when_each_test_is_inside_the_interval(bumped):
    top = bumped.intervals[0]
    for t in bumped.tests:
        t_lo, t_hi = top.windows[t.test_id]
        p = t.profiles["loading"]
        # The test's own displacement at those times (integrated here independently by cumulative sums).
        v = t.v0 - np.concatenate([[0.0], np.cumsum(0.5 * (t.decel[1:] + t.decel[:-1]) * DT)])
        s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * DT)])
        assert np.interp([t_lo, t_hi], t.time, s) == pytest.approx([top.x_lo, min(top.x_hi, p.x[-1])], abs=2e-3)
    faster = [top.windows[f"T{i}"][0] for i in range(len(SPEEDS))]
    assert faster == sorted(faster, reverse=True)  # a faster test reaches the interval sooner


def test_equal_pulses_give_no_significant_interval(surrogate):
    c = campaign(bump_g=0.0)
    g = locate_gap(c, surrogate=surrogate, k=1, windows_ms=((0, 60),))
    assert g.intervals == (), [(i.branch, i.x_lo, i.x_hi, i.share) for i in g.intervals]
    assert not g.map_significant.any()
    assert all(not p.significant.any() for t in g.tests for p in t.profiles.values())


def test_share_ranks_a_large_bump_above_a_small_one(surrogate):
    bumps = [(0.06, 0.13, 4.0), (0.25, 0.35, 2.0)]  # m, m, g; peak 19 g: floor 0.95 g
    law = crush_law(lambda s: sum(hann(s, lo, hi, a * G) for lo, hi, a in bumps))
    tests = [pulse(law, v, f"T{i}", "test", 0.02 * G, seed=i, cae_run_id=f"C{i}") for i, v in enumerate(SPEEDS)]
    c = Campaign.from_pulses(tests + cae_runs())
    g = locate_gap(c, surrogate=surrogate, k=1, windows_ms=((0, 60),))
    # Expected shares: each bump's squared mass above its floor over the squared mass of both.
    s = np.linspace(0.0, 0.4, 40001)
    mass = [np.trapezoid(hann(s, lo, hi, a) ** 2 * (s >= f[0]) * (s <= f[1]), s)
            for lo, hi, a in bumps for f in [above_floor(lo, hi, a, 19.0)]]
    total = sum(np.trapezoid(hann(s, lo, hi, a) ** 2, s) for lo, hi, a in bumps)
    first, second = g.intervals
    assert first.x_hi < 0.15 < 0.2 < second.x_lo
    assert (first.share, second.share) == pytest.approx((mass[0] / total, mass[1] / total), abs=0.02)


def test_opposite_signs_on_one_interval_split_the_share_without_double_counting(surrogate):
    def law(v):  # slower tests decelerate less than the CAE on BUMP, faster ones more
        return crush_law(lambda s: hann(s, *BUMP, (3.0 if v > 12.5 else -3.0) * G))
    tests = [pulse(law(v), v, f"T{i}", "test", 0.02 * G, seed=i, cae_run_id=f"C{i}") for i, v in enumerate(SPEEDS)]
    c = Campaign.from_pulses(tests + cae_runs())
    g = locate_gap(c, surrogate=surrogate, k=1, windows_ms=((0, 60),))
    up, down = g.intervals
    assert (up.sign, set(up.tests)) == (1, {"T2", "T3", "T4"}) and (down.sign, set(down.tests)) == (-1, {"T0", "T1"})
    assert (down.x_lo, down.x_hi) == pytest.approx(above_floor(*BUMP, 3.0, 15.0), abs=0.004)
    # Equal bumps: three tests' squared mass against two, each cut at its floor (18 g and 15 g peaks).
    assert up.share / down.share == pytest.approx(1.5, rel=0.05)
    assert up.share + down.share == pytest.approx(0.97, abs=0.02)


def test_sub_scores_deficits_add_up_to_the_overall_deficit(bumped):
    w = bumped.windows["0-60"]
    for scores in w["tests"].values():
        deficits = [gapmod.WEIGHTS[k] * (1 - scores[k]) for k in gapmod.SUBSCORES]
        assert sum(deficits) == pytest.approx(1 - scores["overall"], abs=1e-9)
        assert scores["carrier"] == gapmod.SUBSCORES[int(np.argmax(deficits))]
    assert w["ranking"] == sorted(w["mean_deficit"], key=lambda k: -w["mean_deficit"][k])


def test_to_json_is_plain_json_with_units_in_the_keys(bumped, tmp_path):
    doc = json.loads(json.dumps(bumped.to_json()))
    top = doc["intervals"][0]
    assert top["rank"] == 1 and top["x_lo_m"] == pytest.approx(bumped.intervals[0].x_lo)
    assert {"t_lo_ms", "t_hi_ms", "test_id", "significant"} <= set(top["windows"][0])
    r = doc["regimes"][0]
    assert r["v0_lo_mph"] == pytest.approx(r["v0_lo_mps"] / 0.44704)
    assert set(doc["windows"]) == {"0-60"}
    assert plots.save_png(plots.bias_map_figure(bumped), tmp_path / "map.png").stat().st_size > 0
    assert plots.save_png(plots.gap_pulses_figure(bumped), tmp_path / "pulses.png").stat().st_size > 0


@pytest.mark.parametrize("make, field", [
    (lambda: Campaign.from_pulses([pulse(crush_law(lambda s: 0 * s), 12.0, "T0", "test", cae_run_id="C0"),
                                   pulse(crush_law(lambda s: 0 * s), 12.0, "C0", "cae")]), "source"),
    (lambda: campaign(cae=False), "source"),
])
def test_one_test_or_no_cae_runs_is_an_input_error(make, field):
    with pytest.raises(InputError, match="at least two tests|no CAE runs") as err:
        locate_gap(make())
    assert err.value.field == field


def test_a_bad_window_is_an_input_error():
    with pytest.raises(InputError, match="windows"):  # refused before anything is fitted
        locate_gap(campaign(bump_g=3.0), windows_ms=((40, 20),))
