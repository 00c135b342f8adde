"""CAE surrogate: held-out ISO/TS 18571 accuracy, curves taken from runs, energy balance, bad input."""

from __future__ import annotations

import dataclasses
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from threadpoolctl import threadpool_info, threadpool_limits

from crashfuse.signals.domain import displacement_branches
from crashfuse.errors import InputError
from crashfuse.signals.filters import filter_pulse
from crashfuse.io.nhtsa import read_nhtsa
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.pulse import Pulse
from crashfuse.units import G0
from crashfuse.method import surrogate as surrogate_module
from crashfuse.method.surrogate import CAECurve, CAESurrogate
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

NHTSA = Path(__file__).resolve().parents[2] / "shared" / "data" / "nhtsa" / "v10146"


@pytest.fixture(scope="module")
def world():
    return build(resolve("paper"), seed=1, n_cae=200)[0]


@pytest.fixture(scope="module")
def fitted(world):
    return CAESurrogate(n_restarts=0, random_state=0).fit(world)


def test_held_out_cae_runs_score_iso_above_095(world):
    # A seeded 10 % of the CAE runs held out; each condition rolled out with zero bias and rated
    # against the run it has never seen, over 0-60 ms.
    held = set(np.random.default_rng(0).choice(world.cae, size=21, replace=False))
    surrogate = CAESurrogate(n_restarts=0, random_state=0).fit([world.pulses[r] for r in world.cae if r not in held])
    scores = []
    for run_id in sorted(held):
        p = world.pulses[run_id]
        c = surrogate.curve(p.v0, p.front_weight, p.rear_weight, p.meta["powertrain"], p.meta["drive"])
        traj = c.rollout(p.dt, p.time.size - 1)
        scores.append(iso_score(p.time, p.decel, traj.time, traj.decel[0], 0.0, 0.06)["overall"])
    assert np.mean(scores) >= 0.95
    assert np.min(scores) >= 0.85


def test_from_pulse_rollout_reproduces_the_cae_run(world):
    # A run that stops, rebounds and separates inside its record: the zero-bias rollout of its own
    # curve gives the pulse back through maximum crush and the spring-back.
    curves = (CAECurve.from_pulse(world.pulses[r]) for r in world.cae)
    curve = next(c for c in curves if c.unloading_origin == "run")
    run = world.pulses[curve.run_id]
    traj = curve.rollout(run.dt, run.time.size - 1)
    assert traj.s_max[0] == pytest.approx(displacement_branches(run).s_max, abs=1e-9)
    contact = traj.branch[0] < 2
    np.testing.assert_allclose(traj.decel[0, contact], run.decel[contact], atol=1e-6)
    assert iso_score(run.time, run.decel, traj.time, traj.decel[0], 0.0, 0.1)["overall"] > 0.99


@pytest.mark.skipif(not NHTSA.is_dir(), reason="shared NHTSA data absent")
def test_from_pulse_reproduces_the_real_nhtsa_test_to_separation():
    pulse = filter_pulse(read_nhtsa(NHTSA), 60).after_contact()
    curve = CAECurve.from_pulse(pulse)
    assert curve.u_end is not None and 0 < curve.u_end < curve.s_max
    traj = curve.rollout(pulse.dt, pulse.time.size - 1)
    br = displacement_branches(pulse)
    assert traj.s_max[0] == pytest.approx(br.s_max, abs=1e-9)
    # Up to separation the rollout revisits the test's own samples; after it the decel is 0.
    t_sep = traj.time[np.argmax(traj.branch[0] == 2)]
    assert t_sep > br.t_stop
    before = traj.time < t_sep
    np.testing.assert_allclose(traj.decel[0, before], pulse.decel[before], atol=1e-6)
    assert np.all(traj.decel[0, ~before] == 0.0)


def test_loading_beyond_the_data_continues_with_the_last_stiffness(world):
    curve = CAECurve.from_pulse(world.pulses["CT08"])
    end = curve.s[-1]
    assert not curve.extrapolated(end) and curve.extrapolated(end + 1e-3)
    tail = curve.s >= 0.95 * end
    slope = np.polyfit(curve.s[tail], curve.a_loading[tail], 1)[0]
    assert curve.loading(end + 0.01) == pytest.approx(curve.a_loading[-1] + 0.01 * slope)
    assert curve.unloading(curve.u_end + 1e-3) == 0.0


def test_a_run_that_never_stops_has_no_unloading_unless_given_one(world, fitted):
    run = next(world.pulses[r] for r in world.cae if not displacement_branches(world.pulses[r]).stopped)
    alone = CAECurve.from_pulse(run)
    with pytest.raises(InputError, match="never reaches zero velocity"):
        alone.unloading(0.01)
    # Its maximum crush lies beyond the record: the energy balance on the continued curve.
    assert alone.s_max > alone.s[-1] and alone.extrapolated(alone.s_max)
    stand_in = fitted.curve(run.v0, run.front_weight, run.rear_weight, run.meta["powertrain"], run.meta["drive"])
    mixed = CAECurve.from_pulse(run, unloading_from=stand_in)
    np.testing.assert_array_equal(mixed.unloading(stand_in.u), stand_in.unloading(stand_in.u))
    np.testing.assert_array_equal(mixed.a_loading, alone.a_loading)


def test_a_run_cut_before_separation_is_continued_or_stood_in_for(world, fitted):
    run = world.pulses["CT03"]  # stops about 5 ms before the record ends, still in contact
    br = displacement_branches(run)
    assert br.stopped and br.unloading.decel[-1] > 0.5 * br.unloading.decel[0]
    own = CAECurve.from_pulse(run)
    assert own.unloading_origin == "continued"
    assert own.u_end > br.unloading.x[-1] and own.unloading(own.u_end) == 0.0
    np.testing.assert_allclose(own.unloading(br.unloading.x), br.unloading.decel)
    stand_in = fitted.curve(run.v0, run.front_weight, run.rear_weight, run.meta["powertrain"], run.meta["drive"])
    joined = CAECurve.from_pulse(run, unloading_from=stand_in)
    assert CAECurve.from_pulse(world.pulses["CT08"], unloading_from=stand_in).unloading_origin == "run"
    # With a stand-in: the run's own spring-back as far as the record goes, the stand-in's shape beyond,
    # joined without a step, to the stand-in's separation.
    assert joined.unloading_origin == "joined" and joined.u_end == stand_in.u_end
    np.testing.assert_allclose(joined.unloading(br.unloading.x), br.unloading.decel)
    u_join = br.unloading.x[-1]
    step = joined.unloading(u_join + 1e-4) - joined.unloading(u_join)
    assert abs(step) < 0.02 * br.unloading.decel[-1] < abs(stand_in.unloading(u_join) - br.unloading.decel[-1])
    # A stand-in that separates before the record's spring-back ends does not replace the run's own: the run
    # is continued as without one (decisions.md, section 85; section 70 took the stand-in whole).
    short = stand_in.u < 0.5 * u_join
    early = dataclasses.replace(stand_in, u=stand_in.u[short], u_end=float(stand_in.u[short][-1]),
                                a_unloading=np.append(stand_in.a_unloading[short][:-1], 0.0))
    kept = CAECurve.from_pulse(run, unloading_from=early)
    assert kept.unloading_origin == "continued" and kept.u_end == own.u_end
    np.testing.assert_array_equal(kept.unloading(own.u), own.unloading(own.u))


def test_a_spring_back_that_pushes_harder_as_its_record_ends_is_continued_with_its_mean_slope():
    # The second world's engine on its mounts: a run's unloading falls to 1 g, then rises to 1.5 g by the record's
    # end. Its last slope cannot say where it ends; its mean slope from maximum crush can (decisions.md, section 85).
    u = np.linspace(0.0, 0.06, 61)
    a = G0 * np.where(u < 0.01, 30.0 - 2900.0 * u, 1.0 + 10.0 * (u - 0.01))
    cont_u, cont_a, origin = surrogate_module._continued_unloading(u, a)
    assert origin == "continued" and cont_a[-1] == 0.0
    assert cont_u[-1] == pytest.approx(u[-1] + a[-1] * (u[-1] - u[0]) / (a[0] - a[-1]))
    assert surrogate_module._continued_unloading(u, G0 * (1.0 + u)) is None  # a branch that never falls: no end to read


def test_surrogate_s_max_is_where_its_rollout_stops(world, fitted):
    for test_id in ("T01", "T06", "T09"):
        p = world.pulses[test_id]
        curve = fitted.curve(p.v0, p.front_weight, p.rear_weight, p.meta["powertrain"], p.meta["drive"])
        traj = curve.rollout(p.dt, p.time.size - 1)
        assert traj.s_max[0] == pytest.approx(curve.s_max, abs=2e-3)


def test_surrogate_matches_the_companions_at_the_test_conditions(world, fitted):
    # The companions CT01..CT11 are in the fit, so this checks fidelity at training points.
    scores = []
    for test_id in world.tests:
        p, cae = world.pulses[test_id], world.companion(test_id)
        curve = fitted.curve(p.v0, p.front_weight, p.rear_weight, p.meta["powertrain"], p.meta["drive"])
        traj = curve.rollout(cae.dt, cae.time.size - 1)
        scores.append(iso_score(cae.time, cae.decel, traj.time, traj.decel[0])["overall"])
    assert min(scores) > 0.93


def test_estimator_manners_and_seeding(world):
    est = CAESurrogate(n_components=4, n_unload_components=3, n_restarts=0, random_state=7)
    assert clone(est).get_params() == est.get_params()
    with pytest.raises(NotFittedError):
        est.curve(10.0, 900.0, 700.0)
    runs = [world.pulses[r] for r in world.cae[:60]]
    a = clone(est).fit(runs).curve(10.0, 950.0, 720.0, "Type I", "FWD")
    b = clone(est).fit(runs).curve(10.0, 950.0, 720.0, "Type I", "FWD")
    np.testing.assert_array_equal(a.a_loading, b.a_loading)
    assert a.u_end == b.u_end


def test_the_fit_runs_on_one_blas_thread_whatever_the_caller_set(world, monkeypatch):
    # A threaded product sums in a thread-count-dependent order: the workflow (one thread per
    # job) and a 2-thread shell would give surrogates 1e-5 apart and a fold 0.008 apart in ISO.
    seen = []
    impute = surrogate_module._impute_low_rank
    monkeypatch.setattr(surrogate_module, "_impute_low_rank", lambda *a: (
        seen.append([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]), impute(*a))[1])
    with threadpool_limits(limits=2, user_api="blas"):
        CAESurrogate(n_components=4, n_unload_components=3, random_state=0).fit(
            [world.pulses[r] for r in world.cae[:60]])
    assert seen and all(n == [1] * len(n) for n in seen)


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="x86 kernel names")
def test_the_kernels_are_named_as_numpy_and_blas_run_them():
    """One thread fixes the summation order on one processor, not across processors: validation tables
    and diagnoses record the machine code they ran (docs/decisions.md, sections 56 and 60)."""
    from crashfuse.gp.threads import cpu_kernels
    assert cpu_kernels().startswith(f"numpy {np.__version__} SIMD ") and "scipy: openblas" in cpu_kernels()
    code = "from crashfuse.gp.threads import cpu_kernels; print(cpu_kernels())"
    # numpy's dispatched targets all off, BLAS on SSE4.2 kernels: on every x86-64 of the last 15 years
    env = {**os.environ, "OPENBLAS_CORETYPE": "Nehalem",
           "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"}
    named = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert named.startswith(f"numpy {np.__version__} SIMD baseline;")
    assert named.count(" Nehalem") == named.count("openblas") == 2


def test_the_surrogate_records_and_checks_its_campaign(world, fitted):
    assert fitted.campaign_hash_ == world.content_hash()
    fitted.check_campaign(world)
    other = world.subset([r for r in world.pulses if r != world.cae[-1]])
    with pytest.raises(InputError, match=f"fitted on campaign {world.content_hash()[:12]}") as err:
        fitted.check_campaign(other, "s.cfmodel")
    assert (err.value.file, err.value.field) == ("s.cfmodel", "campaign_hash")
    from_pulses = clone(fitted).fit([world.pulses[r] for r in world.cae[:60]])
    assert from_pulses.campaign_hash_ is None
    with pytest.raises(InputError, match="records no campaign"):
        from_pulses.check_campaign(world)


def test_evaluate_refuses_a_surrogate_of_another_campaign(tmp_path, world, fitted, capsys):
    from crashfuse.cli import main
    from crashfuse.io.campaign_write import write_campaign
    from crashfuse.method.model import save_surrogate

    folder = write_campaign(world.subset([r for r in world.pulses if r != world.cae[-1]]), tmp_path / "campaign")
    save_surrogate(fitted, tmp_path / "s.cfmodel")
    argv = ["evaluate", str(folder), "--k", "1", "--surrogate", str(tmp_path / "s.cfmodel"), "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    assert "campaign_hash" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_run_whose_falling_tail_cannot_absorb_the_energy_is_an_input_error():
    # Closed form: the decel falls linearly from 101 to 1 m/s^2 in 0.1 s, a velocity change of
    # 5.1 m/s at v0 = 10 m/s. Continued with its falling last stiffness the decel reaches 0 long
    # before the remaining energy is absorbed, so the run has no maximum crush: an input error, not a NaN.
    t = np.linspace(0.0, 0.1, 1001)
    run = Pulse(time=t, decel=101.0 - 1000.0 * t, v0=10.0, front_weight=900.0, rear_weight=700.0,
                run_id="C999", source="cae", where="c999.csv")
    assert not displacement_branches(run).stopped
    with pytest.raises(InputError, match="C999.*before absorbing the impact energy") as err:
        CAECurve.from_pulse(run)
    assert err.value.file == "c999.csv" and err.value.field == "v0"


def test_bad_input(world, fitted):
    with pytest.raises(InputError, match="at least 10 CAE runs"):
        CAESurrogate().fit([world.pulses[r] for r in world.cae[:5]])
    with pytest.raises(InputError, match="CAE runs only"):
        CAESurrogate().fit([world.pulses["T01"], *(world.pulses[r] for r in world.cae[:20])])
    assert set(fitted.categories_) == {"powertrain", "drive"}
    with pytest.raises(InputError, match="powertrain"):
        fitted.curve(10.0, 900.0, 700.0, None, "FWD")
    with pytest.raises(InputError, match="drive"):
        fitted.curve(10.0, 900.0, 700.0, "Type I", "RWD")
    with pytest.raises(InputError, match="v0"):
        fitted.curve(-1.0, 900.0, 700.0, "Type I", "FWD")
