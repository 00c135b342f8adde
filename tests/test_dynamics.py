"""The rollout's stepping loop against the data integrator, closed forms and a CAE pulse."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.signals.domain import displacement_branches, kinematics
from crashfuse.signals.dynamics import Trajectory, rollout
from crashfuse.errors import InputError
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

DT = 8e-5
G = 9.80665


@pytest.fixture(scope="module")
def paper_campaign():
    return build(resolve("paper"), seed=0, n_cae=4)[0]


def _half_sine(n, peak=30 * G, length=0.07):
    t = np.arange(n) * DT
    return t, np.where(t <= length, peak * np.sin(np.pi * t / length), 0.0) + 0.5 * G


def test_time_only_decel_is_bit_identical_to_kinematics_through_the_stop():
    # A positive decel never triggers the barrier constraints, so the loop must be kinematics().
    t, a = _half_sine(1251)
    v0 = 12.0
    traj = rollout(lambda st: np.full(st.s.shape, a[st.step]), v0, DT, t.size - 1)
    v, s = kinematics(a, DT, v0)
    assert (v < 0).any(), "the case must cross zero velocity"
    np.testing.assert_array_equal(traj.v[0], v)
    np.testing.assert_array_equal(traj.s[0], s)
    np.testing.assert_array_equal(traj.time, t)
    # Unloading from the first step whose displacement does not advance (the maximum crush).
    first_back = int(np.flatnonzero(np.diff(s) <= 0)[0]) + 1
    assert np.all(traj.branch[0, :first_back] == Trajectory.LOADING)
    assert np.all(traj.branch[0, first_back:] == Trajectory.UNLOADING)
    assert traj.s_max[0] == s.max()


def test_velocity_dependent_decel_matches_the_closed_form_at_second_order():
    # a = c v: v = v0 exp(-c t), s = v0 (1 - exp(-c t)) / c; the vehicle never stops.
    c, v0, T = 40.0, 15.0, 0.1

    def error(dt):
        n = round(T / dt)
        traj = rollout(lambda st: c * st.v, v0, dt, n)
        return np.abs(traj.s[0] - v0 * (1 - np.exp(-c * traj.time)) / c).max()

    e1, e2 = error(4 * DT), error(2 * DT)
    assert e2 < 1e-5  # m, at dt = 0.16 ms
    assert e1 / e2 > 3.5  # second order in s


def test_cae_pulse_own_branches_reproduce_the_pulse(paper_campaign):
    p = paper_campaign.pulses["CT03"]
    br = displacement_branches(p)
    lo, un = br.loading, br.unloading

    def decel(st):
        return np.where(st.loading, np.interp(st.s, lo.x, lo.decel), np.interp(st.u, un.x, un.decel, right=0.0))

    traj = rollout(decel, p.v0, p.dt, p.time.size - 1)
    v, s = kinematics(p.decel, p.dt, p.v0)
    stop = int(np.flatnonzero(v <= 0)[0])
    # Loading retraces the data's own displacements, so the interpolation is exact there.
    np.testing.assert_array_equal(traj.decel[0, :stop], p.decel[:stop])
    assert traj.s_max[0] == pytest.approx(br.s_max, abs=1e-9)
    assert np.abs(traj.decel[0] - p.decel).max() < 0.1 * G
    assert np.abs(traj.v[0] - v).max() < 0.01
    assert np.abs(traj.s[0] - s).max() < 1e-3


def test_unloading_cannot_pull_and_separation_is_final():
    # Loading 20 g; on unloading the law is -5 g until u = 5 mm, then +10 g (a re-contact that must not happen).
    def decel(st):
        return np.where(st.loading, 20 * G, np.where(st.u < 0.005, -5 * G, 10 * G))

    traj = rollout(decel, 8.0, DT, 1500)
    unl = traj.branch[0] != Trajectory.LOADING
    assert unl.any()
    assert np.all(traj.decel[0, unl] == 0.0)
    assert np.all(traj.branch[0, unl][1:] == Trajectory.SEPARATED)
    # Free flight after separation: constant (negative) velocity.
    assert np.ptp(traj.v[0, unl][1:]) == 0.0 and traj.v[0, -1] < 0


def test_samples_are_independent_rows():
    v0 = np.array([8.0, 12.0, 15.6])
    t, a = _half_sine(1000)

    def decel(st):
        return np.where(st.loading, 2000 * st.s + a[st.step], 300.0 * st.u)

    many = rollout(decel, v0, DT, 999)
    for k, v in enumerate(v0):
        one = rollout(decel, v, DT, 999)
        np.testing.assert_allclose(many.s[k], one.s[0], rtol=0, atol=1e-15)
        np.testing.assert_array_equal(many.branch[k], one.branch[0])


@pytest.mark.parametrize("fn, v0, field", [
    (lambda st: np.zeros(3), 10.0, "decel_fn"),
    (lambda st: np.full(st.s.shape, np.nan), 10.0, "decel_fn"),
    (lambda st: np.zeros(st.s.shape), -1.0, "v0"),
    (lambda st: np.zeros(st.s.shape), np.array([[1.0]]), "v0"),
])
def test_bad_input_is_an_input_error(fn, v0, field):
    with pytest.raises(InputError) as err:
        rollout(fn, v0, DT, 10, n_samples=2)
    assert err.value.field == field


def test_on_branch_gives_the_branch_coordinate_of_one_sample():
    s = np.array([[0.0, 0.2, 0.5, 0.4, 0.1], [0.0, 0.1, 0.2, 0.3, 0.3]])
    v = np.array([[9.0, 6.0, 0.0, -1.0, -2.0], [9.0, 8.0, 7.0, 6.0, 5.0]])
    branch = np.array([[0, 0, 1, 1, 2], [0, 0, 0, 0, 0]], dtype=np.int8)
    traj = Trajectory(np.arange(5) * 1e-3, s, v, np.zeros_like(s), branch, np.array([0.5, 0.3]))
    on, x, vel = traj.on_branch("unloading")
    np.testing.assert_array_equal(on, [False, False, True, True, False])
    np.testing.assert_allclose(x, [0.0, 0.1])  # u = s_max - s
    np.testing.assert_array_equal(vel, [0.0, -1.0])
    on, x, vel = traj.on_branch("loading", sample=1)
    assert on.all() and np.array_equal(x, s[1]) and np.array_equal(vel, v[1])
