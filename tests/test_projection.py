"""Bijective projection (Eq. 11-15) against a constructed pair with a known bias, and on the world."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.signals.domain import displacement_branches
from crashfuse.signals.dynamics import rollout
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.method.projection import bias_columns, bias_data, bias_inputs, nominal_time, project_branch, thin
from crashfuse.signals.pulse import Pulse
from crashfuse.method.surrogate import CAECurve, CAESurrogate
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

DT = 8e-5
N_STEPS = 2499  # 200 ms: both constructed pulses stop, rebound and separate inside the record
V0 = 10.0
U_SEP_CAE, U_SEP_TEST = 0.02, 0.03  # spring-back to separation (m)


# Constructed curves, m/s^2 vs m. Loading: the CAE's a linear stiffness; the test adds a known bias.
def cae_loading(s):
    return 100.0 + 400.0 * s


def stiffer_bias(s):  # positive: the test crushes less, the CAE reaches further
    return 20.0 + 30.0 * np.sin(6.0 * s)


def softer_bias(s):  # negative: the test reaches further
    return -40.0 - 50.0 * s


def unloading(peak, u_sep):
    """A linear spring-back from ``peak`` to 0 at ``u_sep``, 0 beyond (separated)."""
    return lambda u: peak * np.clip(1.0 - u / u_sep, 0.0, None)


CAE_UNLOAD = unloading(250.0, U_SEP_CAE)
TEST_UNLOAD = unloading(200.0, U_SEP_TEST)


def unload_bias(u):
    return TEST_UNLOAD(u) - CAE_UNLOAD(u)


def _pulse(load, unload, run_id, source, cae_run_id=None):
    """A pulse made by the real integrator from branch curves a(s) and a(u)."""
    traj = rollout(lambda st: np.where(st.loading, load(st.s), unload(st.u)), V0, DT, N_STEPS)
    meta = {"powertrain": "Type I", "drive": "FWD", "cae_run_id": cae_run_id, "cfc": 60}
    return Pulse(traj.time, traj.decel[0], V0, 900.0, 700.0, run_id=run_id, source=source, meta=meta)


@pytest.fixture(scope="module")
def cae():
    return _pulse(cae_loading, CAE_UNLOAD, "C1", "cae")


def _test_pulse(bias, run_id="T1", cae_run_id="C1"):
    return _pulse(lambda s: cae_loading(s) + bias(s), TEST_UNLOAD, run_id, "test", cae_run_id)


def _inner(x, *branches):
    """Points beyond the first sample interval of each branch (the unloading branch's first sample
    carries the loading decel at maximum crush: a jump no projection can see between samples)."""
    return x > max(b.x[1] for b in branches)


@pytest.mark.parametrize("bias", [stiffer_bias, softer_bias], ids=["cae-reaches-further", "test-reaches-further"])
def test_projection_recovers_a_known_loading_bias(cae, bias):
    tb, cb = displacement_branches(_test_pulse(bias)), displacement_branches(cae)
    x, v, b = project_branch(tb.loading, cb.loading)
    further = "cae" if bias is stiffer_bias else "test"
    assert (cb.s_max > tb.s_max) == (further == "cae"), "the constructed case must be the named scenario"
    # Both scenarios: every test point and every CAE point inside the overlap, nothing beyond it.
    top = min(tb.s_max, cb.s_max)
    assert x[0] == 0.0 and x[-1] == top
    expected = np.union1d(tb.loading.x[tb.loading.x <= top], cb.loading.x[cb.loading.x <= top])
    np.testing.assert_array_equal(x, expected)
    np.testing.assert_allclose(b, bias(x), atol=1e-3)
    # The test's velocity at x, against the closed-form energy balance v^2 = v0^2 - 2 int a ds.
    work = 100.0 * x + 200.0 * x**2 + (20.0 * x + 5.0 * (1 - np.cos(6.0 * x)) if bias is stiffer_bias
                                       else -40.0 * x - 25.0 * x**2)
    np.testing.assert_allclose(v**2, V0**2 - 2 * work, atol=1e-3)  # m^2/s^2 (v itself is stiff near v = 0)


def test_projection_recovers_a_known_unloading_bias(cae):
    tb, cb = displacement_branches(_test_pulse(stiffer_bias)), displacement_branches(cae)
    x, v, b = project_branch(tb.unloading, cb.unloading)
    # Away from the first sample interval and from the two separation kinks, where linear
    # interpolation between samples cannot follow the constructed curves' corners.
    h = max(np.diff(tb.unloading.x).max(), np.diff(cb.unloading.x).max())
    inner = _inner(x, tb.unloading, cb.unloading) & (np.abs(x - U_SEP_CAE) > h) & (np.abs(x - U_SEP_TEST) > h)
    assert inner.sum() > 100
    np.testing.assert_allclose(b[inner], unload_bias(x[inner]), atol=1e-3)
    assert np.all(v[x > 0] <= 0), "past maximum crush the test moves back"
    assert x[-1] == min(tb.unloading.x[-1], cb.unloading.x[-1])


def test_no_overlap_gives_no_data(cae):
    tb, cb = displacement_branches(_test_pulse(stiffer_bias)), displacement_branches(cae)
    shifted = type(cb.loading)(cb.loading.x + 10.0, cb.loading.decel, cb.loading.time, cb.loading.velocity)
    assert all(a.size == 0 for a in project_branch(tb.loading, shifted))


def _pair_campaign(cae, bias=stiffer_bias, companion="C1"):
    return Campaign.from_pulses([_test_pulse(bias, cae_run_id=companion), cae])


def test_bias_data_columns_and_known_bias(cae):
    camp = _pair_campaign(cae)
    paper = bias_data(camp, ["T1"], inputs="paper", n_grid=None)
    state = bias_data(camp, ["T1"], inputs="state", extra_inputs=True, n_grid=150)
    assert paper.loading.columns == ("x_m", "v0_mps", "front_weight_kg", "rear_weight_kg")
    # One powertrain and one drive level in this campaign: nothing to one-hot encode.
    assert state.loading.columns == ("x_m", "v_mps", "v0_mps", "front_weight_kg", "rear_weight_kg")
    assert state.loading.X.shape == (150, 5) and set(state.unloading.groups) == {"T1"}
    np.testing.assert_allclose(paper.loading.y, stiffer_bias(paper.loading.X[:, 0]), atol=1e-3)
    np.testing.assert_allclose(state.loading.y, stiffer_bias(state.loading.X[:, 0]), atol=1e-2)
    np.testing.assert_array_equal(paper.loading.X[:, 1:], [[V0, 900.0, 700.0]] * len(paper.loading.y))
    # The CAE separated at U_SEP_CAE: beyond it its decel is known to be 0, so the test's longer
    # spring-back still gives bias data (= the test's own decel), up to the test's reach.
    u, y = state.unloading.X[:, 0], state.unloading.y
    assert u[-1] > U_SEP_TEST
    inner = u > 5e-3
    np.testing.assert_allclose(y[inner], unload_bias(u[inner]), atol=0.5)


def test_one_hot_inputs_follow_the_campaign_levels():
    cols = bias_columns("state", {"powertrain": ["Type I", "Type II"], "drive": ["AWD", "FWD"]})
    assert cols[-2:] == ("powertrain=Type II", "drive=FWD")
    X = bias_inputs(cols, [0.1, 0.2], [5.0, 4.0], 10.0, 900.0, 700.0, "Type II", "AWD")
    np.testing.assert_array_equal(X, [[0.1, 5.0, 10.0, 900.0, 700.0, 1.0, 0.0],
                                      [0.2, 4.0, 10.0, 900.0, 700.0, 1.0, 0.0]])
    with pytest.raises(InputError, match="drive"):
        bias_inputs(cols, [0.1], [5.0], 10.0, 900.0, 700.0, "Type II", None)


def test_thinning_keeps_the_ends_and_recovers_the_bias(cae):
    tb, cb = displacement_branches(_test_pulse(stiffer_bias)), displacement_branches(cae)
    x, v, b = project_branch(tb.loading, cb.loading)
    xt, vt, bt = thin(x, v, b, 50)
    assert xt.size == 50 and xt[0] == x[0] and xt[-1] == x[-1]
    np.testing.assert_allclose(bt, stiffer_bias(xt), atol=0.05)
    assert thin(x, v, b, None)[0] is x


def test_missing_companion_is_an_input_error_unless_a_surrogate_stands_in(cae):
    camp = _pair_campaign(cae, companion=None)
    with pytest.raises(InputError, match="cae_run_id"):
        bias_data(camp, ["T1"])
    with pytest.raises(InputError, match="inputs"):
        bias_data(camp, ["T1"], inputs="speed")
    with pytest.raises(InputError, match="cae run"):
        bias_data(camp, ["C1"], cae_curves={})
    with pytest.raises(InputError, match="n_grid"):
        bias_data(camp, ["T1"], n_grid=1)
    # An explicit CAE curve (e.g. from a surrogate) stands in for the missing companion.
    explicit = bias_data(camp, ["T1"], cae_curves={"T1": CAECurve.from_pulse(cae)})
    paired = bias_data(_pair_campaign(cae), ["T1"])
    np.testing.assert_array_equal(explicit.loading.y, paired.loading.y)
    np.testing.assert_array_equal(explicit.unloading.X, paired.unloading.X)


@pytest.fixture(scope="module")
def world():
    return build(resolve("paper"), seed=3, n_cae=60)[0]


@pytest.fixture(scope="module")
def surrogate(world):
    return CAESurrogate(n_restarts=0, random_state=0).fit(world)


def test_fold_sees_only_its_training_tests(world):
    train = [t for t in world.tests if t != "T05"]
    data = bias_data(world, train, inputs="state", extra_inputs=True)
    for branch in (data.loading, data.unloading):
        assert "T05" not in set(branch.groups)
        assert set(branch.groups) <= set(train)
    assert data.loading.columns[-2:] == ("powertrain=Type II", "drive=FWD")


def test_companions_that_never_stop_take_the_surrogate_unloading(world, surrogate):
    direct = bias_data(world, world.tests)
    never = {t for t in world.tests if not displacement_branches(world.companion(t)).stopped}
    assert never, "the paper campaign has mid-speed companions that never stop in 100 ms"
    assert {k.split("/")[0] for k in direct.missing} == never
    filled = bias_data(world, world.tests, surrogate=surrogate)
    assert filled.missing == {} and set(filled.unloading.groups) == set(world.tests)
    # Without companions every test is projected on the surrogate's curve.
    alone = bias_data(world, world.tests[:3], surrogate=surrogate, use_companion=False)
    assert alone.loading.y.size == 3 * 200 and np.all(np.isfinite(alone.loading.y))


def test_low_speed_tests_have_a_sensible_unloading_branch(world):
    data = bias_data(world, ["T01", "T02", "T03"], inputs="state", n_grid=None)
    for test_id in ("T01", "T02", "T03"):
        tb = displacement_branches(world.pulses[test_id])
        cb = displacement_branches(world.companion(test_id))
        rows = data.unloading.groups == test_id
        u, v, y = data.unloading.X[rows, 0], data.unloading.X[rows, 1], data.unloading.y[rows]
        assert rows.sum() >= 10
        assert u.min() >= 0 and u.max() <= tb.unloading.x[-1]
        assert np.all(v[u > 0] <= 0), "past maximum crush the test moves back"
        # The bias is bounded by what the two curves can differ by on this branch.
        bound = max(np.abs(tb.unloading.decel).max(), np.abs(cb.unloading.decel).max())
        assert np.abs(y).max() <= bound
        loading = data.loading.groups == test_id
        assert data.loading.X[loading, 0].max() <= min(tb.s_max, cb.s_max) + 1e-12


def test_thinning_cost_falls_with_the_grid(world):
    """Bias recovered from the thinned data vs the full projection, on the world's 11 pairs."""
    errors = []
    for n_grid in (25, 100, 400):
        err = []
        for test_id in world.tests:
            tb = displacement_branches(world.pulses[test_id])
            cb = displacement_branches(world.companion(test_id))
            x, v, b = project_branch(tb.loading, cb.loading)
            xt, _, bt = thin(x, v, b, n_grid)
            err.append(np.sqrt(np.mean((np.interp(x, xt, bt) - b) ** 2)) / np.sqrt(np.mean(b**2)))
        errors.append(max(err))
    assert errors[0] > errors[1] > errors[2]
    # What remains at 400 points is the tests' measurement noise (the GP's nugget's share).
    assert errors[2] < 0.05


def test_relative_target_divides_by_the_floored_cae_decel(cae):
    from crashfuse.method.projection import SCALE_FLOOR, bias_scale
    camp = _pair_campaign(cae)
    absolute = bias_data(camp, ["T1"], inputs="paper", n_grid=None)
    relative = bias_data(camp, ["T1"], inputs="paper", n_grid=None, target="relative")
    x = absolute.loading.X[:, 0]
    np.testing.assert_allclose(relative.loading.y * bias_scale(cae_loading(x)), absolute.loading.y, atol=1e-3)
    assert relative.target == "relative" and bias_scale([0.0, 1e3]).tolist() == [SCALE_FLOOR, 1e3]
    no_weights = bias_data(camp, ["T1"], inputs="state", weights=False)
    assert no_weights.loading.columns == ("x_m", "v_mps", "v0_mps")
    with pytest.raises(InputError, match="target"):
        bias_data(camp, ["T1"], target="ratio")


def test_sqrt_velocity_column_round_trips(cae):
    from crashfuse.method.projection import column_velocity
    camp = _pair_campaign(cae)
    linear = bias_data(camp, ["T1"], inputs="state", n_grid=50)
    root = bias_data(camp, ["T1"], inputs="state", n_grid=50, velocity="sqrt")
    assert root.loading.columns[:2] == ("x_m", "v_sqrt")
    v = linear.loading.X[:, 1]
    np.testing.assert_allclose(root.loading.X[:, 1], np.sign(v) * np.sqrt(np.abs(v)))
    np.testing.assert_allclose(column_velocity("v_sqrt", root.loading.X[:, 1]), v)
    np.testing.assert_allclose(bias_inputs(root.loading.columns, [0.1], [-4.0], 1.0, 1.0, 1.0)[0, 1], -2.0)
    with pytest.raises(InputError, match="velocity"):
        bias_columns("state", velocity="log")


def test_cae_decel_input_is_the_cae_curve_where_the_bias_is_measured(cae):
    from crashfuse.units import G0
    camp = _pair_campaign(cae)
    data = bias_data(camp, ["T1"], inputs="state", n_grid=80, cae_decel="both")
    load, unload = data.loading, data.unloading
    assert load.columns[-1] == "cae_decel_g" and load.X.shape == (80, 6)
    np.testing.assert_allclose(load.X[:, -1] * G0, cae_loading(load.X[:, 0]), rtol=2e-3)
    u = unload.X[:, 0]
    inner = u > 1e-3  # the sampled pulse's peak is its own at u = 0
    np.testing.assert_allclose(unload.X[inner, -1] * G0, CAE_UNLOAD(u[inner]), atol=1e-6)  # 0 after separation
    plain = bias_data(camp, ["T1"], inputs="state", n_grid=80)
    np.testing.assert_array_equal(load.X[:, :-1], plain.loading.X)  # the other inputs unchanged
    with pytest.raises(InputError, match="CAE deceleration"):
        bias_inputs(load.columns, [0.1], [4.0], V0, 900.0, 700.0)
    only = bias_data(camp, ["T1"], inputs="state", n_grid=80, cae_decel="unloading")  # the state default
    assert only.loading.columns == plain.loading.columns and only.unloading.columns == unload.columns
    np.testing.assert_array_equal(only.unloading.X, unload.X)
    with pytest.raises(InputError, match="cae_decel.*'loading'"):
        bias_data(camp, ["T1"], inputs="state", cae_decel="loading")


def test_a_record_ending_before_separation_widens_the_rebound_span_upwards_only(cae):
    """The span the rollout holds a rebound to (:meth:`FittedModel.rebound_range`) comes from every
    training test: one whose record ends while its spring-back still pushes gives its ratio so far, a
    lower bound, so it may raise the span's top but not lower its bottom."""
    from crashfuse.method.model import _rebound_ratios
    curve = CAECurve.from_pulse(cae)
    ratio = np.sqrt((200.0 * U_SEP_TEST) / (250.0 * U_SEP_CAE))  # linear spring-backs: work = peak * u_sep / 2

    def ratios(unload, n_steps):
        test = _pulse(cae_loading, unload, "T1", "test", "C1")
        cut = Pulse(test.time[:n_steps], test.decel[:n_steps], V0, 900.0, 700.0, run_id="T1", source="test",
                    meta=test.meta)
        return _rebound_ratios(Campaign.from_pulses([cut, cae]), {"T1": curve})

    assert ratios(TEST_UNLOAD, N_STEPS) == [pytest.approx(ratio, rel=0.02)]  # separated inside the record
    t_stop = displacement_branches(cae).t_stop  # the test's loading is the CAE's
    early = int(round(t_stop / DT)) + 40  # a few mm into the spring-back
    assert ratios(TEST_UNLOAD, early) == [1.0]  # less work so far than the CAE's: no lower bound on the span
    strong = unloading(2000.0, U_SEP_TEST)  # ten times the force: more than the CAE's whole work within mm
    assert ratios(strong, early)[0] > 1.5


@pytest.mark.parametrize("velocity", ["linear", "sqrt"])
def test_nominal_time_is_exact_at_constant_deceleration(velocity):
    v0, a = 15.0, 200.0  # m/s, m/s^2
    t = np.linspace(0.0, 0.07, 8)
    s, v = v0 * t - 0.5 * a * t**2, v0 - a * t
    columns = bias_columns("state", velocity=velocity)
    X = bias_inputs(columns, s, v, v0, 900.0, 700.0)
    np.testing.assert_allclose(nominal_time(columns, X), t, atol=1e-12)
    with pytest.raises(InputError, match="velocity"):
        nominal_time(bias_columns("paper"), bias_inputs(bias_columns("paper"), s, None, v0, 900.0, 700.0))
