"""Single-mass barrier model: a true single mass, the real NHTSA test 10146, bad input."""

import re
from pathlib import Path

import numpy as np
import pytest
from fakes import EV5Spec, write_ev5

from crashfuse.world.barrier import barrier_campaign, fit_single_mass, impulse_mass, model_pulse, momentum_lag
from crashfuse.cli import main
from crashfuse.signals.dynamics import rollout
from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign
from crashfuse.signals.pulse import Pulse

V10146 = Path(__file__).resolve().parents[2] / "shared" / "data" / "nhtsa" / "v10146"
real = pytest.mark.skipif(not V10146.is_dir(), reason="shared NHTSA data not present")
G0 = 9.80665


# --- a vehicle that really is one mass ----------------------------------------------------

MASS, V0, DT = 1500.0, 15.0, 1e-4


def _load(s):
    """A stiffening crush force (N) with a bump where a stiff member buckles."""
    return 8e5 * s + 2e5 * np.exp(-(((s - 0.3) / 0.05) ** 2))


def _unload(u, f_max, u_end=0.08):
    return f_max * np.clip(1 - u / u_end, 0, None) ** 2


def _single_mass_test() -> tuple[np.ndarray, np.ndarray, Pulse]:
    """A 'test' whose measured deceleration is exactly F / M: time (s), force (N), pulse."""

    def decel(state):
        f_max = _load(state.s_max)
        return np.where(state.loading, _load(state.s), _unload(state.u, f_max)) / MASS

    traj = rollout(decel, V0, DT, 1500)
    pulse = Pulse(traj.time, traj.decel[0], V0, 800.0, 700.0, run_id="T1")
    return traj.time, MASS * traj.decel[0], pulse


def test_a_true_single_mass_is_reproduced():
    time, force, test = _single_mass_test()
    model = fit_single_mass(time, force, test, MASS)
    cae = model_pulse(model, test)
    assert cae.source == "cae" and cae.run_id == "T1_single_mass" and cae.meta["cfc"] == 60
    np.testing.assert_allclose(cae.time, test.time, atol=1e-12)
    # 1e-6 of the peak: interpolation at the very samples the same integrator visits.
    np.testing.assert_allclose(cae.decel, test.decel, rtol=0, atol=1e-6 * test.decel.max())
    assert impulse_mass(time, force, test) == pytest.approx(MASS, rel=1e-3)
    assert np.abs(momentum_lag(time, force, test, MASS)).max() < 1e-6 * MASS * V0


def test_a_heavier_model_mass_crushes_further():
    """The mass is the model's: 10 % more mass on the same force curve crushes further, stops later."""
    time, force, test = _single_mass_test()
    light, heavy = (model_pulse(fit_single_mass(time, force, test, m), test) for m in (MASS, 1.1 * MASS))
    dv_light, dv_heavy = (np.cumsum(p.decel) * DT for p in (light, heavy))
    assert np.argmax(dv_heavy >= V0) > np.argmax(dv_light >= V0)


def test_a_vehicle_that_never_stops_is_an_input_error():
    time, force, test = _single_mass_test()
    short = test.replace(time=test.time[:200], decel=test.decel[:200], where="T1.csv")
    with pytest.raises(InputError, match=r"T1\.csv: field 'decel'.*zero velocity"):
        fit_single_mass(time, force, short, MASS)


def test_a_force_record_shorter_than_the_pulse_is_an_input_error():
    time, force, test = _single_mass_test()
    with pytest.raises(InputError, match=r"field 'force'.*cover the pulse"):
        fit_single_mass(time[:500], force[:500], test.replace(where="T1.csv"), MASS)


def test_a_non_positive_mass_is_an_input_error():
    time, force, test = _single_mass_test()
    with pytest.raises(InputError, match=r"field 'mass'.*> 0 kg"):
        fit_single_mass(time, force, test, 0.0)


# --- the real test ----------------------------------------------------------------------


@real
def test_10146_single_mass_campaign(tmp_path):
    folder, cmp = barrier_campaign(V10146, tmp_path / "camp", "ICE", "FWD")
    campaign = read_campaign(folder)
    assert campaign.tests == ["v10146"] and campaign.cae == ["v10146_single_mass"]
    assert campaign.companion("v10146").run_id == "v10146_single_mass"
    assert campaign.pulses["v10146"].meta["warnings"] == []  # the row's conditions are the EV5's
    mass = cmp["mass_kg"]
    assert mass["test_weight_vehtwt"] == 1719
    assert 0.97 < mass["ratio"] < 1.05  # two instruments, one momentum: within a few per cent
    measured, model = cmp["measured"], cmp["single_mass"]
    assert measured["dynamic_crush_mm"] == pytest.approx(746, abs=2)
    assert 550 < model["dynamic_crush_mm"] < measured["dynamic_crush_mm"]  # the rear body travels further
    assert 60 < model["t_zero_velocity_ms"] < 85 and 30 < model["peak_decel_g"] < 50
    for window, scores in cmp["iso"].items():
        assert 0.3 < scores["overall"] < 0.9, window
    # The powertrain and crushed front stop first: the barrier takes momentum the rear body has not lost.
    lag = cmp["momentum_lag"]
    assert 25 < lag["t_peak_ms"] < 60 and lag["peak_Ns"] > 0.1 * 1719 * 57.09 / 3.6
    assert cmp["energy_kJ"]["ratio"] > 1.05


@real
def test_cli_barrier_model_json(tmp_path, capsys):
    assert main(["barrier-model", str(V10146), "--out", str(tmp_path / "c"), "--json"]) == 0
    out = capsys.readouterr().out
    assert '"0-60"' in out and '"impulse"' in out and '"t_zero_velocity_ms"' in out


# --- bad input --------------------------------------------------------------------------


def _without_barrier(tmp_path: Path) -> Path:
    spec = EV5Spec(test_number=7, speed_kmh=56.0, weight_kg=1500, wheelbase_mm=2700, cg_mm=1200, delt_us=100,
                   nfp=-20, n=100, n_pulse=2, missing_default=False, short_channel=False, crlf=False, seed=1)
    w = write_ev5(tmp_path / "v7", spec)
    lines = w.header.read_text().splitlines()
    barrier_rows = [ln for ln in lines if re.match(r"0\|\d+\|LC\|", ln)]
    assert barrier_rows
    w.header.write_text("\n".join(ln for ln in lines if ln not in barrier_rows) + "\n")
    return w.folder


def test_a_folder_without_barrier_channels_is_an_input_error(tmp_path):
    folder = _without_barrier(tmp_path)
    with pytest.raises(InputError, match=r"v7\.EV5: field 'INSTRUMENTATION'.*barrier load-cell"):
        barrier_campaign(folder, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_cli_without_barrier_channels_exits_2(tmp_path, capsys):
    folder = _without_barrier(tmp_path)
    assert main(["barrier-model", str(folder), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "v7.EV5" in err and "INSTRUMENTATION" in err
