"""ISO-MME reader: pyisomme-written fixtures of test 10146, synthetic folders and bad input."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from fakes import G0, MMESpec, mme_specs, write_mme
from hypothesis import HealthCheck, given, settings

from crashfuse.errors import InputError
from crashfuse.io.isomme import ChannelCode, parse_fields, read_isomme, read_test
from crashfuse.io.nhtsa import read_nhtsa

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
ISO = SHARED / "isomme" / "v10146_isomme"
ISO_12K5 = SHARED / "isomme" / "v10146_isomme_12k5"
EV5 = SHARED / "nhtsa" / "v10146"
real = pytest.mark.skipif(not (ISO.is_dir() and ISO_12K5.is_dir() and EV5.is_dir()), reason="shared data absent")


def _ev5_raw(channel: int) -> tuple[np.ndarray, np.ndarray]:
    data = np.loadtxt(EV5 / f"v10146.{channel:03d}", delimiter="\t")
    return data[:, 0], data[:, 1]


def test_channel_code_parts():
    c = ChannelCode.parse("10VEHCCG0000ACXP")
    assert (c.test_object, c.position, c.main_location) == ("1", "0", "VEHC")
    assert (c.fine_location_1, c.fine_location_2, c.fine_location_3) == ("CG", "00", "00")
    assert (c.dimension, c.direction, c.filter_class, c.cfc) == ("AC", "X", "P", None)
    assert ChannelCode.parse("11HEAD0000H3ACXD").cfc == 60
    with pytest.raises(InputError, match="16-character"):
        ChannelCode.parse("10VEHCCG00ACXP")


def test_fields_split_at_column_29_or_first_colon():
    lines = ["Timestamp                   :2020-01-01 12:30:00", "Comments:a", "Comments                    :NOVALUE"]
    assert parse_fields(lines, Path("x")) == {"Timestamp": ["2020-01-01 12:30:00"], "Comments": ["a", None]}


# --- real data --------------------------------------------------------------------------


@real
def test_channel_list_of_the_fixture():
    t = read_test(ISO)
    codes = {n: c.code for n, (c, _) in t.channels.items()}
    # The .chn (and each channel's Comments) put EV5 channel 95 at 003, the README lists it last.
    assert codes[3] == "10ENGNTP0000ACXP" and codes[6] == "10SEATLEL1REACXP"
    assert len(t.fields["Comments"]) == 2


@real
def test_agrees_with_the_ev5_reader_sample_by_sample():
    iso, ev5 = read_isomme(ISO), read_nhtsa(EV5)
    assert iso.meta["channels"] == ["10SEATLERE00ACXP", "10SEATRIRE00ACXP"]
    assert iso.v0 == pytest.approx(ev5.v0, rel=1e-12)
    assert iso.mass == pytest.approx(ev5.mass, rel=1e-12)
    assert iso.meta["cfc"] is None and iso.meta["axle_split"] == "assumed"
    assert iso.front_weight == iso.rear_weight and any("assumed" in w for w in iso.meta["warnings"])
    np.testing.assert_allclose(iso.time, ev5.time, atol=1e-12)
    np.testing.assert_allclose(iso.decel, ev5.decel, atol=1e-6 * G0)  # 6-decimal rounding, in g


@real
def test_given_axle_masses_are_used():
    p = read_isomme(ISO, front_weight=961.0, rear_weight=758.0)
    assert (p.front_weight, p.rear_weight) == (961.0, 758.0)
    assert "axle_split" not in p.meta and p.meta["warnings"] == []


@real
def test_12k5_folder_has_its_own_time_base_and_matches_the_ev5_data():
    p = read_isomme(ISO_12K5)
    assert p.time.size == 2751
    assert p.time[0] == pytest.approx(-0.02) and p.dt == pytest.approx(80e-6)
    # pyisomme interpolated the EV5 channels linearly onto this grid: do the same from the raw files.
    rows = []
    for channel in (93, 94):
        t, a = _ev5_raw(channel)
        a = np.interp(p.time, t, a)
        rows.append(a - a[p.time < -40e-6].mean())
    np.testing.assert_allclose(p.decel, -G0 * np.mean(rows, axis=0), atol=2e-6 * G0)


@real
def test_explicit_channels_and_engine(tmp_path):
    p = read_isomme(ISO, channels=[6, 7])
    assert p.meta["channels"] == ["10SEATLEL1REACXP", "10SEATRIR1REACXP"]
    with pytest.raises(InputError, match=r"10146\.004.*not an X acceleration"):
        read_isomme(ISO, channels=[4])
    with pytest.raises(InputError, match="channel 9 is not in the channel list"):
        read_isomme(ISO, channels=[9])


# --- synthetic folders ------------------------------------------------------------------


@settings(max_examples=30, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(spec=mme_specs())
def test_reader_recovers_a_synthetic_test(tmp_path_factory, spec: MMESpec):
    w = write_mme(tmp_path_factory.mktemp("mme"), spec)
    p = read_isomme(w.folder, front_weight=600.0, rear_weight=500.0)
    scale = G0 if spec.unit == "g" else 1.0
    rows = []
    for c in w.pulse_channels:
        t, v, _ = w.data[c]
        rows.append(scale * (v - v[t < -1e-12].mean()))
    np.testing.assert_allclose(p.time, w.data[w.pulse_channels[0]][0], atol=1e-12)
    np.testing.assert_allclose(p.decel, -np.mean(rows, axis=0), atol=1e-9)
    assert p.v0 == spec.v0 and p.meta["mass_kg"] == spec.mass
    assert p.meta["cfc"] == {"P": None, "0": None, "A": 1000, "B": 600, "C": 180, "D": 60}[spec.filter_class]
    assert len(p.meta["channels"]) == (1 if spec.with_cg else 2)


# --- bad input --------------------------------------------------------------------------

BASE = MMESpec(v0=15.0, mass=1500.0, dt_us=100, k0=20, n=100, with_cg=False, filter_class="P", unit="g",
               crlf=False, upper_names=False, padded=True, seed=3)


@pytest.fixture
def fake(tmp_path):
    return write_mme(tmp_path / "t1", BASE)


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def test_novalue_velocity(fake):
    _edit(fake.folder / "t1.mme", ":15.0", ":NOVALUE")
    with pytest.raises(InputError, match=r"t1\.mme: field 'Velocity test object 1': missing or NOVALUE"):
        read_isomme(fake.folder)


def test_missing_channel_file(fake):
    (fake.folder / "Channel" / "t1.002").unlink()
    with pytest.raises(InputError, match=r"Channel: field 'channel file': missing channel file 't1.002'"):
        read_isomme(fake.folder)


@pytest.mark.parametrize("bad", ["1.0e", "inf"])
def test_non_numeric_sample(fake, bad):
    path = fake.folder / "Channel" / "t1.001"
    lines = path.read_text().splitlines()
    lines[-5] = bad
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=rf"t1\.001: field 'data': sample 96.*'{bad}'"):
        read_isomme(fake.folder)


def test_sample_count_mismatch(fake):
    path = fake.folder / "Channel" / "t1.001"
    path.write_text("\n".join(path.read_text().splitlines()[:-3]))
    with pytest.raises(InputError, match=r"t1\.001: field 'Number of samples': found 97 samples, expected 100"):
        read_isomme(fake.folder)


def test_unknown_unit(fake):
    _edit(fake.folder / "Channel" / "t1.002", ":g\n", ":ft/s^2\n")
    with pytest.raises(InputError, match=r"t1\.002: field 'Unit'.*'ft/s\^2'"):
        read_isomme(fake.folder)


def test_unknown_filter_class(fake):
    _edit(fake.folder / "Channel" / "t1.chn", "10SEATLERE00ACXP", "10SEATLERE00ACXQ")
    with pytest.raises(InputError, match=r"t1\.001.*unknown filter class 'Q'"):
        read_isomme(fake.folder)


def test_mixed_filter_classes(fake):
    _edit(fake.folder / "Channel" / "t1.chn", "10SEATLERE00ACXP", "10SEATLERE00ACXD")
    with pytest.raises(InputError, match="mix filter classes"):
        read_isomme(fake.folder)


def test_bad_channel_code_in_list(fake):
    _edit(fake.folder / "Channel" / "t1.chn", "10SEATLERE00ACXP", "10SEAT")
    with pytest.raises(InputError, match=r"t1\.chn: field 'Name of channel 001'.*16-character"):
        read_isomme(fake.folder)


def test_channel_count_mismatch(fake):
    _edit(fake.folder / "Channel" / "t1.chn", ":6", ":7")
    with pytest.raises(InputError, match=r"t1\.chn: field 'Number of channels'"):
        read_isomme(fake.folder)


def test_one_axle_mass_only(fake):
    with pytest.raises(InputError, match="field 'front_weight/rear_weight'"):
        read_isomme(fake.folder, front_weight=800.0)


def test_no_mme_file(tmp_path, fake):
    shutil.rmtree(fake.folder / "Channel")
    with pytest.raises(InputError, match="field 'channel folder'"):
        read_isomme(fake.folder)
    with pytest.raises(InputError, match="expected one ISO-MME test file"):
        read_isomme(tmp_path / "nothing")
