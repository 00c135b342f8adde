"""The campaign folder format: round trips, unit conversion, real data and every bad input."""

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crashfuse.signals import filters
from crashfuse.errors import InputError
from crashfuse.io import campaign_write, pulse_csv
from crashfuse.io.campaign import Campaign, read_campaign
from crashfuse.io.campaign_write import write_campaign
from crashfuse.io.conditions import CANONICAL
from crashfuse.io.pulse_csv import read_pulse_csv, write_pulse_csv
from crashfuse.io.tables import is_blank
from crashfuse.io.nhtsa import read_nhtsa
from crashfuse.io.loading import load_pulses
from crashfuse.signals.pulse import Pulse

SHARED = Path(__file__).resolve().parents[2] / "shared"
NHTSA = SHARED / "data" / "nhtsa" / "v10146"
ISOMME = SHARED / "data" / "isomme" / "v10146_isomme"
# Exact unit definitions (NIST SP 811), written here independently of crashfuse.units.
G_N, MPH_MPS, KMH_MPS, LB_KG = 9.80665, 0.44704, 1 / 3.6, 0.45359237
HEADER = "run_id,source,v0_mph,front_weight_lb,rear_weight_lb,powertrain,drive,cae_run_id"


def half_sine(v0, n=400, dt=1e-4, duration=0.06, restitution=0.2):
    """A half-sine pulse whose velocity change is v0 (1 + restitution), in m/s^2."""
    t = np.arange(n) * dt
    peak = v0 * (1 + restitution) * np.pi / (2 * duration)
    return t, np.where(t <= duration, peak * np.sin(np.pi * t / duration), 0.0)


def make_pulse(run_id, source, v0=15.0, fw=900.0, rw=700.0, cfc=60, **meta):
    t, a = half_sine(v0)
    return Pulse(t, a, v0, fw, rw, run_id, source, meta={"powertrain": "ICE", "drive": "FWD", "cfc": cfc, **meta})


def write_folder(root: Path, rows: list[str], header: str = HEADER, pulses: dict | None = None) -> Path:
    """A campaign folder from conditions rows; every run gets a valid half-sine pulse unless given."""
    (root / "pulses").mkdir(parents=True, exist_ok=True)
    (root / "conditions.csv").write_text("\n".join([header, *rows]) + "\n")
    for row in rows:
        run_id = row.split(",")[0]
        text = (pulses or {}).get(run_id)
        if text is None:
            t, a = half_sine(15.0)
            text = "time_s,decel_g\n" + "".join(f"{float(ti)!r},{float(ai / G_N)!r}\n" for ti, ai in zip(t, a))
        (root / "pulses" / f"{run_id}.csv").write_text(text)
    return root


VALID_ROWS = ["T1,test,33.5,2100,1700,ICE,FWD,C1", "C1,cae,33.5,2100,1700,ICE,FWD,", "C2,cae,25,2100,1700,EV,AWD,"]


def pulse_text(t, a_g, header="time_s,decel_g"):
    return header + "\n" + "".join(f"{x},{y}\n" for x, y in zip(t, a_g))


# --- reading: conversion against independent constants, API --------------------------------------


def test_units_are_converted_to_si_once(tmp_path):
    t = np.arange(100) * 1e-4
    text = pulse_text(t, np.where(t < 0.005, 2.0, 0.0))
    write_folder(tmp_path, ["A,test,35,2000,1000,ICE,RWD"], header=HEADER.removesuffix(",cae_run_id"),
                 pulses={"A": text})
    c = read_campaign(tmp_path, cfc=None)
    row = c.conditions.iloc[0]
    assert row["v0_mps"] == pytest.approx(35 * MPH_MPS, rel=1e-15)
    assert row["front_weight_kg"] == pytest.approx(2000 * LB_KG, rel=1e-15)
    assert row["rear_weight_kg"] == pytest.approx(1000 * LB_KG, rel=1e-15)
    p = c.pulses["A"]
    assert p.decel[:50] == pytest.approx(np.full(50, 2 * G_N), rel=1e-15)
    assert (p.v0, p.front_weight, p.rear_weight) == (row["v0_mps"], row["front_weight_kg"], row["rear_weight_kg"])
    assert list(c.conditions.columns) == list(CANONICAL)


def test_kmh_kg_mps2_variants(tmp_path):
    t = np.arange(100) * 1e-4
    header = "run_id,source,v0_kmh,front_weight_kg,rear_weight_kg,powertrain,drive"
    write_folder(tmp_path, ["A,cae,36,900,700,EV,AWD"], header=header,
                 pulses={"A": pulse_text(t, np.where(t < 0.005, 50.0, 0.0), "time_s,decel_mps2")})
    c = read_campaign(tmp_path)
    assert c.conditions.loc[0, "v0_mps"] == pytest.approx(36 * KMH_MPS, rel=1e-15)
    assert c.pulses["A"].meta["cfc"] == 60


def test_campaign_api(tmp_path):
    write_folder(tmp_path, VALID_ROWS)
    c = read_campaign(tmp_path)
    assert c.tests == ["T1"] and c.cae == ["C1", "C2"]
    assert c.companion("T1") is c.pulses["C1"]
    assert c.companion("C2") is None
    assert c.pulses["T1"].meta["cae_run_id"] == "C1"
    assert c.pulses["C2"].meta["powertrain"] == "EV"
    sub = c.subset(["C1", "T1"])
    assert sub.conditions["run_id"].tolist() == ["T1", "C1"] and sub.companion("T1") is c.pulses["C1"]
    with pytest.raises(InputError, match="'C1' is no run"):
        c.subset(["C2", "T1"])
    with pytest.raises(KeyError):
        c.subset(["nope"])
    assert c.content_hash() == read_campaign(tmp_path).content_hash()
    reordered = Campaign(c.conditions.iloc[::-1].reset_index(drop=True), c.pulses)
    assert reordered.content_hash() == c.content_hash()
    changed = c.conditions.copy()
    changed.loc[0, "v0_mps"] += 1e-9
    assert Campaign(changed, c.pulses).content_hash() != c.content_hash()


def test_extra_columns_are_kept_and_typed(tmp_path):
    header = HEADER + ",lab,barrier_deg"
    write_folder(tmp_path, ["T1,test,35,2000,1500,ICE,FWD,,MGA,0", "C1,cae,35,2000,1500,ICE,FWD,,,30.5"], header)
    c = read_campaign(tmp_path)
    assert c.conditions["barrier_deg"].tolist() == [0.0, 30.5]
    assert c.conditions["lab"].tolist()[0] == "MGA" and pd.isna(c.conditions["lab"].tolist()[1])
    assert c.pulses["C1"].meta["lab"] is None and c.pulses["C1"].meta["barrier_deg"] == 30.5


def test_cfc_column_and_filtering(tmp_path):
    header = HEADER.removesuffix(",cae_run_id") + ",cfc"
    rng = np.random.default_rng(0)
    t, a = half_sine(15.0, n=600)
    noisy = a + rng.normal(0, 20.0, a.size)
    texts = {r: pulse_text(t, noisy / G_N) for r in ("R", "P", "H")}
    write_folder(tmp_path, ["R,cae,33,2000,1500,ICE,FWD,raw", "P,cae,33,2000,1500,ICE,FWD,",
                            "H,cae,33,2000,1500,ICE,FWD,180"], header, texts)
    kept = read_campaign(tmp_path, cfc=None)
    assert [kept.pulses[r].meta["cfc"] for r in "RPH"] == [None, 60, 180]
    assert np.array_equal(kept.pulses["R"].decel, kept.pulses["P"].decel)
    done = read_campaign(tmp_path, cfc=60)
    expected = filters.filter_pulse(kept.pulses["R"], 60)
    np.testing.assert_allclose(done.pulses["R"].decel, expected.decel)
    np.testing.assert_allclose(done.pulses["H"].decel, expected.decel)
    assert np.array_equal(done.pulses["P"].decel, kept.pulses["P"].decel)  # processed: never filtered again


# --- round trip (property based) -----------------------------------------------------------------

EXTRA_TEXT = st.one_of(st.none(), st.text("abcXYZ ,\"'_-é", min_size=1, max_size=8).map(lambda s: "x" + s.strip()))
EXTRA_NUM = st.one_of(st.none(), st.floats(-1e6, 1e6, allow_nan=False, allow_subnormal=False))


@st.composite
def campaigns(draw):
    n_cae = draw(st.integers(1, 4))
    n_test = draw(st.integers(0, 3))
    extras = draw(st.lists(st.sampled_from(["lab", "note", "angle_deg", "offset_mm"]), max_size=3, unique=True))
    cae_ids = [f"C{i}" for i in range(n_cae)]
    pulses = []
    for i, (rid, source) in enumerate([(c, "cae") for c in cae_ids] + [(f"T{i}", "test") for i in range(n_test)]):
        n = draw(st.integers(16, 120))
        dt = draw(st.sampled_from([1e-4, 8e-5, 5e-5]))
        v0 = draw(st.floats(3.0, 40.0))
        t = np.arange(n) * dt
        shape = draw(st.lists(st.floats(0.0, 1.0), min_size=n, max_size=n))
        a = np.asarray(shape) * min(v0 / (n * dt), 300 * G_N)  # velocity change <= v0, peak <= 300 g
        a[0] = max(a[0], 1e-3)
        meta = {"powertrain": draw(st.sampled_from(["ICE", "EV", "PHEV"])),
                "drive": draw(st.sampled_from(["FWD", "RWD", "AWD"])),
                "cfc": draw(st.sampled_from([60, 60, 180, None]))}
        if source == "test" and draw(st.booleans()):
            meta["cae_run_id"] = draw(st.sampled_from(cae_ids))
        for col in extras:
            meta[col] = draw(EXTRA_TEXT if col in ("lab", "note") else EXTRA_NUM)
        pulses.append(Pulse(t, a, v0, draw(st.floats(100, 3000)), draw(st.floats(100, 3000)), rid, source,
                            meta=meta))
    order = draw(st.permutations(range(len(pulses))))
    units = (draw(st.sampled_from(["mph", "kmh", "mps"])), draw(st.sampled_from(["lb", "kg"])),
             draw(st.sampled_from(["g", "mps2"])))
    return Campaign.from_pulses([pulses[i] for i in order], columns=extras), units


def folder_bytes(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def same_cell(a, b):
    if is_blank(a) or is_blank(b):
        return is_blank(a) and is_blank(b)
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return a == pytest.approx(b, rel=1e-9, abs=1e-300)


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(campaigns())
def test_round_trip_and_deterministic_bytes(tmp_path_factory, drawn):
    original, (speed, mass, accel) = drawn
    base = tmp_path_factory.mktemp("rt")
    write_campaign(original, base / "a", speed, mass, accel)
    write_campaign(original, base / "b", speed, mass, accel)
    assert folder_bytes(base / "a") == folder_bytes(base / "b")
    back = read_campaign(base / "a", cfc=None)
    assert list(back.conditions.columns) == list(original.conditions.columns)
    for (_, r1), (_, r2) in zip(original.conditions.iterrows(), back.conditions.iterrows()):
        for col in original.conditions.columns:
            assert same_cell(r1[col], r2[col]), (col, r1[col], r2[col])
    for rid, p in original.pulses.items():
        q = back.pulses[rid]
        np.testing.assert_allclose(q.time, p.time, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(q.decel, p.decel, rtol=1e-9, atol=1e-9 * np.abs(p.decel).max())
        assert q.meta["cfc"] == p.meta["cfc"]
        assert (q.meta.get("cae_run_id"), q.source) == (p.meta.get("cae_run_id"), p.source)
    write_campaign(back, base / "c", speed, mass, accel)
    assert folder_bytes(base / "c") == folder_bytes(base / "a")


# --- writing --------------------------------------------------------------------------------------


def small_campaign():
    return Campaign.from_pulses([make_pulse("T1", "test", cae_run_id="C1"), make_pulse("C1", "cae")])


def test_write_refuses_non_empty_folder_unless_overwrite(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(InputError, match="not empty") as err:
        write_campaign(small_campaign(), out)
    assert err.value.file == os.fspath(out)
    write_campaign(small_campaign(), out, overwrite=True)
    assert sorted(folder_bytes(out)) == ["conditions.csv", "pulses/C1.csv", "pulses/T1.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("umask, mode", [(0o022, 0o755), (0o077, 0o700)])
def test_written_folders_get_the_permissions_mkdir_gives(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        write_campaign(small_campaign(), tmp_path / "new")
        write_campaign(small_campaign(), tmp_path / "new", overwrite=True)  # the swapped-in copy too
    finally:
        os.umask(old)
    for folder in (tmp_path / "new", tmp_path / "new" / "pulses"):
        assert folder.stat().st_mode & 0o777 == mode, folder


def test_write_failure_leaves_nothing_half_written(tmp_path, monkeypatch):
    calls = []

    def failing(path, *args):
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        return real(path, *args)

    real = campaign_write.write_pulse_file
    monkeypatch.setattr(campaign_write, "write_pulse_file", failing)
    with pytest.raises(OSError):
        write_campaign(small_campaign(), tmp_path / "new")
    assert list(tmp_path.iterdir()) == []
    old = write_folder(tmp_path / "old", VALID_ROWS)
    before = folder_bytes(old)
    calls.clear()
    with pytest.raises(OSError):
        write_campaign(small_campaign(), old, overwrite=True)
    assert folder_bytes(old) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]


def test_extra_files_are_written_with_the_campaign(tmp_path):
    out = write_campaign(small_campaign(), tmp_path / "new", extra_files={"world.json": "{}\n", "key.bin": b"\0\1"})
    assert (out / "world.json").read_text() == "{}\n" and (out / "key.bin").read_bytes() == b"\0\1"
    assert read_campaign(out).tests == ["T1"]  # the reader ignores files it does not know


def test_extra_file_failure_leaves_no_folder_and_keeps_the_old_one(tmp_path, monkeypatch):
    real = Path.write_bytes

    def failing(self, data):
        if self.name == "world.json":
            raise OSError("disk full")
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", failing)
    with pytest.raises(OSError):
        write_campaign(small_campaign(), tmp_path / "new", extra_files={"world.json": "{}"})
    assert list(tmp_path.iterdir()) == []
    old = write_folder(tmp_path / "old", VALID_ROWS)
    before = folder_bytes(old)
    with pytest.raises(OSError):
        write_campaign(small_campaign(), old, overwrite=True, extra_files={"world.json": "{}"})
    assert folder_bytes(old) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]


@pytest.mark.parametrize("extra, field", [({"conditions.csv": "x"}, "extra_files"), ({"pulses": "x"}, "extra_files"),
                                          ({"sub/world.json": "x"}, "extra_files"), ({"..": "x"}, "extra_files"),
                                          ({"a\\b": "x"}, "extra_files"), ({"": "x"}, "extra_files"),
                                          ({"world.json": 3}, "extra_files['world.json']")])
def test_extra_files_need_plain_new_names_and_text_or_bytes(tmp_path, extra, field):
    with pytest.raises(InputError) as err:
        write_campaign(small_campaign(), tmp_path / "x", extra_files=extra)
    assert err.value.field == field
    assert list(tmp_path.iterdir()) == []


def test_write_rejects_unknown_unit(tmp_path):
    with pytest.raises(InputError, match="speed_unit"):
        write_campaign(small_campaign(), tmp_path / "x", speed_unit="fps")
    assert not (tmp_path / "x").exists()


def test_single_pulse_csv_round_trip(tmp_path):
    t, a = half_sine(15.0)
    for unit in ("g", "mps2"):
        write_pulse_csv(tmp_path / f"p_{unit}.csv", t, a, unit=unit)
        t2, a2 = read_pulse_csv(tmp_path / f"p_{unit}.csv")
        np.testing.assert_allclose(t2, t, rtol=1e-9)
        np.testing.assert_allclose(a2, a, rtol=1e-9, atol=1e-9 * a.max())
    assert (tmp_path / "p_g.csv").read_text().splitlines()[0] == "time_s,decel_g"


# --- real data through pulse_path and the dispatcher ----------------------------------------------

needs_nhtsa = pytest.mark.skipif(not NHTSA.is_dir(), reason="shared NHTSA data absent")


def nhtsa_campaign(root: Path, v0_kmh="57.09") -> Path:
    rel = os.path.relpath(NHTSA, root)
    header = HEADER + ",pulse_path"
    return write_folder(root, [f"T10146,test,{v0_kmh},961,758,ICE,FWD,C1,{rel}", "C1,cae,35.47,2119,1671,ICE,FWD,,"],
                        header.replace("v0_mph", "v0_kmh").replace("_lb", "_kg"))


@needs_nhtsa
def test_pulse_path_reads_real_nhtsa_test(tmp_path):
    c = read_campaign(nhtsa_campaign(tmp_path / "camp"))
    p = c.pulses["T10146"]
    assert p.meta["cfc"] == 60 and p.time[0] == pytest.approx(0, abs=0.5 * p.dt)
    assert p.v0 == pytest.approx(57.09 * KMH_MPS)
    # Rigid-barrier physics: velocity change between v0 and 1.5 v0 (restitution 0 .. 0.5).
    dv = np.trapezoid(p.decel, p.time)
    assert p.v0 < dv < 1.5 * p.v0
    assert 20 * G_N < p.decel.max() < 60 * G_N
    assert not p.meta["warnings"]
    assert c.companion("T10146") is c.pulses["C1"]
    # Written elsewhere, the path is re-based and still names the same test.
    out = write_campaign(c, tmp_path / "deeper" / "copy")
    assert not (out / "pulses" / "T10146.csv").exists()
    again = read_campaign(out)
    np.testing.assert_array_equal(again.pulses["T10146"].decel, p.decel)


@needs_nhtsa
def test_pulse_path_row_conditions_win_with_warning(tmp_path):
    p = read_campaign(nhtsa_campaign(tmp_path, v0_kmh="60")).pulses["T10146"]
    assert p.v0 == pytest.approx(60 * KMH_MPS)
    assert any(w.startswith("v0") for w in p.meta["warnings"])


@pytest.mark.skipif(not ISOMME.is_dir(), reason="shared ISO-MME data absent")
def test_pulse_path_reads_isomme_with_row_weights(tmp_path):
    rel = os.path.relpath(ISOMME, tmp_path)
    header = "run_id,source,v0_kmh,front_weight_kg,rear_weight_kg,powertrain,drive,pulse_path"
    write_folder(tmp_path, [f"M,test,57.09,961,758,ICE,FWD,{rel}"], header)
    p = read_campaign(tmp_path).pulses["M"]
    assert (p.front_weight, p.rear_weight) == (961.0, 758.0)
    assert p.meta["cfc"] == 60 and p.v0 < np.trapezoid(p.decel, p.time) < 1.5 * p.v0


@needs_nhtsa
def test_load_pulses_dispatches_on_folder_content(tmp_path):
    write_folder(tmp_path / "camp", VALID_ROWS)
    assert [p.run_id for p in load_pulses(tmp_path / "camp")] == ["T1", "C1", "C2"]
    assert [p.run_id for p in load_pulses(tmp_path / "camp" / "conditions.csv")] == ["T1", "C1", "C2"]
    (raw,) = load_pulses(NHTSA, cfc=None)
    full = read_nhtsa(NHTSA)  # unfiltered and uncropped: pulse_metrics filters before it crops
    assert raw.meta["cfc"] is None and raw.time[0] < 0
    assert np.array_equal(raw.time, full.time) and np.array_equal(raw.decel, full.decel)
    assert load_pulses(NHTSA / "v10146.EV5")[0].meta["cfc"] == 60
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.txt").write_text("x")
    for bad in (tmp_path / "other", tmp_path / "other" / "x.txt", tmp_path / "missing"):
        with pytest.raises(InputError, match="expected a campaign folder"):
            load_pulses(bad)


# --- every bad input: the error names the file and the field --------------------------------------

T, GOOD = half_sine(35 * MPH_MPS, n=1000)  # a realistic 50 g pulse for the 35 mph rows
GOOD_G = GOOD / G_N


BAD_CONDITIONS = {
    "missing column": (HEADER.replace(",drive", ""), ["T1,test,35,2000,1500,ICE,", "C1,cae,35,2000,1500,ICE,"],
                       "drive", "missing required column"),
    "missing quantity": (HEADER.replace(",v0_mph", ""), ["T1,test,2000,1500,ICE,FWD,", "C1,cae,2000,1500,ICE,FWD,"],
                         "v0", "v0_mph"),
    "two unit variants": (HEADER + ",v0_kmh", ["C1,cae,35,2000,1500,ICE,FWD,,56"], "v0_kmh", "two unit variants"),
    "unknown suffix": (HEADER.replace("v0_mph", "v0_fps"), ["C1,cae,35,2000,1500,ICE,FWD,"], "v0_fps",
                       "unknown unit suffix 'fps'"),
    "no unit": (HEADER.replace("rear_weight_lb", "rear_weight"), ["C1,cae,35,2000,1500,ICE,FWD,"], "rear_weight",
                "unit is missing"),
    "blank number": (HEADER, ["C1,cae,,2000,1500,ICE,FWD,"], "v0_mph", "blank"),
    "nan number": (HEADER, ["C1,cae,35,nan,1500,ICE,FWD,"], "front_weight_lb", "finite number"),
    "text number": (HEADER, ["C1,cae,35,2000,heavy,ICE,FWD,"], "rear_weight_lb", "'heavy'"),
    "blank text": (HEADER, ["C1,cae,35,2000,1500,ICE,,"], "drive", "blank"),
    "blank run_id": (HEADER, [",cae,35,2000,1500,ICE,FWD,"], "run_id", "blank"),
    "duplicate run_id": (HEADER, ["C1,cae,35,2000,1500,ICE,FWD,", "c1,cae,36,2000,1500,ICE,FWD,"], "run_id",
                         "duplicate"),
    "path in run_id": (HEADER, ["../C1,cae,35,2000,1500,ICE,FWD,"], "run_id", "file name"),
    "bad source": (HEADER, ["C1,sim,35,2000,1500,ICE,FWD,"], "source", "'sim'"),
    "companion missing": (HEADER, ["T1,test,35,2000,1500,ICE,FWD,C9"], "cae_run_id", "'C9' is no run"),
    "companion is a test": (HEADER, ["T1,test,35,2000,1500,ICE,FWD,T2", "T2,test,35,2000,1500,ICE,FWD,"],
                            "cae_run_id", "a test"),
    "companion on cae row": (HEADER, ["C1,cae,35,2000,1500,ICE,FWD,C2", "C2,cae,35,2000,1500,ICE,FWD,"],
                             "cae_run_id", "only on test rows"),
    "bad cfc": (HEADER + ",cfc", ["C1,cae,35,2000,1500,ICE,FWD,,75"], "cfc", "75"),
    "impossible speed": (HEADER, ["C1,cae,350,2000,1500,ICE,FWD,"], "v0_mph", "got 350"),
    "zero mass": (HEADER, ["C1,cae,35,0,1500,ICE,FWD,"], "front_weight_lb", "got 0"),
    "duplicate header": (HEADER + ",drive", ["C1,cae,35,2000,1500,ICE,FWD,,FWD"], "drive", "duplicate column"),
}


@pytest.mark.parametrize("case", BAD_CONDITIONS, ids=list(BAD_CONDITIONS))
def test_bad_conditions_name_file_and_field(tmp_path, case):
    header, rows, field, words = BAD_CONDITIONS[case]
    write_folder(tmp_path, rows, header)
    with pytest.raises(InputError) as err:
        read_campaign(tmp_path)
    assert err.value.file.endswith("conditions.csv") and err.value.field == field
    assert words in err.value.message


def with_line(text, i, line):
    """``text`` with its line ``i`` (0 = header) replaced."""
    lines = text.splitlines()
    lines[i] = line
    return "\n".join(lines) + "\n"


BAD_PULSES = {
    "missing decel column": ("time_s,accel\n0,1\n", "decel", "decel_mps2, decel_g"),
    "missing time column": ("t,decel_g\n0,1\n", "time", "time_s"),
    "unknown accel unit": (pulse_text(T, GOOD_G, "time_s,decel_fps2"), "decel_fps2", "unknown unit suffix"),
    "nan": (pulse_text(T, np.r_[GOOD_G[:50], np.nan, GOOD_G[51:]]), "decel_g", "data row 51"),
    "blank": (with_line(pulse_text(T, GOOD_G), 30, "0.0029,"), "decel_g", "blank cell (data row 30"),
    "text": (with_line(pulse_text(T, GOOD_G), 30, "0.0029,ten"), "decel_g", "'ten' (data row 30"),
    "decreasing time": (pulse_text(T[::-1], GOOD_G), "time_s", "strictly increasing"),
    "repeated time": (pulse_text(np.r_[T[:10], T[9:999]], GOOD_G), "time_s", "strictly increasing"),
    "non-uniform time": (pulse_text(np.r_[T[:500], 0.0501 + T[:500] * 2], GOOD_G), "time_s", "uniform"),
    "empty": ("time_s,decel_g\n", "time_s", "at least 16"),
    "one sample": ("time_s,decel_g\n0,10\n", "time_s", "got 1"),
    "zero bytes": ("", None, "empty file"),
    "mps2 in a g column": (pulse_text(T, GOOD_G * G_N), "decel", "wrong units"),
    "absurd peak": (pulse_text(T, GOOD_G * 90), "decel_g", "wrong units"),
    "sign flipped": (pulse_text(T, -GOOD_G), "decel", "sign flipped"),
    "starts late": (pulse_text(T + 0.01, GOOD_G), "time_s", "t = 0 at first contact"),
    "ragged": ("time_s,decel_g\n0,1\n0.0001,1,5\n", None, "readable CSV"),
}


@pytest.mark.parametrize("case", BAD_PULSES, ids=list(BAD_PULSES))
@pytest.mark.filterwarnings("error::UserWarning")  # the error names the file; no warning beside it
def test_bad_pulse_files_name_file_and_field(tmp_path, case):
    text, field, words = BAD_PULSES[case]
    write_folder(tmp_path, ["C1,cae,35,2000,1500,ICE,FWD,"], pulses={"C1": text})
    with pytest.raises(InputError) as err:
        read_campaign(tmp_path)
    assert err.value.file.endswith(os.path.join("pulses", "C1.csv")) and err.value.field == field
    assert words in err.value.message


def test_missing_folder_conditions_and_pulse_file(tmp_path):
    with pytest.raises(InputError, match="does not exist") as err:
        read_campaign(tmp_path / "nope")
    assert err.value.file == os.fspath(tmp_path / "nope")
    with pytest.raises(InputError, match="missing conditions.csv") as err:
        read_campaign(tmp_path)
    write_folder(tmp_path, VALID_ROWS)
    (tmp_path / "pulses" / "C2.csv").unlink()
    with pytest.raises(InputError, match="missing pulse file for run 'C2'") as err:
        read_campaign(tmp_path)
    assert err.value.file.endswith("C2.csv")


def test_header_only_conditions(tmp_path):
    write_folder(tmp_path, [])
    with pytest.raises(InputError, match="at least one run"):
        read_campaign(tmp_path)


def test_bad_pulse_path_rows(tmp_path):
    header = HEADER.removesuffix(",cae_run_id") + ",pulse_path,cfc"
    write_folder(tmp_path / "a", ["A,test,35,2000,1500,ICE,FWD,nowhere,"], header)
    with pytest.raises(InputError, match="not a folder") as err:
        read_campaign(tmp_path / "a")
    assert err.value.field == "pulse_path" and err.value.file.endswith("conditions.csv")
    (tmp_path / "a" / "lab").mkdir()
    write_folder(tmp_path / "a", ["A,test,35,2000,1500,ICE,FWD,lab,"], header)
    with pytest.raises(InputError, match=r"\*.EV5 .* \*.mme"):
        read_campaign(tmp_path / "a")
    write_folder(tmp_path / "a", ["A,test,35,2000,1500,ICE,FWD,lab,60"], header)
    with pytest.raises(InputError, match="blank cfc") as err:
        read_campaign(tmp_path / "a")
    assert err.value.field == "cfc"


def test_in_memory_campaign_obeys_the_file_rules():
    with pytest.raises(InputError, match="blank") as err:
        Campaign.from_pulses([make_pulse("A", "cae", drive=None)])
    assert err.value.field == "drive"
    with pytest.raises(InputError, match="file name"):
        Campaign.from_pulses([make_pulse("../A", "cae")])
    with pytest.raises(InputError, match="only on test rows"):
        Campaign.from_pulses([make_pulse("A", "cae", cae_run_id="B"), make_pulse("B", "cae")])
    frame = Campaign.from_pulses([make_pulse("A", "cae")]).conditions
    with pytest.raises(InputError, match="one pulse per run_id"):
        Campaign(frame, {})


def test_plain_and_general_pulse_readers_agree(tmp_path):
    """A plain file takes numpy's fast path; the same numbers quoted, padded and with an extra
    column take pandas' path. Both give bit-identical SI arrays."""
    plain, fancy = tmp_path / "plain.csv", tmp_path / "fancy.csv"
    plain.write_text(pulse_text(T, GOOD_G))
    rows = "".join(f'"x", "{float(x)!r}", {float(y)!r}\n' for x, y in zip(T, GOOD_G))
    fancy.write_text("note, time_s, decel_g\n" + rows)
    assert pulse_csv.plain_pulse_csv(plain) is not None and pulse_csv.plain_pulse_csv(fancy) is None
    for got, want in zip(read_pulse_csv(plain), read_pulse_csv(fancy)):
        np.testing.assert_array_equal(got, want)


def test_pulses_parsed_together_equal_each_file_read_alone(tmp_path):
    """read_campaign parses plain pulse files in one pass; each pulse is bit-identical to its file
    read alone. Units, an extra column and a missing final line feed stay on the joint path; CRLF
    line ends and quotes are read file by file."""
    t, a = (arr.tolist() for arr in half_sine(15.0))
    g = [f"{y / G_N!r}" for y in a]
    texts = {
        "C1": "time_s,decel_g\n" + "\n".join(f"{x!r},{y}" for x, y in zip(t, g)),
        "C2": "time_s,decel_mps2\n" + "".join(f"{x!r},{y!r}\n" for x, y in zip(t, a)),
        "C3": "channel,decel_g,time_s\n" + "".join(f"7,{y},{x!r}\n" for x, y in zip(t, g)),
        "C4": "time_s,decel_g\r\n" + "".join(f"{x!r},{y}\r\n" for x, y in zip(t, g)),
        "T1": "time_s,decel_g\n" + "".join(f'"{x!r}",{y}\n' for x, y in zip(t, g)),
    }
    rows = ["T1,test,33.5,2100,1700,ICE,FWD,C1"] + [f"{r},cae,33.5,2100,1700,ICE,FWD," for r in ("C1", "C2", "C3", "C4")]
    write_folder(tmp_path, rows, pulses=texts)
    files = {r: tmp_path / "pulses" / f"{r}.csv" for r in texts}
    together = pulse_csv.plain_pulse_files(files.values())
    assert sorted(p.stem for p in together) == ["C1", "C2", "C3"]
    campaign = read_campaign(tmp_path)
    for run_id, path in files.items():
        alone = read_pulse_csv(path)
        np.testing.assert_array_equal(campaign.pulses[run_id].time, alone[0])
        np.testing.assert_array_equal(campaign.pulses[run_id].decel, alone[1])


@pytest.mark.parametrize("case", ["nan", "blank", "text", "decreasing time", "absurd peak", "empty", "ragged"])
def test_a_bad_pulse_among_plain_ones_is_named(tmp_path, case):
    """Plain neighbours parsed together do not hide a bad file, nor change its message."""
    text, field, words = BAD_PULSES[case]
    write_folder(tmp_path, ["C0,cae,35,2000,1500,ICE,FWD,", "C1,cae,35,2000,1500,ICE,FWD,",
                            "C2,cae,35,2000,1500,ICE,FWD,"], pulses={"C1": text})
    with pytest.raises(InputError) as err:
        read_campaign(tmp_path)
    assert err.value.file.endswith(os.path.join("pulses", "C1.csv")) and err.value.field == field
    assert words in err.value.message
