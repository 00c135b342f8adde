"""The second synthetic world (crashfuse.world.multibody): campaign contract, effect signatures,
measurement-only control, momentum, determinism, CLI errors and the calibration to NHTSA 10146."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign
from crashfuse.signals.filters import filter_pulse
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.metrics import pulse_metrics
from crashfuse.units import G0, MPH
from crashfuse.world.multibody import WORLD_NAME, WORLD_VERSION
from crashfuse.world.multibody.effects import EFFECTS, parse_overrides
from crashfuse.world.multibody.generate import all_params, build, generate
from crashfuse.world.multibody.presets import WIDE_SPEEDS_MPH, matrix_tests, resolve
from crashfuse.world.multibody.simulate import RAW_RATE, Runs, body_decel

REPO = Path(__file__).resolve().parents[1]
NHTSA_10146 = Path(__file__).resolve().parents[2] / "shared" / "data" / "nhtsa" / "v10146"
SMALL = 6  # Latin-hypercube CAE runs in the fast campaigns
PLAUSIBLE = {"peak_decel_g": (5.0, 60.0), "dynamic_crush_mm": (50.0, 900.0), "restitution": (0.05, 0.40)}


def _runs(mph, type2=False, awd=False):
    n = np.size(mph)
    return Runs(v0=np.atleast_1d(mph) * MPH, front=np.full(n, 961.0), rear=np.full(n, 758.0),
                type2=np.full(n, type2), awd=np.full(n, awd))


def _decel(mph, effects, t_end=0.12, **changes):
    return body_decel(_runs(mph), effects, {**all_params(resolve()), **changes}, t_end)


def _without(name):
    return tuple(e for e in EFFECTS if e != name)


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    folder = tmp_path_factory.mktemp("w2") / "paper"
    generate(folder, resolve(), seed=3, n_cae=SMALL)
    return folder


@pytest.fixture(scope="module")
def control():
    campaign, _ = build(resolve(withhold="none"), seed=0, n_cae=0)
    return campaign


def _iso(campaign, tid, end=0.060):
    test, cae = campaign.pulses[tid], filter_pulse(campaign.pulses["C" + tid], 60).after_contact()
    return iso_score(test.time, test.decel, cae.time, cae.decel, 0.0, end)["overall"]


# --- campaign contract -----------------------------------------------------------------------


def test_campaign_reads_back_with_raw_cae_filtered_by_the_reader(paper):
    c = read_campaign(paper)
    assert len(c.tests) == 11 and len(c.cae) == 11 + SMALL
    assert c.companion("T08").run_id == "CT08"
    text = (paper / "conditions.csv").read_text().splitlines()
    header = text[0].split(",")
    cfc = {row.split(",")[0]: row.split(",")[header.index("cfc")] for row in text[1:]}
    assert cfc["T01"] == "60" and cfc["CT01"] == "raw" and cfc["C0001"] == "raw"
    cae = c.pulses["C0001"]
    assert cae.meta["cfc"] == 60 and cae.time[0] == 0.0 and cae.time[-1] == pytest.approx(0.120)
    raw = read_campaign(paper, cfc=None).pulses["C0001"]
    assert raw.time[0] == pytest.approx(-0.010) and raw.meta.get("cfc") is None
    rough = [np.abs(np.diff(p.decel[p.time >= 0], 2)).mean() for p in (raw, cae)]
    assert rough[0] > 2 * rough[1]  # the reader filtered the raw history output
    key = __import__("json").loads((paper / "world.json").read_text())
    assert (key["world"], key["world_version"], key["withheld"]) == (WORLD_NAME, WORLD_VERSION,
                                                                    ["strain_rate", "powertrain"])
    assert set(key["effects"]["cae"]) == {"damping", "unloading", "mass"}


def test_tests_are_physically_plausible(paper):
    c = read_campaign(paper)
    for tid in c.tests:
        m = pulse_metrics(c.pulses[tid])
        for name, (lo, hi) in PLAUSIBLE.items():
            assert lo <= m[name] <= hi, (tid, name, m[name])


def test_momentum_measured_velocity_change_matches_the_body(paper):
    """The lab chain keeps the velocity change: delivered pulse vs the noise-free body, within 2 % of v0."""
    c = read_campaign(paper)
    params = all_params(resolve())
    frame = matrix_tests("table1")
    runs = Runs(v0=frame["v0_mps"].to_numpy(), front=frame["front_weight_kg"].to_numpy(),
                rear=frame["rear_weight_kg"].to_numpy(), type2=(frame["powertrain"] == "Type II").to_numpy(),
                awd=(frame["drive"] == "AWD").to_numpy())
    body = body_decel(runs, EFFECTS, params, 0.100)
    for i, tid in enumerate(c.tests):
        test = c.pulses[tid]
        dv_test = np.trapezoid(test.decel, test.time)
        dv_body = np.trapezoid(body[i], dx=1.0 / RAW_RATE)
        assert dv_test == pytest.approx(dv_body, abs=0.02 * test.v0)
        m = pulse_metrics(test)
        if m["t_zero_velocity_ms"] is not None and m["t_zero_velocity_ms"] < 90:
            # velocity change = v0 + rebound, the rebound a fraction of v0 (restitution < 1)
            assert test.v0 < dv_test < 1.5 * test.v0


def test_control_differs_from_cae_only_by_measurement(control):
    isos = np.array([_iso(control, t) for t in control.tests])
    assert isos.min() > 0.85 and isos.mean() > 0.90
    paper, _ = build(resolve(), seed=0, n_cae=0)
    assert np.mean([_iso(paper, t) for t in paper.tests]) < isos.mean() - 0.05


# --- effect signatures -----------------------------------------------------------------------


def test_powertrain_contact_only_above_the_gap_closing_speed():
    mph = np.array([8.1, 16.7, 25.2, 35.2])
    with_pt, without = _decel(mph, EFFECTS), _decel(mph, _without("powertrain"))
    assert np.array_equal(with_pt[:3], without[:3])  # slow tests never close the gap
    diff = np.abs(with_pt[3] - without[3])
    first = np.argmax(diff > 0) / RAW_RATE
    assert 0.03 < first < 0.07  # engine reaches the barrier well into the crash
    assert diff.max() > 5 * G0  # a secondary pulse


def test_strain_rate_grows_with_speed():
    mph = np.array([10.0, 20.0, 35.0])
    on, off = _decel(mph, EFFECTS, t_end=0.02), _decel(mph, _without("strain_rate"), t_end=0.02)
    gain = (on[:, -100:].mean(axis=1) / off[:, -100:].mean(axis=1)) - 1.0
    assert 0 < gain[0] < gain[1] < gain[2]


def test_damping_is_quadratic_in_crush_speed():
    mph = np.array([10.0, 30.0])
    on, off = _decel(mph, EFFECTS, t_end=0.004), _decel(mph, _without("damping"), t_end=0.004)
    added = (on - off)[:, -1]
    assert added[1] / added[0] > 6  # ~ (30/10)^2 = 9; linear damping would give 3


def test_unloading_changes_nothing_before_maximum_crush_and_adds_rebound():
    on, off = _decel(12.0, EFFECTS, t_end=0.15)[0], _decel(12.0, _without("unloading"), t_end=0.15)[0]
    first = np.argmax(on != off) / RAW_RATE
    assert first > 0.035  # the crash of a 12 mph test is past its maximum crush by then
    v_on = 12.0 * MPH - np.cumsum(on) / RAW_RATE
    v_off = 12.0 * MPH - np.cumsum(off) / RAW_RATE
    assert -v_on.min() > -v_off.min() + 0.3  # m/s more rebound


def test_attached_mass_moves_on_its_link_and_deepens_the_crush():
    on, off = _decel(25.0, EFFECTS)[0], _decel(25.0, _without("mass"))[0]
    assert np.array_equal(on[:2], off[:2])  # the link is unstretched at contact
    s_on = np.cumsum(25 * MPH - np.cumsum(on) / RAW_RATE) / RAW_RATE
    s_off = np.cumsum(25 * MPH - np.cumsum(off) / RAW_RATE) / RAW_RATE
    assert s_on.max() > s_off.max() + 0.01


def test_withheld_pairs_and_subtle_strengths():
    d = resolve(withhold=["damping", "mass"], strength="subtle")
    assert d.withheld == ("damping", "mass") and d.cae_effects == ("strain_rate", "powertrain", "unloading")
    assert d.params["damping.c2"] < resolve(withhold="damping").params["damping.c2"]
    assert d.params["strain_rate.a"] == resolve().params["strain_rate.a"]  # shared effects stay realistic


def test_wide_matrix_spans_10_to_37_mph_and_slow_tests_rebound_in_the_window():
    frame = matrix_tests("wide")
    assert len(frame) == 11 and frame["v0_mps"].min() == pytest.approx(10 * MPH)
    assert frame["v0_mps"].max() == pytest.approx(37 * MPH)
    campaign, key = build(resolve(withhold="none"), seed=1, n_cae=0, matrix="wide")
    assert key["matrix"] == "wide" and len(campaign.tests) == len(WIDE_SPEEDS_MPH)
    t_stop = [pulse_metrics(campaign.pulses[t])["t_zero_velocity_ms"] for t in campaign.tests[:3]]
    assert max(t_stop) < 60.0


@pytest.mark.parametrize("n_cae", [150, 1000])
def test_cae_design_sizes(n_cae):
    campaign, key = build(resolve(withhold="none"), seed=0, n_cae=n_cae)
    assert len(campaign.cae) == 11 + n_cae and key["runs"]["cae"] == 11 + n_cae


# --- determinism, errors, layering --------------------------------------------------------------


def test_same_seed_same_bytes_other_seed_other_noise(tmp_path):
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        generate(tmp_path / name, resolve(withhold=["mass", "unloading"]), seed=seed, n_cae=3)
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)
    assert (tmp_path / "a/pulses/T01.csv").read_bytes() != (tmp_path / "c/pulses/T01.csv").read_bytes()


@pytest.mark.parametrize("argv, field", [
    (["--withhold", "damping", "damping"], "--withhold"),
    (["--withhold", "none", "mass"], "--withhold"),
    (["--withhold", "friction"], "--withhold"),
    (["--preset", "paper", "--withhold", "mass"], "--withhold"),
    (["--matrix", "tall"], "arguments"),
    (["--strength", "huge"], "--strength"),
    (["--effect-param", "mass.k=0"], "--effect-param"),
    (["--effect-param", "damping.c=3"], "--effect-param"),
    (["--seed", "-1"], "arguments"),
])
def test_bad_arguments_exit_2_naming_the_argument_and_write_nothing(tmp_path, capsys, argv, field):
    out = tmp_path / "never"
    assert main(["world", "generate", "--world", "multibody", "--out", str(out), "--n-cae", "2", *argv]) == 2
    err = capsys.readouterr().err
    assert field in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_first_world_refuses_multibody_only_options(tmp_path, capsys):
    assert main(["world", "generate", "--out", str(tmp_path / "x"), "--matrix", "wide"]) == 2
    assert "--matrix" in capsys.readouterr().err


def test_parse_overrides():
    assert parse_overrides(["damping.c2=300"]) == {"damping.c2": 300.0}
    with pytest.raises(InputError):
        parse_overrides(["strain_rate.p=-1"])


def test_does_not_import_the_first_worlds_physics_or_the_effect_laws():
    banned = {"crashfuse.world.vehicle", "crashfuse.world.simulate", "crashfuse.world.effects",
              "crashfuse.method.laws", "crashfuse.diagnosis"}
    for path in (REPO / "crashfuse/world/multibody").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                assert node.module not in banned, (path.name, node.module)


# --- calibration -------------------------------------------------------------------------------


@pytest.mark.skipif(not NHTSA_10146.is_dir(), reason="NHTSA 10146 data not present")
def test_committed_parameters_reproduce_nhtsa_10146():
    from crashfuse.io.nhtsa import read_nhtsa
    from crashfuse.world.multibody.calibrate import comparison, default_params

    table = comparison(read_nhtsa(NHTSA_10146), default_params()).set_index("metric")
    assert table["within_bar"].all(), table
    assert table.loc["peak_decel_g", "rel_error"] == pytest.approx(0.0, abs=0.10)
