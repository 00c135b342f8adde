"""LS-DYNA binout CAE runs: three real solver files, unit systems, the three sources, the errors, and a
campaign of binout CAE rows and EV5 test rows through `evaluate`."""

from __future__ import annotations

import importlib.metadata
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign
from crashfuse.io.campaign_write import write_campaign
from crashfuse.io.lsdyna import read_binout
from crashfuse.units import KMH
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve
from fakes import write_binout, write_ev5_pulse

pytest.importorskip("lasso.dyna", reason="lasso-python not installed: pip install --no-deps -r lsdyna-requirements.txt")

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "lsdyna"
VERSIONS = ["sph_R7_1_2", "sph_R9_3_1", "sph_R12_2_1"]
real = pytest.mark.skipif(not REAL.is_dir(), reason="shared LS-DYNA data not present")
MASS = 1500.0  # kg


def test_the_installed_reader_is_the_pinned_one():
    pins = dict(line.split("==") for line in (Path(__file__).parents[1] / "lsdyna-requirements.txt").read_text()
                .splitlines() if "==" in line and not line.startswith("#"))
    assert {name: importlib.metadata.version(name) for name in pins} == pins


@real
@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("source", ["rwforc", "rwforc:1", "matsum:101"])
def test_real_binouts_are_refused_as_too_coarse_naming_the_rates(version, source):
    with pytest.raises(InputError, match=r"written every 0\.[34]\d* ms \(2\.[56]\d* kHz over 88 samples\): too coarse "
                                         r"for a crash pulse, which needs at least 10 kHz") as err:
        read_binout(REAL / version / "binout", source, "m-s-kg", MASS / 2, MASS / 2)
    assert err.value.field == "lsdyna_source" and err.value.file.endswith("binout")


@real
@pytest.mark.parametrize("version", VERSIONS)
def test_real_binouts_name_what_is_missing(version):
    path = REAL / version / "binout"
    with pytest.raises(InputError, match=r"no nodout database \(it holds glstat, matsum, rcforc, rwforc\)"):
        read_binout(path, "nodout:1", "m-s-kg", MASS / 2, MASS / 2)
    with pytest.raises(InputError, match=r"part 7 is not in matsum \(ids 1, 101\)"):
        read_binout(path, "matsum:7", "m-s-kg", MASS / 2, MASS / 2)
    with pytest.raises(InputError, match="wall 2 is not in rwforc"):
        read_binout(path, "rwforc:2", "m-s-kg", MASS / 2, MASS / 2)
    with pytest.raises(InputError, match=r"covers 0\.0348 ms in mm-ms-kg units.*wrong unit system") as err:
        read_binout(path, "rwforc", "mm-ms-kg", MASS / 2, MASS / 2)  # the model is in seconds
    assert err.value.field == "lsdyna_units"


@pytest.mark.parametrize("units, source", [
    ("in-s-lbf", "rwforc"), ("mm-ms", "rwforc"), ("mm-ms-kg", "nodout"), ("mm-ms-kg", "matsum"), ("mm-ms-kg", "glstat"),
    ("mm-ms-kg", "nodout:1:jerk")])
def test_bad_units_and_sources_are_refused_before_reading(tmp_path, units, source):
    with pytest.raises(InputError, match="expected") as err:
        read_binout(tmp_path / "binout", source, units, MASS / 2, MASS / 2)
    assert err.value.field == ("lsdyna_units" if units != "mm-ms-kg" else "lsdyna_source")


# lasso's Lsda.__del__ trips over the half-built reader it leaves behind; the error we raise is what counts.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_file_that_is_not_lsda_is_refused(tmp_path):
    (tmp_path / "binout").write_bytes(b"not an LSDA file at all" * 10)
    with pytest.raises(InputError, match="cannot read as an LS-DYNA binout"):
        read_binout(tmp_path / "binout", "rwforc", "mm-ms-kg", MASS / 2, MASS / 2)


def _crash(time: np.ndarray, v0: float) -> np.ndarray:
    """A raw pulse (m/s^2) from contact at t = 0: a loading half-sine and a shorter unloading lobe."""
    t = np.clip(time, 0, None)
    load = np.where(t < 0.06, np.sin(np.pi * t / 0.06), 0.0)
    peak = 1.3 * v0 / (2 * 0.06 / np.pi)  # Delta-v 1.3 v0: some rebound
    return np.where(time >= 0, peak * load, 0.0)


def _native_times(lead_s: float, end_s: float, seed: int) -> np.ndarray:
    """LS-DYNA output times: every 0.1 ms, each at the first solver step past it (a few microseconds late)."""
    nominal = np.arange(0.0, lead_s + end_s, 1e-4)
    return nominal + np.random.default_rng(seed).uniform(0, 3e-6, nominal.size) - lead_s


UNITS = {"mm-ms-kg": (1e-3, 1e-3, 1.0), "mm-s-t": (1e-3, 1.0, 1e3), "m-s-kg": (1.0, 1.0, 1.0)}


def _binout_of(path: Path, decel_of, v0: float, source: str, units: str, direction: float = -1.0, seed: int = 0,
               mass: float = MASS):
    """A binout recording the run of ``mass`` (kg) with deceleration ``decel_of(t)`` (SI) in ``units``, travelling
    along X * direction."""
    length, time_unit, mass_unit = UNITS[units]
    t = _native_times(0.004, 0.12, seed)
    decel = decel_of(t)
    velocity = direction * (v0 - np.concatenate([[0.0], np.cumsum(0.5 * (decel[1:] + decel[:-1]) * np.diff(t))]))
    speed = velocity / (length / time_unit)
    accel = -direction * decel / (length / time_unit**2)
    force = decel * mass / (mass_unit * length / time_unit**2)
    db = {"rwforc": {"rwforc/forces": ([1], {"normal_force": force}), "glstat": (None, {"global_x_velocity": speed})},
          "matsum": {"matsum": ([1, 2], {"x_rbvelocity": np.c_[np.zeros_like(speed), speed]})},
          "nodout": {"nodout": ([7, 81234], {"x_acceleration": np.c_[np.zeros_like(accel), accel],
                                             "x_velocity": np.c_[np.zeros_like(speed), speed]})}}
    return write_binout(path, t / time_unit, db[source.split(":")[0]])


@pytest.mark.parametrize("units", list(UNITS))
@pytest.mark.parametrize("source, direction", [("rwforc", -1.0), ("matsum:2", 1.0), ("nodout:81234", -1.0),
                                               ("nodout:81234:velocity", 1.0)])
def test_every_source_and_unit_system_gives_the_same_pulse_as_the_raw_csv(tmp_path, units, source, direction):
    v0 = 15.6
    binout = _binout_of(tmp_path / "run" / "binout", lambda t: _crash(t, v0), v0, source, units, direction)
    grid = np.arange(-40, 1200) * 1e-4  # with pre-contact lead-in for the filter, as the binout has
    pd.DataFrame({"time_s": grid, "decel_mps2": _crash(grid, v0)}).to_csv(tmp_path / "C1.csv", index=False)
    conditions = pd.DataFrame({"run_id": ["C1", "C2"], "source": "cae", "v0_mps": v0, "front_weight_kg": MASS / 2,
                               "rear_weight_kg": MASS / 2, "powertrain": "ICE", "drive": "FWD",
                               "pulse_path": ["", "run"], "lsdyna_source": ["", source], "lsdyna_units": ["", units],
                               "cfc": ["raw", ""]})
    (tmp_path / "pulses").mkdir()
    (tmp_path / "C1.csv").rename(tmp_path / "pulses" / "C1.csv")
    conditions.to_csv(tmp_path / "conditions.csv", index=False)
    campaign = read_campaign(tmp_path)
    csv, lsdyna = campaign.pulses["C1"], campaign.pulses["C2"]
    assert lsdyna.meta["lsdyna"]["units"] == units and lsdyna.dt == pytest.approx(1e-4)
    assert "warnings" not in lsdyna.meta  # its initial velocity is the row's speed
    n = min(csv.time.size, lsdyna.time.size) - 20  # the filters' end effects differ
    np.testing.assert_allclose(lsdyna.time[:n], csv.time[:n], atol=1e-9)
    # float32 histories, output jitter and the 0.1 ms averaging: within 0.5 % of the peak
    np.testing.assert_allclose(lsdyna.decel[:n], csv.decel[:n], atol=5e-3 * csv.decel.max())


def test_a_node_not_in_nodout_and_several_walls_are_named(tmp_path):
    binout = _binout_of(tmp_path / "binout", lambda t: _crash(t, 15.0), 15.0, "nodout", "mm-ms-kg")
    with pytest.raises(InputError, match=r"node 99 is not in nodout \(ids 7, 81234\)") as err:
        read_binout(binout, "nodout:99", "mm-ms-kg", MASS / 2, MASS / 2)
    assert err.value.field == "lsdyna_source"
    t = np.arange(0, 50, 0.1)
    forces = {"rwforc/forces": ([1, 2], {"normal_force": np.ones((t.size, 2))})}
    walls = write_binout(tmp_path / "walls" / "binout", t, forces)
    with pytest.raises(InputError, match=r"2 rigid walls \(ids 1, 2\); name one as rwforc:<wall id>"):
        read_binout(walls, "rwforc", "mm-ms-kg", MASS / 2, MASS / 2)


def test_pulse_metrics_reads_a_binout(tmp_path, capsys):
    binout = _binout_of(tmp_path / "binout", lambda t: _crash(t, 15.6), 15.6, "rwforc", "mm-ms-kg")
    assert main(["pulse-metrics", str(binout), "--lsdyna-source", "rwforc", "--lsdyna-units", "mm-ms-kg",
                 "--mass-kg", str(MASS), "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["restitution"] == pytest.approx(0.3, abs=0.02)
    assert main(["pulse-metrics", str(binout), "--lsdyna-source", "rwforc", "--mass-kg", str(MASS)]) == 2
    assert "--lsdyna-units" in capsys.readouterr().err


def test_lsdyna_columns_belong_to_binout_rows(tmp_path):
    conditions = pd.DataFrame({"run_id": ["C1"], "source": "cae", "v0_mps": 15.0, "front_weight_kg": 700,
                               "rear_weight_kg": 700, "powertrain": "ICE", "drive": "FWD", "lsdyna_units": "mm-ms-kg"})
    conditions.to_csv(tmp_path / "conditions.csv", index=False)
    with pytest.raises(InputError, match="only on rows whose pulse_path names an LS-DYNA binout") as err:
        read_campaign(tmp_path)
    assert err.value.field == "lsdyna_units"
    _binout_of(tmp_path / "run" / "binout", lambda t: _crash(t, 15.0), 15.0, "rwforc", "mm-ms-kg")
    conditions.assign(pulse_path="run", lsdyna_units="").to_csv(tmp_path / "conditions.csv", index=False)
    with pytest.raises(InputError, match="expected lsdyna_source on a row whose pulse_path names an LS-DYNA binout"):
        read_campaign(tmp_path)


def _binout_campaign(folder: Path) -> tuple[Path, Path]:
    """The same small world campaign twice: as raw CSVs, and as binout CAE rows (three sources) + EV5 test rows."""
    full = build(resolve("paper"), seed=0, n_cae=16)[0]
    keep = ["T02", "T05", "T08"]
    companions = [full.companion(t).run_id for t in keep]
    campaign = full.subset(keep + companions + [r for r in full.cae if r.startswith("C0")])
    plain = write_campaign(campaign, folder / "csv")
    rows = pd.read_csv(plain / "conditions.csv", keep_default_na=False)
    # Both read as raw records, so that both are filtered to CFC 60 once more on reading.
    rows.assign(cfc="raw").to_csv(plain / "conditions.csv", index=False)
    sources = ["rwforc", "matsum:2", "nodout:81234"]
    paths, lsdyna = [], []
    for i, row in rows.iterrows():
        pulse = campaign.pulses[row["run_id"]]
        if row["source"] == "test":
            number = 9000 + i
            write_ev5_pulse(folder / "mixed" / "ev5" / f"v{number}", number, pulse.time, pulse.decel, pulse.v0 / KMH,
                            pulse.mass, pulse.rear_weight / pulse.mass)
            paths.append(f"ev5/v{number}")
            lsdyna.append(("", ""))
            continue
        source = sources[i % 3]
        decel_of = lambda t, p=pulse: np.where(t >= 0, np.interp(t, p.time, p.decel), 0.0)  # noqa: E731
        _binout_of(folder / "mixed" / "cae" / row["run_id"] / "binout", decel_of, pulse.v0, source, "mm-ms-kg", seed=i,
                   mass=pulse.mass)
        paths.append(f"cae/{row['run_id']}")
        lsdyna.append((source, "mm-ms-kg"))
    rows["pulse_path"] = paths
    rows["lsdyna_source"], rows["lsdyna_units"] = zip(*lsdyna)
    rows = rows.drop(columns="cfc", errors="ignore")
    rows.to_csv(folder / "mixed" / "conditions.csv", index=False)
    return plain, folder / "mixed"


@pytest.mark.slow
def test_a_campaign_of_binout_cae_and_ev5_tests_runs_through_evaluate(tmp_path):
    plain, mixed = _binout_campaign(tmp_path)
    campaign = read_campaign(mixed)
    assert {p.meta["lsdyna"]["database"] for p in campaign.pulses.values() if p.source == "cae"} == {
        "rwforc", "matsum", "nodout"}
    assert all(p.meta.get("test_number") for p in campaign.pulses.values() if p.source == "test")
    tables = {}
    for name, folder in (("csv", plain), ("mixed", mixed)):
        out = tmp_path / f"eval-{name}"
        assert main(["evaluate", str(folder), "--k", "1", "--inputs", "paper", "--holdout", "T08", "--samples", "20",
                     "--jobs", "1", "--n-grid", "40", "--out", str(out)]) == 0
        tables[name] = pd.read_csv(out / "iso_table.csv").set_index(["model", "window_ms"])["overall"]
    # The same runs read from LS-DYNA and EV5 files (12.5 kHz resampled to 10 kHz, float32, EV5's 6 decimals):
    # the same scores within 0.02 (measured: 0.012 at most).
    assert set(tables["mixed"].index.get_level_values("model")) == {"CAE", "K1"}
    np.testing.assert_allclose(tables["mixed"].to_numpy(), tables["csv"].to_numpy(), atol=0.02)
    print(pd.concat(tables, axis=1))
