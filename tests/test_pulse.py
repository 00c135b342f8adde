"""The Pulse type validates on construction and reports the file and field."""

import numpy as np
import pytest

from crashfuse import InputError, Pulse
from crashfuse.io.pulse_csv import read_pulse_csv
from crashfuse.signals.pulse import check_samples
from crashfuse.units import G0


def _pulse(**kw):
    t = np.arange(200) * 1e-4
    args = dict(time=t, decel=20 * G0 * np.sin(np.pi * t / t[-1]), v0=15.0, front_weight=900.0,
                rear_weight=700.0, where="p.csv")
    args.update(kw)
    return Pulse(**args)


def test_valid_pulse_has_si_properties():
    p = _pulse()
    assert p.dt == pytest.approx(1e-4)
    assert p.mass == 1600.0
    assert p.decel.dtype == float


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(decel=np.full(200, np.nan)), "decel"),
        (dict(time=np.arange(200)[::-1] * 1e-4), "time"),
        (dict(time=np.r_[np.arange(100) * 1e-4, 0.02 + np.arange(100) * 2e-4]), "time"),
        (dict(time=np.arange(5) * 1e-4, decel=np.zeros(5)), "time"),
        (dict(decel=np.full(200, 9000 * G0)), "decel"),
        (dict(v0=-3.0), "v0"),
        (dict(v0=float("nan")), "v0"),
        (dict(rear_weight=0.0), "rear_weight"),
        (dict(source="sim"), "source"),
        (dict(decel=np.zeros(199)), "time/decel"),
    ],
)
def test_bad_pulse_names_file_and_field(change, field):
    with pytest.raises(InputError) as err:
        _pulse(**change)
    assert "p.csv" in str(err.value) and f"'{field}'" in str(err.value)


def test_after_contact_drops_pre_impact_samples():
    t = (np.arange(300) - 100) * 1e-4
    p = _pulse(time=t, decel=np.zeros(300))
    q = p.after_contact()
    assert q.time[0] == pytest.approx(0.0) and q.time.size == 200


def test_input_error_renders_one_line():
    e = InputError("expected a number", "a/b.csv", "v0_mph")
    assert str(e) == "a/b.csv: field 'v0_mph': expected a number"
    assert "\n" not in str(e)
    assert InputError("x").at("f.csv").file == "f.csv"


def test_csv_reader_and_pulse_share_the_sample_checks(tmp_path):
    # Time repeats at data rows 10 and 11: both the Pulse type and the CSV reader say so, the
    # reader naming its file and columns; samples count from 1 like the CSV's data rows.
    t = np.r_[np.arange(10), np.arange(9, 199)] * 1e-4
    decel = np.zeros(200)
    path = tmp_path / "p.csv"
    path.write_text("time_s,decel_mps2\n" + "".join(f"{float(x)!r},0\n" for x in t))
    with pytest.raises(InputError) as from_pulse:
        _pulse(time=t, decel=decel)
    with pytest.raises(InputError) as from_csv:
        read_pulse_csv(path)
    assert from_csv.value.message == from_pulse.value.message
    assert "sample 11 (0.0009 s) does not follow sample 10" in from_csv.value.message
    assert (from_csv.value.file, from_csv.value.field) == (str(path), "time_s")
    with pytest.raises(InputError) as err:
        check_samples(np.arange(200) * 1e-4, np.full(200, 600 * G0), path, ("time_s", "decel_g"))
    assert (err.value.file, err.value.field) == (str(path), "decel_g") and "wrong units" in err.value.message
