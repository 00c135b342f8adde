"""The synthetic crash world: physics against closed forms, calibration against NHTSA 10146,
campaign contract, realism bars, strengths, errors, determinism and timing."""

from __future__ import annotations

import ast
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crashfuse.catalogue import EFFECTS
from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.metrics import pulse_metrics
from crashfuse.units import G0, MPH
from crashfuse.world import WORLD_VERSION
from crashfuse.world.effects import REALISTIC, parse_overrides
from crashfuse.world.generate import all_params, build, generate
from crashfuse.world.presets import TABLE1, resolve
from crashfuse.world.realism import bars, realism_table
from crashfuse.world.simulate import RAW_RATE, Runs, body_decel

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared"
NHTSA_10146 = SHARED / "data" / "nhtsa" / "v10146"
SMALL = 12  # Latin-hypercube CAE runs in the fast campaigns


def _runs(v0_mph, type2=False, awd=False, front=961.0, rear=758.0):
    n = np.size(v0_mph)
    return Runs(v0=np.atleast_1d(v0_mph) * MPH, front=np.full(n, front), rear=np.full(n, rear),
                type2=np.full(n, type2), awd=np.full(n, awd))


def _linear_spring(k):
    """Parameters making the loading branch F = k s and unloading elastic along the same line."""
    p = all_params(resolve())
    p.update({"vehicle.f_can": 0.0, "vehicle.f_rail": 0.0, "vehicle.k_rail": k, "vehicle.s_can": 0.0,
              "vehicle.s_blend": 1e-9, "vehicle.k_stack": 0.0, "vehicle.k_unload": k})
    return p


def _kinematics(a, v0, dt=1.0 / RAW_RATE):
    v = v0 - np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * dt)])
    return v, np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])


# --- physics ---------------------------------------------------------------------------------


def test_linear_spring_gives_the_closed_form_half_sine():
    """Eq. 4 with F = k s: peak v0 sqrt(k/M), stop at pi/2 sqrt(M/k), elastic unloading returns v0."""
    k, m, v0 = 1.0e6, 1719.0, 15.0
    a = body_decel(_runs(v0 / MPH), (), _linear_spring(k), t_end=0.2)[0]
    w = np.sqrt(k / m)
    t = np.arange(a.size) / RAW_RATE
    assert a.max() == pytest.approx(v0 * w, rel=2e-3)
    assert t[np.argmax(a)] == pytest.approx(np.pi / 2 / w, abs=2.0 / RAW_RATE)
    v, _ = _kinematics(a, v0)
    assert -v.min() == pytest.approx(v0, rel=5e-3)  # restitution 1 along the elastic line


def test_cae_absorbs_the_kinetic_energy_in_the_crush_spring():
    """Without damping, the work of F(s) up to the maximum crush equals 1/2 M v0^2."""
    from crashfuse.world.vehicle import loading_force, stack_onset, strength

    p = all_params(resolve())
    runs = _runs(np.array([8.1, 25.2, 35.2]), front=961.0)
    a = body_decel(runs, (), p, t_end=0.15)
    m = 961.0 + 758.0
    for i, v0 in enumerate(runs.v0):
        _, s = _kinematics(a[i], v0)
        grid = np.linspace(0, s.max(), 4001)
        f = loading_force(grid, strength(runs.front[:1], p), stack_onset(runs.type2[:1], p), p)
        assert np.trapezoid(f, grid) == pytest.approx(0.5 * m * v0 ** 2, rel=5e-3)


def test_low_speed_pulses_are_not_scaled_copies():
    """Staged crush: the peak over the mean deceleration differs between 8 and 35 mph."""
    p = all_params(resolve())
    runs = _runs(np.array([8.1, 35.2]))
    a = body_decel(runs, (), p, t_end=0.15)
    shape = []
    for i, v0 in enumerate(runs.v0):
        _, s = _kinematics(a[i], v0)
        shape.append(a[i].max() / (v0 ** 2 / (2 * s.max())))
    assert abs(shape[1] / shape[0] - 1) > 0.2


def test_strain_rate_bias_grows_with_speed():
    p = all_params(resolve())
    runs = _runs(np.array([8.1, 16.7, 35.2]))
    cae = body_decel(runs, (), p, t_end=0.03)
    test = body_decel(runs, ("strain_rate",), p, t_end=0.03)
    early = slice(int(0.005 * RAW_RATE), int(0.03 * RAW_RATE))
    ratio = test[:, early].mean(axis=1) / cae[:, early].mean(axis=1)
    assert np.all(ratio > 1.0) and np.all(np.diff(ratio) > 0)


def test_powertrain_acts_only_once_the_crush_closes_its_gap():
    """At 8 mph the crush stays short of the gap: the pulse is that of the rigid powertrain."""
    p = all_params(resolve())
    runs = _runs(np.array([8.1, 35.2]))
    rigid = body_decel(runs, (), p, t_end=0.12)
    separate = body_decel(runs, ("powertrain",), p, t_end=0.12)
    _, s = _kinematics(rigid[0], runs.v0[0])
    assert s.max() < p["powertrain.gap_type1"]
    # short of the gap only the soft mounts act: within 10 % of the peak at 8 mph; at 35 mph the
    # powertrain strikes the barrier and the body feels a secondary pulse of several g
    assert np.abs(separate[0] - rigid[0]).max() < 0.1 * rigid[0].max()
    assert np.abs(separate[1] - rigid[1]).max() > 5 * G0


def test_unloading_restitution_is_larger_at_low_speed():
    """The test side (unloading with every other effect): restitution 0.1-0.2 at 35 mph, larger at 8 mph."""
    p = all_params(resolve())
    runs = _runs(np.array([8.1, 35.2]))
    a = body_decel(runs, EFFECTS, p, t_end=0.25)
    e = [-_kinematics(a[i], v0)[0].min() / v0 for i, v0 in enumerate(runs.v0)]
    assert 0.10 <= e[1] <= 0.20
    assert e[0] > e[1]


def test_effective_mass_lengthens_the_crush():
    p = all_params(resolve())
    runs = _runs(np.array([25.0]))
    crush = [_kinematics(body_decel(runs, eff, p, t_end=0.15)[0], runs.v0[0])[1].max() for eff in ((), ("mass",))]
    assert crush[1] > crush[0]


# --- calibration -----------------------------------------------------------------------------


@pytest.mark.skipif(not NHTSA_10146.is_dir(), reason="shared NHTSA data absent")
def test_calibrated_simulator_reproduces_nhtsa_10146_within_10_percent():
    from crashfuse.io.nhtsa import read_nhtsa
    from crashfuse.world.calibrate import comparison, default_params

    table = comparison(read_nhtsa(NHTSA_10146), default_params())
    print("\n" + table.to_string(index=False))
    assert table["within_10pct"].all(), table


# --- campaigns -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    folder = tmp_path_factory.mktemp("paper") / "campaign"
    return generate(folder, resolve(), seed=3, n_cae=SMALL)


def test_paper_campaign_carries_table1_exactly(paper):
    raw = pd.read_csv(paper / "conditions.csv", dtype=str)
    tests = raw[raw["source"] == "test"]
    assert tests["run_id"].tolist() == [f"T{i:02d}" for i in range(1, 12)]
    assert tests["cae_run_id"].tolist() == [f"CT{i:02d}" for i in range(1, 12)]
    expected = TABLE1.astype(str)
    assert [float(x) for x in tests["v0_mph"]] == TABLE1["speed_mph"].tolist()
    assert [float(x) for x in tests["front_weight_lb"]] == TABLE1["front_lb"].tolist()
    assert [float(x) for x in tests["rear_weight_lb"]] == TABLE1["rear_lb"].tolist()
    assert tests["powertrain"].tolist() == expected["powertrain"].tolist()
    assert tests["drive"].tolist() == expected["drive"].tolist()


def test_paper_campaign_reads_back_as_cfc60_pulses(paper):
    campaign = read_campaign(paper)
    assert len(campaign.tests) == 11 and len(campaign.cae) == 11 + SMALL
    for tid in campaign.tests:
        test, cae = campaign.pulses[tid], campaign.companion(tid)
        assert (test.v0, test.front_weight, test.rear_weight) == pytest.approx((cae.v0, cae.front_weight,
                                                                                  cae.rear_weight))
    p = campaign.pulses["T08"]
    assert p.time.size == 1251 and p.dt == pytest.approx(1 / 12500) and p.time[-1] == pytest.approx(0.1)
    speeds = campaign.conditions.loc[campaign.conditions["source"] == "cae", "v0_mps"] / MPH
    assert speeds.between(5.0, 40.0).all()


def test_world_json_is_the_answer_key(paper):
    world = json.loads((paper / "world.json").read_text())
    assert world["world_version"] == WORLD_VERSION and world["seed"] == 3
    assert world["withheld"] == ["strain_rate", "powertrain"]
    assert set(world["effects"]["test"]) == set(EFFECTS)
    assert set(world["effects"]["cae"]) == {"damping", "unloading", "mass"}
    listed = {f"{e}.{k}": v for e, ps in world["effects"]["test"].items() for k, v in ps.items()}
    assert listed == REALISTIC


def test_campaign_takes_its_final_name_with_world_json_or_not_at_all(tmp_path, monkeypatch):
    from crashfuse.io import campaign_write
    from crashfuse.world import generate as gmod

    seen, swap = [], campaign_write._swap_in
    monkeypatch.setattr(campaign_write, "_swap_in", lambda tmp, folder: (seen.append(sorted(os.listdir(tmp))),
                                                                         swap(tmp, folder)))
    generate(tmp_path / "ok", resolve(), seed=3, n_cae=2)
    assert seen == [["conditions.csv", "pulses", "world.json"]]
    campaign, _ = build(resolve(), seed=3, n_cae=2)
    monkeypatch.setattr(gmod, "build", lambda *args: (campaign, {"bad": float("nan")}))  # not JSON
    with pytest.raises(ValueError):
        generate(tmp_path / "bad", resolve(), seed=3, n_cae=2)
    assert sorted(os.listdir(tmp_path)) == ["ok"]


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path, paper):
    again = generate(tmp_path / "again", resolve(), seed=3, n_cae=SMALL)
    other = generate(tmp_path / "other", resolve(), seed=4, n_cae=SMALL)
    files = sorted(p.relative_to(paper) for p in paper.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert all((paper / f).read_bytes() == (again / f).read_bytes() for f in files)
    assert (paper / "pulses" / "T01.csv").read_bytes() != (other / "pulses" / "T01.csv").read_bytes()
    assert (paper / "conditions.csv").read_bytes() != (other / "conditions.csv").read_bytes()


def test_withheld_presets_differ_only_in_what_they_withhold():
    for name in EFFECTS:
        design = resolve(withhold=name)
        assert design.withheld == (name,) and set(design.cae_effects) == set(EFFECTS) - {name}
    control = resolve(withhold="none")
    assert control.withheld == () and control.cae_effects == control.test_effects
    # without a withheld effect the companions differ only by measurement realism
    campaign, _ = build(control, seed=0, n_cae=0)
    scores = [iso_score(campaign.pulses[t].time, campaign.pulses[t].decel, campaign.companion(t).time,
                        campaign.companion(t).decel, 0.0, 0.06)["overall"] for t in campaign.tests]
    assert min(scores) > 0.85


def test_a_pair_is_withheld_together_at_its_strength(tmp_path):
    """Two effects withheld at once: the CAE carries neither, both at the subtle strength, the others
    shared and realistic (the pairs of ``world validate --pairs``)."""
    design = resolve(withhold=["damping", "mass"], strength="subtle")
    assert design.withheld == ("damping", "mass") and design.cae_effects == ("strain_rate", "powertrain", "unloading")
    assert design.params["damping.c"] == 2.5e3 and design.params["mass.extra"] == 230.0  # both subtle
    assert design.params["strain_rate.d"] == REALISTIC["strain_rate.d"]
    world = json.loads((generate(tmp_path / "c", design, seed=0, n_cae=0) / "world.json").read_text())
    assert {"damping", "mass"} <= set(world["effects"]["test"]) and not {"damping", "mass"} & set(world["effects"]["cae"])


def _mean_iso(design, end):
    campaign, _ = build(design, seed=0, n_cae=0)
    return np.mean([iso_score(campaign.pulses[t].time, campaign.pulses[t].decel, campaign.companion(t).time,
                              campaign.companion(t).decel, 0.0, end)["overall"] for t in campaign.tests])


@pytest.mark.parametrize("effect", EFFECTS)
def test_subtle_strength_lowers_mean_iso_by_003_to_008(effect):
    end = 0.1 if effect == "unloading" else 0.06  # unloading acts after 60 ms at every Table 1 speed
    control = _mean_iso(resolve(withhold="none"), end)
    drop = control - _mean_iso(resolve(withhold=effect, strength="subtle"), end)
    print(f"\n{effect}: control {control:.3f}, subtle drop {drop:.3f}")
    assert 0.03 <= drop <= 0.08


def test_effect_param_overrides_reach_world_json(tmp_path):
    folder = generate(tmp_path / "c", resolve(withhold="damping", overrides=parse_overrides(["damping.c=2000"])),
                      seed=0, n_cae=0)
    world = json.loads((folder / "world.json").read_text())
    assert world["effects"]["test"]["damping"] == {"c": 2000.0} and "damping" not in world["effects"]["cae"]


# --- realism ---------------------------------------------------------------------------------


def test_paper_preset_meets_the_realism_bars():
    campaign, _ = build(resolve(), seed=0, n_cae=0)
    table = realism_table(campaign)
    print("\n" + table.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    assert bars(table) == {"iso": True, "plausible": True, "not_scaled": True}


# --- errors, CLI, rules ----------------------------------------------------------------------


@pytest.mark.parametrize("args, field", [
    (["--withhold", "rust"], "--withhold"),
    (["--withhold", "mass", "mass"], "--withhold"),
    (["--withhold", "none", "mass"], "--withhold"),
    (["--preset", "nope"], "--preset"),
    (["--strength", "huge"], "--strength"),
    (["--effect-param", "damping.c=-5"], "--effect-param"),
    (["--effect-param", "strain_rate.q=0"], "--effect-param"),
    (["--effect-param", "damping.k=5"], "--effect-param"),
    (["--effect-param", "damping.c"], "--effect-param"),
    (["--effect-param", "powertrain.gap_awd=1"], "powertrain.gap_awd"),
    (["--preset", "withheld"], "--withhold"),
    (["--preset", "paper", "--withhold", "mass"], "--withhold"),
    (["--seed", "-1"], "--seed"),
])
def test_bad_arguments_exit_2_naming_the_field_and_write_nothing(tmp_path, capsys, args, field):
    out = tmp_path / "c"
    assert main(["world", "generate", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and field in err
    assert not out.exists()


def test_resolve_rejects_unknown_names_directly():
    with pytest.raises(InputError, match="unknown effect"):
        resolve(withhold="friction")


def _imported_modules(path: Path, package: str) -> list[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            names += [module] + [f"{module}.{a.name}" for a in node.names]
    return names


def test_import_scan_resolves_relative_imports(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("from . import world\nfrom .world import presets\nfrom ..x import y\n")
    names = _imported_modules(src, "crashfuse.sub")
    assert "crashfuse.sub.world" in names and "crashfuse.sub.world.presets" in names and "crashfuse.x.y" in names
    assert "crashfuse.world" in _imported_modules(src, "crashfuse")


def test_nothing_outside_world_and_cli_imports_the_world():
    offenders = []
    for path in (REPO / "crashfuse").rglob("*.py"):
        rel = path.relative_to(REPO / "crashfuse")
        if rel.parts[0] == "world" or rel.as_posix() == "cli.py":
            continue
        package = ".".join(("crashfuse", *rel.parent.parts))
        if any(n == "crashfuse.world" or n.startswith("crashfuse.world.") for n in _imported_modules(path, package)):
            offenders.append(rel.as_posix())
    assert not offenders


def test_full_paper_preset_cli_generates_in_well_under_a_minute(tmp_path, capsys):
    start = time.perf_counter()
    assert main(["world", "generate", "--out", str(tmp_path / "c")]) == 0
    elapsed = time.perf_counter() - start
    print(f"\nfull paper preset (11 tests, 1020 CAE runs) generated in {elapsed:.1f} s")
    assert elapsed < 30.0
    campaign = read_campaign(tmp_path / "c")
    assert len(campaign.cae) == 1020
    metrics = pulse_metrics(campaign.pulses["T09"])
    assert 30.0 < metrics["peak_decel_g"] < 50.0
