"""The physics-first hybrid (crashfuse.method.hybrid): effect laws fitted on training tests only,
added to the CAE model; without effects it is the GMM-GPR model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.method import effect_fit
from crashfuse.method.config import MethodConfig
from crashfuse.method.hybrid import fit_physics
from crashfuse.method.model import fit_model, load_model
from crashfuse.method.projection import cae_curve
from crashfuse.method.rollout import predict
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

N_CAE = 12
CANDIDATES = ("mass", "damping")  # two laws keep the forward selection fast


CONFIG = MethodConfig(k=1, inputs="paper", n_grid=40)  # cheap bias fits: these tests are about the laws


def _with(effects) -> MethodConfig:
    return dataclasses.replace(CONFIG, effects=effects)


@pytest.fixture(scope="module")
def worlds():
    """The damping world and the control (same seed: same conditions and CAE runs), with a surrogate."""
    damped, _ = build(resolve("withheld", withhold="damping"), seed=2, n_cae=N_CAE)
    control, _ = build(resolve("withheld", withhold="none"), seed=2, n_cae=N_CAE)
    return damped, control, CAESurrogate(random_state=0).fit(control)


def _held_out_only(damped: Campaign, control: Campaign, test_id: str) -> Campaign:
    """The control with one test replaced by the damping world's: the effect exists in that test only."""
    pulses = {**control.pulses, test_id: damped.pulses[test_id]}
    return Campaign(control.conditions, pulses, control.root)


def _predict(model, campaign, test_id):
    t = campaign.pulses[test_id]
    return predict(model, t.v0, t.front_weight, t.rear_weight, t.meta.get("powertrain"), t.meta.get("drive"),
                   n_samples=20, random_state=0, duration=0.08)


@pytest.fixture(scope="module")
def held(worlds):
    return worlds[0].tests[-1]  # the fastest test: the damping force is largest there


@pytest.fixture(scope="module")
def auto_damped(worlds, held):
    damped, _, surrogate = worlds
    return fit_physics(damped, [t for t in damped.tests if t != held], "auto", surrogate, candidates=CANDIDATES)


def test_auto_finds_a_withheld_effect_on_the_training_tests(worlds, held, auto_damped):
    assert auto_damped.effects[0] == "damping"
    assert auto_damped.tests == sorted(t for t in worlds[0].tests if t != held)
    assert auto_damped.inner_mse["damping"] < 0.9 * auto_damped.inner_mse["none"]


def test_an_effect_only_the_held_out_test_carries_is_not_chosen(worlds, held, auto_damped):
    damped, control, surrogate = worlds
    planted = _held_out_only(damped, control, held)
    train = [t for t in planted.tests if t != held]  # what fit_model passes for this fold
    assert fit_physics(planted, train, "auto", surrogate, candidates=CANDIDATES).effects == ()
    assert "damping" in auto_damped.effects  # the same fold with the effect in its training tests: can fail
    model = fit_model(planted, _with(("damping",)), holdout=held, surrogate=surrogate)
    assert held not in model.physics.tests and len(model.physics.tests) == len(train)


def test_the_hybrid_without_effects_is_the_gmm_gpr_model(worlds):
    _, control, surrogate = worlds
    held = control.tests[3]
    plain = fit_model(control, CONFIG, holdout=held, surrogate=surrogate)
    none = fit_model(control, _with("none"), holdout=held, surrogate=surrogate)
    a = _predict(plain, control, held)
    np.testing.assert_array_equal(_predict(none, control, held).decel, a.decel)
    # a zero effect's laws replay the CAE curve the bias is learnt against (loading branch, 1 % of peak)
    physics = fit_physics(control, [t for t in control.tests if t != held], ("mass",), surrogate)
    zero = dataclasses.replace(physics, theta={"mass.extra": 0.0, "mass.k_link": 1e12})
    for t in control.tests:
        p = control.pulses[t]
        base = cae_curve(control, p, surrogate)
        replay = zero.curve(base, p.mass, p.meta.get("powertrain"), None, p.front_weight, p.rear_weight)
        s = np.linspace(0.0, 0.98 * base.s_max, 200)  # the stop itself falls between rollout steps
        assert replay.s_max == pytest.approx(base.s_max, rel=1e-3)
        np.testing.assert_allclose(replay.loading(s), base.loading(s), atol=0.01 * base.a_loading.max())


def test_a_fitted_effect_moves_the_cae_curve_and_survives_the_model_file(worlds, tmp_path):
    damped, _, surrogate = worlds
    held = damped.tests[-1]
    model = fit_model(damped, _with(("damping",)), holdout=held, surrogate=surrogate)
    assert model.physics.theta["damping.c"] > 0
    t = damped.pulses[held]
    labels = t.meta.get("powertrain"), t.meta.get("drive")
    cond = model.condition(t.v0, t.front_weight, t.rear_weight, *labels)
    base = model.surrogate.curve(t.v0, t.front_weight, t.rear_weight, *labels)
    # damping adds force: the CAE + effects curve stops in less crush than the CAE model's
    assert model.cae_curve(cond).s_max < base.s_max
    model.save(tmp_path / "hybrid.cfmodel")
    loaded = load_model(tmp_path / "hybrid.cfmodel")
    assert loaded.physics.effects == ("damping",)
    np.testing.assert_allclose(_predict(loaded, damped, held).decel, _predict(model, damped, held).decel,
                               rtol=1e-9, atol=1e-6)


def test_physics_fitted_on_other_tests_is_refused(worlds):
    damped, _, surrogate = worlds
    physics = fit_physics(damped, damped.tests[1:], ("mass",), surrogate)
    with pytest.raises(ValueError, match="physics fitted on"):
        fit_model(damped, _with(("mass",)), holdout=damped.tests[2],
                  surrogate=surrogate, physics=physics)


@pytest.mark.parametrize("effects", [("friction",), ("mass", "mass"), 3, "everything"])
def test_unknown_effects_are_refused_naming_the_setting(effects):
    with pytest.raises(InputError) as err:
        MethodConfig(effects=effects)
    assert err.value.field == "effects"


def test_the_command_line_names_the_flag(capsys):
    assert main(["fit", "campaign-not-needed", "--k", "1", "--effects", "friction", "--out", "m.cfmodel"]) != 0
    assert "--effects" in capsys.readouterr().err


def test_rate_laws_need_cae_runs_at_several_speeds(worlds, monkeypatch):
    damped, _, surrogate = worlds
    monkeypatch.setattr(effect_fit, "MIN_CAE_SPEEDS", 10 ** 6)  # as if every CAE run had one speed
    with pytest.raises(InputError, match="impact speeds") as err:
        fit_physics(damped, damped.tests[1:], ("damping",), surrogate)
    assert err.value.field == "effects"
    physics = fit_physics(damped, damped.tests[1:], "auto", surrogate, candidates=CANDIDATES)
    assert "damping" not in physics.effects and not physics.rate_aware
    assert any("left out" in note for note in physics.notes)


def test_an_evaluation_labels_the_hybrid_and_records_its_effects(worlds, tmp_path):
    from crashfuse.evaluation.iso_table import is_model_label, model_order
    from crashfuse.evaluation.loto import evaluate
    from crashfuse.evaluation.records import read_fold_json

    damped, _, surrogate = worlds
    held = damped.tests[-1]
    result = evaluate(damped, ks=[1], inputs=["paper"], out=tmp_path, n_samples=10, n_jobs=1, surrogate=surrogate,
                      holdout=held, progress=None, n_grid=40, effects=("damping",))
    assert set(result.iso_table["model"]) == {"CAE", "K1+damping"}
    record = read_fold_json(tmp_path / "paper" / "K1+damping" / held / f"{held}.fold.json")
    assert record.model == "K1+damping" and record.settings["effects_fitted"] == "damping"
    assert is_model_label("K2+strain_rate+powertrain") and not is_model_label("K1+")
    assert sorted(["K2", "K1+auto", "CAE", "K1"], key=model_order) == ["CAE", "K1", "K1+auto", "K2"]


def test_a_powertrain_arrest_no_training_test_reached_is_switched_off(worlds):
    from crashfuse.method.hybrid import UNREACHED_GAP, _reach, _switch_off_unreached

    damped, _, surrogate = worlds
    case = effect_fit.test_case(damped.subset([*damped.tests[:-1], *damped.cae]), surrogate)
    reach = _reach(case, range(len(case.test_ids)))
    assert all(0.0 < r == max(case.crush[case.plant.group == g]) for g, r in enumerate(reach.values()))
    (far, far_reach), (near, near_reach) = sorted(reach.items())[:2]
    theta = {f"powertrain.gap[{far}]": far_reach + 0.01, f"powertrain.gap[{near}]": near_reach - 0.05,
             f"powertrain.mass[{far}]": 200.0, f"powertrain.mass[{near}]": 200.0, "powertrain.f_mount": 5e4}
    notes = _switch_off_unreached(theta, reach)
    assert theta[f"powertrain.gap[{far}]"] == UNREACHED_GAP and len(notes) == 1 and far in notes[0]
    assert theta[f"powertrain.gap[{near}]"] == pytest.approx(near_reach - 0.05)


def test_the_inner_error_predicts_a_test_that_alone_reached_its_engine_without_it(worlds):
    """``auto``'s inner error predicts each training test as the model fitted without it would: a test
    that is the only one of its powertrain label meets no arrest (fit_physics switches it off), not
    the engine its inner fit left at the starting point."""
    from crashfuse.method import hybrid

    damped, _, surrogate = worlds
    case = effect_fit.test_case(damped.subset([*damped.tests, *damped.cae]), surrogate)
    group = case.plant.group
    sole = next(r for r in range(len(group)) if (group == group[r]).sum() > 1)  # keep it alone among ``rows``
    rows = [sole] + [r for r in range(len(group)) if group[r] != group[sole]]
    params = effect_fit.parameters_to_fit(case, ("powertrain",))
    value = {p.name: (0.05 if ".gap[" in p.name else p.upper if ".mass[" in p.name else p.start[0]) for p in params}
    theta = np.tile([value[p.name] for p in params], (len(rows) + 1, 1))  # an engine every test reaches at once
    fits = effect_fit.FoldFits(("powertrain",), params, theta, np.zeros(len(rows) + 1))
    guarded = hybrid._inner_errors(case, fits, rows)
    unguarded = effect_fit.predict(case, fits, range(len(rows)), rows)[1]
    off = theta.copy()
    off[0, [p.name == f"powertrain.gap[{case.plant.labels[group[sole]]}]" for p in params]] = hybrid.UNREACHED_GAP
    alone = effect_fit.predict(case, dataclasses.replace(fits, theta=off), [0], [sole])[1][0]
    np.testing.assert_allclose(guarded, [alone, *unguarded[1:]], rtol=1e-12)
    assert abs(alone - unguarded[0]) > 0.1 * unguarded[0]  # the engine matters there: the check can fail


def test_a_warm_start_stuck_in_a_worse_basin_is_beaten_by_the_listed_starts(worlds):
    """``auto`` warm-starts a bigger effect set from the smaller one's fit; where that start holds a fit
    in a worse basin, the listed starts tried beside it (``listed_too``) keep each set's best."""
    damped, _, surrogate = worlds
    case = effect_fit.test_case(damped.subset([*damped.tests, *damped.cae]), surrogate)
    sets = effect_fit.loto_sets(len(case.test_ids))[:2]
    stuck = np.tile([10.0, 3.0], (len(sets), 1))  # a weak damping of high exponent: the fit stays near it
    warm = effect_fit.fit_folds(case, ("damping",), sets, start=stuck)
    listed = effect_fit.fit_folds(case, ("damping",), sets)
    assert (warm.cost > 2.0 * listed.cost).all()  # the start alone loses: the check below can fail
    both = effect_fit.fit_folds(case, ("damping",), sets, start=stuck, listed_too=True)
    np.testing.assert_allclose(both.cost, np.minimum(warm.cost, listed.cost), rtol=1e-9)


def test_fit_reports_the_laws_and_their_fallbacks():
    from crashfuse.cli import _physics_line
    from crashfuse.method.hybrid import PhysicsFirst

    physics = PhysicsFirst(("powertrain",), ["T01"], {"powertrain.gap[A]": 0.5, "powertrain.f_mount": 5e4}, ("A",),
                           1.0, np.zeros((2, 4)), True, 1.0, {}, ["powertrain law off for B"])
    line = _physics_line(physics)
    assert "powertrain (powertrain.gap[A]=0.5, powertrain.f_mount=5e+04)" in line and "law off for B" in line
    empty = dataclasses.replace(physics, effects=(), theta={}, notes=[])
    assert _physics_line(empty) == "effect laws: none (nothing fitted)"


def test_an_earlier_pick_the_later_ones_make_unneeded_leaves(monkeypatch):
    """Scripted inner errors: A joins first (50 of 100), B next (30); refitted from A + B's values B
    alone does as well (31), so A leaves and C, which would not gain 10 %, is not added."""
    from types import SimpleNamespace

    from crashfuse.method import hybrid

    def fit(case, effects, sets, start=None, listed_too=False):
        return SimpleNamespace(effects=tuple(effects), params=[SimpleNamespace(name=e) for e in effects],
                               theta=np.zeros((len(sets), len(effects))), refit=start is not None and len(effects) == 1)

    table = {(): 100.0, ("A",): 50.0, ("B",): 60.0, ("C",): 95.0, ("A", "B"): 30.0, ("A", "C"): 45.0,
             ("B", "C"): 29.0, ("A", "B", "C"): 24.0}
    monkeypatch.setattr(hybrid, "fit_folds", fit)
    monkeypatch.setattr(hybrid, "warm_start", lambda case, current, effects: None)
    monkeypatch.setattr(hybrid, "parameters_to_fit", lambda case, effects: [SimpleNamespace(name=e) for e in effects],
                        raising=False)
    monkeypatch.setattr(hybrid, "_per_label", lambda effect: True)
    monkeypatch.setattr(hybrid, "_inner_errors",
                        lambda case, f, rows: np.full(3, 31.0 if f.refit else table[tuple(sorted(f.effects))]))
    effects, tried, fits, _ = hybrid.choose_effects(None, [0, 1, 2], ("A", "B", "C"))
    assert effects == ("B",) and fits.effects == ("B",)
    assert tried["B (refitted without A)"] == 31.0 and tried["B+C"] == 29.0 and "A+B+C" not in tried
    table[("A", "B")] = 25.0  # now A still removes more than 10 % beyond B refitted: it stays
    assert hybrid.choose_effects(None, [0, 1, 2], ("A", "B", "C"))[0] == ("A", "B")


def test_a_law_of_no_label_joins_only_where_it_gains_on_more_than_one_label(monkeypatch):
    """Scripted inner errors on two labels' tests: rate hardening removes 45 % of the error, all of it on
    the first label's tests, and is refused; extra mass removes 30 % spread over both and joins. The
    powertrain law, one per label, may gain on one label alone."""
    from types import SimpleNamespace

    from crashfuse.method import hybrid

    def fit(case, effects, sets, start=None, listed_too=False):
        return SimpleNamespace(effects=tuple(effects), params=[], theta=np.zeros((len(sets), 0)))

    table = {(): [10, 10, 10, 10], ("strain_rate",): [1, 1, 10, 10], ("mass",): [7, 7, 7, 7],
             ("powertrain",): [2, 2, 10, 10], ("mass", "strain_rate"): [1, 1, 7, 7],
             ("mass", "powertrain"): [2, 2, 7, 7], ("powertrain", "strain_rate"): [1, 1, 10, 10]}
    monkeypatch.setattr(hybrid, "fit_folds", fit)
    monkeypatch.setattr(hybrid, "warm_start", lambda case, current, effects: None)
    monkeypatch.setattr(hybrid, "parameters_to_fit", lambda case, effects: [])
    monkeypatch.setattr(hybrid, "_inner_errors", lambda case, f, rows: np.array(table[tuple(sorted(f.effects))], float))
    case = SimpleNamespace(plant=SimpleNamespace(group=np.array([0, 0, 1, 1])))
    effects, tried, _, notes = hybrid.choose_effects(case, [0, 1, 2, 3], ("strain_rate", "mass"))
    assert effects == ("mass",) and tried["strain_rate"] == 5.5
    assert len(notes) == 2 and all(n.startswith("strain_rate refused") for n in notes)
    assert hybrid.choose_effects(case, [0, 1, 2, 3], ("strain_rate", "powertrain"))[0] == ("powertrain",)
    case.plant.group = np.array([0, 0, 0, 1])  # one test of the second label: the rule has nothing to compare
    assert hybrid.choose_effects(case, [0, 1, 2, 3], ("strain_rate", "mass"))[0][0] == "strain_rate"
