"""Bad input through the command line: exit code 2, one stderr line naming file and field, no output."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from crashfuse.cli import main

SHARED = Path(__file__).resolve().parents[2] / "shared"
NHTSA = SHARED / "data" / "nhtsa" / "v10146"
CRASHFUSE = Path(sys.executable).with_name("crashfuse")
G_N = 9.80665
HEADER = "run_id,source,v0_mph,front_weight_lb,rear_weight_lb,powertrain,drive"


def half_sine_g(n=1000, dt=1e-4, duration=0.06, dv=18.8):
    """Times in s and a half-sine pulse in g with velocity change ``dv`` m/s (fits 35 mph)."""
    t = np.arange(n) * dt
    return t, np.where(t <= duration, dv * np.pi / (2 * duration) * np.sin(np.pi * t / duration), 0.0) / G_N


def pulse_text(t, a, header="time_s,decel_g"):
    return header + "\n" + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in zip(t, a))


T, A = half_sine_g()
GOOD = pulse_text(T, A)
# Pulse files that break one rule each: (text, field named in the message, words in the message).
BAD_PULSES = {
    "missing column": ("time_s,accel\n0,1\n", "decel", "missing required column"),
    "nan": (pulse_text(T, np.r_[A[:9], np.nan, A[10:]]), "decel_g", "data row 10"),
    "decreasing time": (pulse_text(T[::-1], A), "time_s", "strictly increasing"),
    "non-uniform time": (pulse_text(np.r_[T[:500], 0.0501 + 2 * T[:500]], A), "time_s", "uniform"),
    "wrong units": (pulse_text(T, A * 90), "decel_g", "wrong units"),
    "empty": ("time_s,decel_g\n", "time_s", "at least 16"),
    "one sample": ("time_s,decel_g\n0,1.5\n", "time_s", "got 1"),
    "unknown unit suffix": (pulse_text(T, A, "time_s,decel_fps2"), "decel_fps2", "unknown unit suffix"),
}


def snapshot(folder: Path) -> dict:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def run_cli(capsys, args, folder: Path, words: str, file_part: str, field: str | None):
    """Run the CLI, check exit 2, one stderr line naming file and field, no stdout, nothing written."""
    before = snapshot(folder)
    assert main([str(a) for a in args]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1, err
    assert lines[0].startswith("crashfuse: error: ") and "Traceback" not in err
    assert file_part in lines[0] and words in lines[0]
    if field is not None:
        assert f"field '{field}'" in lines[0]
    assert snapshot(folder) == before
    return lines[0]


def campaign(root: Path, pulse: str, conditions: str | None = None) -> Path:
    (root / "pulses").mkdir(parents=True)
    (root / "conditions.csv").write_text(conditions or f"{HEADER}\nC1,cae,35,2000,1500,ICE,FWD\n")
    (root / "pulses" / "C1.csv").write_text(pulse)
    return root


# --- pulse-metrics ----------------------------------------------------------------------------------


@pytest.mark.parametrize("case", BAD_PULSES, ids=list(BAD_PULSES))
def test_pulse_metrics_bad_pulse_file(tmp_path, capsys, case):
    text, field, words = BAD_PULSES[case]
    root = campaign(tmp_path / "camp", text)
    run_cli(capsys, ["pulse-metrics", root], tmp_path, words, "C1.csv", field)


CONDITIONS = {
    "missing column": (f"{HEADER.replace(',drive', '')}\nC1,cae,35,2000,1500,ICE\n", "drive", "missing required"),
    "nan": (f"{HEADER}\nC1,cae,nan,2000,1500,ICE,FWD\n", "v0_mph", "finite number"),
    "unknown unit suffix": (f"{HEADER.replace('v0_mph', 'v0_fps')}\nC1,cae,35,2000,1500,ICE,FWD\n", "v0_fps",
                            "unknown unit suffix"),
    "two unit variants": (f"{HEADER},v0_kmh\nC1,cae,35,2000,1500,ICE,FWD,56\n", "v0_kmh", "two unit variants"),
}


@pytest.mark.parametrize("case", CONDITIONS, ids=list(CONDITIONS))
def test_pulse_metrics_bad_conditions(tmp_path, capsys, case):
    text, field, words = CONDITIONS[case]
    root = campaign(tmp_path / "camp", GOOD, text)
    run_cli(capsys, ["pulse-metrics", root], tmp_path, words, "conditions.csv", field)


def test_pulse_metrics_missing_folder_and_pulse_file(tmp_path, capsys):
    run_cli(capsys, ["pulse-metrics", tmp_path / "nope"], tmp_path, "does not exist", "nope", None)
    (tmp_path / "empty").mkdir()
    run_cli(capsys, ["pulse-metrics", tmp_path / "empty"], tmp_path, "expected a campaign folder", "empty", None)
    root = campaign(tmp_path / "camp", GOOD)
    (root / "pulses" / "C1.csv").unlink()
    run_cli(capsys, ["pulse-metrics", root], tmp_path, "missing pulse file", "C1.csv", None)


def test_pulse_metrics_good_campaign_succeeds(tmp_path, capsys):
    # The same helpers produce a campaign the CLI accepts, so the failures above are the broken rule.
    root = campaign(tmp_path / "camp", GOOD)
    assert main(["pulse-metrics", str(root), "--json"]) == 0
    assert capsys.readouterr().err == ""


# --- NHTSA EV5: small broken copies ------------------------------------------------------------------


@pytest.fixture
def ev5_copy(tmp_path):
    """Header plus the two default crossmember channels of test 10146, copied into tmp_path."""
    if not NHTSA.is_dir():
        pytest.skip("shared NHTSA data absent")
    folder = tmp_path / "v10146"
    folder.mkdir()
    for name in ("v10146.EV5", "v10146.093", "v10146.094"):
        shutil.copy(NHTSA / name, folder / name)
    return folder


def test_ev5_copy_is_readable(ev5_copy, capsys):
    assert main(["pulse-metrics", str(ev5_copy)]) == 0
    capsys.readouterr()


def test_ev5_truncated_header(ev5_copy, tmp_path, capsys):
    header = ev5_copy / "v10146.EV5"
    header.write_text("".join(header.read_text().splitlines(keepends=True)[:7]))
    run_cli(capsys, ["pulse-metrics", ev5_copy], tmp_path, "INSTRUMENTATION", "v10146.EV5", None)


def test_ev5_wrong_column_count(ev5_copy, tmp_path, capsys):
    channel = ev5_copy / "v10146.093"
    channel.write_text("".join(line.rstrip("\n") + "\t0\n" for line in channel.read_text().splitlines()))
    run_cli(capsys, ["pulse-metrics", ev5_copy], tmp_path, "column", "v10146.093", None)


# --- iso-score ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("case", BAD_PULSES, ids=list(BAD_PULSES))
@pytest.mark.parametrize("position", ["test", "prediction"])
def test_iso_score_bad_pulse_file(tmp_path, capsys, case, position):
    text, field, words = BAD_PULSES[case]
    (tmp_path / "good.csv").write_text(GOOD)
    (tmp_path / "bad.csv").write_text(text)
    files = ["bad.csv", "good.csv"] if position == "test" else ["good.csv", "bad.csv"]
    run_cli(capsys, ["iso-score", *(tmp_path / f for f in files)], tmp_path, words, "bad.csv", field)


@pytest.mark.parametrize("position", ["test", "prediction"])
def test_iso_score_curve_short_of_the_window_names_its_file(tmp_path, capsys, position):
    # Valid pulse files, but one ends at 49.9 ms, before the default 0-60 ms window does.
    (tmp_path / "good.csv").write_text(GOOD)
    (tmp_path / "short.csv").write_text(pulse_text(T[:500], A[:500]))
    files = ["short.csv", "good.csv"] if position == "test" else ["good.csv", "short.csv"]
    field = "reference time" if position == "test" else "compared signal time"
    run_cli(capsys, ["iso-score", *(tmp_path / f for f in files)], tmp_path, "does not cover", "short.csv", field)


def test_iso_score_missing_file(tmp_path, capsys):
    (tmp_path / "good.csv").write_text(GOOD)
    run_cli(capsys, ["iso-score", tmp_path / "good.csv", tmp_path / "nope.csv"], tmp_path, "does not exist",
            "nope.csv", None)


def test_installed_command_exit_code_and_single_line(tmp_path):
    if not CRASHFUSE.exists():
        pytest.skip("crashfuse console script not installed in this environment")
    (tmp_path / "good.csv").write_text(GOOD)
    (tmp_path / "bad.csv").write_text(BAD_PULSES["nan"][0])
    before = snapshot(tmp_path)
    proc = subprocess.run([str(CRASHFUSE), "iso-score", "good.csv", "bad.csv"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert "bad.csv: field 'decel_g'" in proc.stderr
    assert snapshot(tmp_path) == before
