"""NHTSA EV5 reader: the real test 10146, synthetic folders (hypothesis) and bad input."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from fakes import G0, EV5Spec, ev5_specs, write_ev5
from hypothesis import HealthCheck, given, settings

from crashfuse.errors import InputError
from crashfuse.io.nhtsa import barrier_channels, read_barrier_force, read_header, read_nhtsa
from crashfuse.signals.filters import cfc_filter
from crashfuse.world.noise_control import NOISE_G

SHARED = Path(__file__).resolve().parents[2] / "shared"
V10146 = SHARED / "data" / "nhtsa" / "v10146"
real = pytest.mark.skipif(not V10146.is_dir(), reason="shared NHTSA data not present")


def _raw(channel: int) -> tuple[np.ndarray, np.ndarray]:
    """A channel file read with numpy alone."""
    data = np.loadtxt(V10146 / f"v10146.{channel:03d}", delimiter="\t")
    return data[:, 0], data[:, 1]


# --- real data --------------------------------------------------------------------------


@real
def test_header_of_10146_matches_the_readme():
    h = read_header(V10146)
    assert h.test["number"] == "10146"
    assert h.test["impact_speed_kmh"] == 57.09
    assert (h.vehicle["test_weight_kg"], h.vehicle["curb_weight_kg"]) == (1719, 1514)
    assert (h.vehicle["wheelbase_mm"], h.vehicle["cg_behind_front_axle_mm"]) == (2825, 1246)
    assert h.vehicle["year"] == 2018
    inst = h.instrumentation.set_index("channel")
    assert len(inst) == 634
    assert inst.loc[96, ["last_index", "status"]].tolist() == [669, "CF"]
    assert "No valid data after 67ms" in inst.loc[96, "description"]
    assert inst.loc[99, "primary_redundant"] == "R"
    assert inst.loc[93, ["first_index", "time_step_us", "units", "prefilter_hz"]].tolist() == [-500, 100, "G'S", "2800"]


@real
def test_default_pulse_of_10146_is_the_mean_of_93_and_94():
    p = read_nhtsa(V10146)
    assert p.meta["channels"] == [93, 94]
    assert p.meta["cfc"] is None and p.meta["warnings"] == []
    assert p.v0 == pytest.approx(57.09 / 3.6)
    # README: roughly 961 kg on the front axle and 758 kg on the rear.
    assert (round(p.front_weight), round(p.rear_weight)) == (961, 758)
    t, a93 = _raw(93)
    _, a94 = _raw(94)
    pre = t < -1e-9
    expected = -G0 * ((a93 - a93[pre].mean()) + (a94 - a94[pre].mean())) / 2
    np.testing.assert_allclose(p.time, t, atol=1e-9)
    np.testing.assert_allclose(p.decel, expected, atol=1e-9)
    assert p.time[0] == pytest.approx(-0.05) and p.run_id == "v10146"


@real
def test_10146_pulse_is_physical():
    """The crossmember pulse stops the car: its integral reaches v0 (plus a small rebound)."""
    p = read_nhtsa(V10146).after_contact()
    dv = np.trapezoid(p.decel[p.time <= 0.15], p.time[p.time <= 0.15])
    assert p.v0 < dv < 1.25 * p.v0


@real
def test_the_noise_controls_level_is_what_10146s_accelerometers_read_before_contact():
    """``NOISE_G``: each X accelerometer at CFC 60 over the 45 ms before contact reads 0.040 and 0.047 g
    (the two averaged, as the default pulse is, 0.038 g: the control's level is one accelerometer's)."""
    levels = []
    for channel in (93, 94):
        t, x = _raw(channel)
        filtered = cfc_filter(x - x[t < 0].mean(), t[1] - t[0], 60)
        levels.append(filtered[t < -0.005].std())
    assert np.mean(levels) == pytest.approx(NOISE_G, abs=0.002)


@real
def test_barrier_impulse_matches_the_vehicle_pulse():
    """Two independent instruments: barrier impulse / mass = velocity change of the car (to 5 %)."""
    t, f = read_barrier_force(V10146)
    used, skipped = barrier_channels(read_header(V10146))
    assert len(used) == 174 and len(skipped) == 2  # cells 347 and 500 flagged 'No valid data'
    p = read_nhtsa(V10146)
    window = (t >= 0) & (t <= 0.1)
    impulse = np.trapezoid(f[window], t[window]) / p.mass
    dv = np.trapezoid(p.decel[window], p.time[window])
    assert impulse == pytest.approx(dv, rel=0.05)
    assert f.max() > 5e5  # a 57 km/h NCAP test peaks well above 500 kN


@real
def test_explicit_flagged_or_missing_channel_is_an_error():
    for channel, words in ((96, "flagged 'CF'"), (91, "flagged 'NO'")):
        with pytest.raises(InputError, match=f"v10146.{channel:03d}.*channel {channel}.*{words}"):
            read_nhtsa(V10146, channels=[channel])


@real
def test_explicit_channels_redundant_twins():
    """The redundant twins measure the same velocity change (raw peaks differ by their own noise)."""
    twins, primary = read_nhtsa(V10146, channels=[99, 100]), read_nhtsa(V10146)
    assert twins.meta["channels"] == [99, 100]
    window = (primary.time >= 0) & (primary.time <= 0.1)
    dv = [np.trapezoid(p.decel[window], p.time[window]) for p in (twins, primary)]
    assert dv[0] == pytest.approx(dv[1], rel=0.02)


@real
def test_missing_default_channel_file_is_skipped_with_a_warning(tmp_path):
    folder = tmp_path / "v10146"
    folder.mkdir()
    for name in ("v10146.EV5", "v10146.093"):
        shutil.copy(V10146 / name, folder / name)
    p = read_nhtsa(folder)
    assert p.meta["channels"] == [93]
    assert any("94" in w and "no data file" in w for w in p.meta["warnings"])
    with pytest.raises(InputError, match=r"v10146\.094.*channel 94.*no data file"):
        read_nhtsa(folder, channels=[93, 94])


# --- synthetic folders ------------------------------------------------------------------


@settings(max_examples=30, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(spec=ev5_specs())
def test_reader_recovers_a_synthetic_test(tmp_path_factory, spec: EV5Spec):
    w = write_ev5(tmp_path_factory.mktemp("ev5"), spec)
    p = read_nhtsa(w.folder)
    assert p.meta["channels"] == w.pulse_channels
    assert p.v0 == pytest.approx(spec.speed_kmh / 3.6)
    assert p.rear_weight == pytest.approx(spec.weight_kg * spec.cg_mm / spec.wheelbase_mm)
    assert p.mass == pytest.approx(spec.weight_kg)
    n = min(w.data[c][0].size for c in w.pulse_channels)  # a short channel cuts the pulse
    rows = []
    for c in w.pulse_channels:
        t, v = w.data[c]
        rows.append(v[:n] - v[t < 0].mean())
    np.testing.assert_allclose(p.time, w.data[w.pulse_channels[0]][0][:n], atol=1e-12)
    np.testing.assert_allclose(p.decel, -G0 * np.mean(rows, axis=0), atol=1e-9)
    assert any("valid only" in m for m in p.meta["warnings"]) == spec.short_channel
    assert any("common span" in m for m in p.meta["warnings"]) == (spec.short_channel and spec.n_pulse == 2)
    assert any("skipped" in m for m in p.meta["warnings"]) == spec.missing_default
    t, f = read_barrier_force(w.folder)
    expected = -sum(w.data[c][1] - w.data[c][1][w.data[c][0] < 0].mean() for c in w.barrier_channels)
    np.testing.assert_allclose(f, expected, atol=1e-6)


# --- bad input --------------------------------------------------------------------------

BASE = EV5Spec(test_number=7, speed_kmh=56.0, weight_kg=1500, wheelbase_mm=2700, cg_mm=1200, delt_us=100,
               nfp=-20, n=100, n_pulse=2, missing_default=False, short_channel=False, crlf=False, seed=1)


@pytest.fixture
def fake(tmp_path):
    return write_ev5(tmp_path / "v7", BASE)


def _edit(path: Path, old: str, new: str, count: int = 1) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, count))


def test_missing_instrumentation_section(fake):
    text = fake.header.read_text()
    fake.header.write_text(text[: text.index("----- INSTRUMENTATION")])
    with pytest.raises(InputError, match=r"v7\.EV5: field 'INSTRUMENTATION'.*missing"):
        read_nhtsa(fake.folder)


def test_short_instrumentation_row(fake):
    lines = fake.header.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("1|3|"))
    lines[i] = "|".join(lines[i].split("|")[:12])
    fake.header.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"v7\.EV5: field 'INSTRUMENTATION'.*12 fields, expected 20"):
        read_nhtsa(fake.folder)


def test_short_test_row(fake):
    lines = fake.header.read_text().splitlines()
    i = lines.index("----- TEST -----") + 1
    lines[i] = "|".join(lines[i].split("|")[:10])
    fake.header.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"v7\.EV5: field 'TEST'.*expected at least 15"):
        read_nhtsa(fake.folder)


def test_non_numeric_header_field(fake):
    _edit(fake.header, "|2700|", "|27OO|")
    with pytest.raises(InputError, match=r"v7\.EV5: field 'VEHICLE WHLBAS'.*'27OO'"):
        read_nhtsa(fake.folder)


def test_cg_outside_the_wheelbase(fake):
    _edit(fake.header, "|1200|", "|2800|")
    with pytest.raises(InputError, match="field 'VEHICLE VEHCG'"):
        read_nhtsa(fake.folder)


def test_wrong_column_count(fake):
    path = fake.folder / "v7.003"
    lines = path.read_text().splitlines()
    lines[10] += "\t1.0"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"v7\.003: field 'columns'.*line 11.*got 3"):
        read_nhtsa(fake.folder)


@pytest.mark.parametrize("bad", ["n/a", "nan"])
def test_non_numeric_value(fake, bad):
    path = fake.folder / "v7.004"
    lines = path.read_text().splitlines()
    lines[5] = lines[5].split("\t")[0] + "\t" + bad
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=rf"v7\.004: field 'value'.*line 6.*'{bad}'"):
        read_nhtsa(fake.folder)


def test_non_uniform_time(fake):
    path = fake.folder / "v7.003"
    lines = path.read_text().splitlines()
    del lines[40]
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"v7\.003: field 'time'.*uniform"):
        read_nhtsa(fake.folder)


def test_truncated_channel_file(fake):
    path = fake.folder / "v7.003"
    path.write_text("\n".join(path.read_text().splitlines()[:50]))
    with pytest.raises(InputError, match=r"v7\.003: field 'samples'.*expected 100 samples.*got 50"):
        read_nhtsa(fake.folder)


def test_empty_channel_file(fake):
    (fake.folder / "v7.003").write_text("")
    with pytest.raises(InputError, match=r"v7\.003: field 'columns'"):
        read_nhtsa(fake.folder)


def test_unknown_channel(fake):
    with pytest.raises(InputError, match=r"v7\.EV5: field 'CURNO'.*channel 55"):
        read_nhtsa(fake.folder, channels=[55])


def test_not_an_x_accelerometer(fake):
    with pytest.raises(InputError, match="channel 8 is AC on axis ZG"):
        read_nhtsa(fake.folder, channels=[8])


def test_no_header_file(tmp_path):
    with pytest.raises(InputError, match="expected one NHTSA header file"):
        read_nhtsa(tmp_path)
