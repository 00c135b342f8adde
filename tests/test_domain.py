"""The one integrator (velocity Verlet) and the displacement-domain branches, on closed-form cases."""

import numpy as np
import pytest

from crashfuse import InputError, Pulse
from crashfuse.signals.domain import displacement_branches, kinematics, position_step, rebound_work, velocity_step
from crashfuse.units import G0

DT = 1e-4


def _half_sine(amp, period, t):
    """Half-sine deceleration and its exact velocity and displacement for impact speed v0 = 0
    (add v0 and v0 t): a = A sin(pi t / T) on [0, T], zero after."""
    w = np.pi / period
    tc = np.minimum(t, period)
    dv = amp / w * (1 - np.cos(w * tc))
    ds = amp / w * (tc - np.sin(w * tc) / w) + (amp / w * 2) * (t - tc)
    return amp * np.sin(w * tc), dv, ds


def _pulse(decel, t, v0, **kw):
    return Pulse(time=t, decel=decel, v0=v0, front_weight=900.0, rear_weight=700.0, where="p.csv", **kw)


def test_record_and_step_forms_agree_bit_for_bit():
    rng = np.random.default_rng(3)
    decel = rng.normal(200.0, 80.0, size=(5, 300))
    v0 = rng.uniform(10, 20, size=5)
    v, s = kinematics(decel, DT, v0)
    s_k, v_k = np.zeros(5), v0.copy()
    for i in range(1, 300):
        s_k = position_step(s_k, v_k, decel[:, i - 1], DT)
        v_k = velocity_step(v_k, decel[:, i - 1], decel[:, i], DT)
        np.testing.assert_array_equal(s_k, s[:, i])
        np.testing.assert_array_equal(v_k, v[:, i])


def test_constant_deceleration_is_integrated_exactly():
    t = np.arange(400) * DT
    v, s = kinematics(np.full(400, 300.0), DT, 15.0)
    np.testing.assert_allclose(v, 15.0 - 300.0 * t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s, 15.0 * t - 150.0 * t**2, rtol=0, atol=1e-12)


def test_broadcasts_over_leading_axes():
    decel = np.ones((2, 3, 50))
    v, s = kinematics(decel, DT, np.array([[10.0], [20.0]]))
    assert v.shape == s.shape == (2, 3, 50)
    np.testing.assert_array_equal(v[1, 2], kinematics(decel[1, 2], DT, 20.0)[0])


def test_second_order_on_a_half_sine():
    amp, period, v0 = 30 * G0, 0.08, 15.0
    errors = []
    for dt in (4e-4, 2e-4, 1e-4):
        t = np.arange(int(0.1 / dt) + 1) * dt
        a, dv, ds = _half_sine(amp, period, t)
        v, s = kinematics(a, dt, v0)
        errors.append(max(np.abs(v - (v0 - dv)).max(), np.abs(s - (v0 * t - ds)).max()))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 3.5) & (ratios < 4.5)), ratios


def test_rollout_of_a_linear_spring_matches_the_closed_form_for_many_samples():
    # decel = w^2 s (a linear barrier spring): s = v0/w sin(w t) while loading.
    w = np.array([40.0, 45.0, 50.0])
    v0 = 15.0
    s, v = np.zeros(3), np.full(3, v0)
    a = w**2 * s
    n = int(0.9 * np.pi / 2 / w.max() / DT)
    for _ in range(n):  # the explicit step the rollout takes: the new deceleration needs only the new s
        s_new = position_step(s, v, a, DT)
        a_new = w**2 * s_new
        s, v, a = s_new, velocity_step(v, a, a_new, DT), a_new
    t = n * DT
    np.testing.assert_allclose(s, v0 / w * np.sin(w * t), rtol=1e-5)
    np.testing.assert_allclose(v, v0 * np.cos(w * t), rtol=1e-5)


def test_branches_of_a_rebounding_half_sine():
    amp, period, v0 = 30 * G0, 0.08, 12.0
    t = np.arange(1500) * DT
    a, dv, ds = _half_sine(amp, period, t)
    br = displacement_branches(_pulse(a, t, v0))
    w = np.pi / period
    t_stop = np.arccos(1 - v0 * w / amp) / w  # v0 = A/w (1 - cos(w t))
    s_max = v0 * t_stop - amp / w * (t_stop - np.sin(w * t_stop) / w)
    assert br.stopped
    assert br.t_stop == pytest.approx(t_stop, abs=DT / 10)
    assert br.s_max == pytest.approx(s_max, abs=1e-5)
    lo, un = br.loading, br.unloading
    assert lo.x[0] == 0 and lo.x[-1] == br.s_max and np.all(np.diff(lo.x) > 0)
    assert un.x[0] == 0 and np.all(np.diff(un.x) > 0) and un.time[-1] == t[-1]
    assert np.all(lo.velocity > 0) and np.all(un.velocity[1:] < 0)  # the max is shared
    # Resampling on the exact displacement of known times gives the exact deceleration back.
    tq = np.linspace(0.002, 0.95 * t_stop, 25)
    aq, _, dsq = _half_sine(amp, period, tq)
    np.testing.assert_allclose(np.interp(v0 * tq - dsq, lo.x, lo.decel), aq, rtol=2e-3)


def test_pre_impact_samples_are_cropped():
    t = np.arange(-200, 1500) * DT
    a, _, _ = _half_sine(30 * G0, 0.08, np.clip(t, 0, None))
    full = displacement_branches(_pulse(a, t, 12.0))
    cropped = displacement_branches(_pulse(a[t >= -DT / 2], t[t >= -DT / 2], 12.0))
    assert full.s_max == cropped.s_max and full.t_stop == cropped.t_stop
    np.testing.assert_array_equal(full.loading.x, cropped.loading.x)


def test_pulse_that_never_stops_has_a_flagged_loading_branch_only():
    t = np.arange(800) * DT
    a, dv, _ = _half_sine(20 * G0, 0.06, t)
    br = displacement_branches(_pulse(a, t, 25.0))  # 25 m/s > total delta-v of 7.5 m/s
    assert not br.stopped and br.unloading is None and br.t_stop is None
    assert np.all(np.diff(br.loading.x) > 0) and br.s_max == br.loading.x[-1]


def test_second_reversal_ends_the_unloading_branch():
    t = np.arange(2000) * DT
    a, _, _ = _half_sine(30 * G0, 0.08, t)
    a = np.where(t > 0.12, -40 * G0, a)  # pushed forward again after the rebound
    v, _ = kinematics(a, DT, 12.0)
    br = displacement_branches(_pulse(a, t, 12.0))
    forward_again = t[(t > br.t_stop) & (v > 0)][0]
    assert br.unloading.time[-1] < forward_again
    assert np.all(np.diff(br.unloading.x) > 0)


def test_noise_never_breaks_monotonic_branches():
    rng = np.random.default_rng(7)
    t = np.arange(1500) * DT
    a, _, _ = _half_sine(30 * G0, 0.08, t)
    br = displacement_branches(_pulse(a + rng.normal(0, 20 * G0, t.size), t, 12.0))
    assert np.all(np.diff(br.loading.x) > 0) and np.all(np.diff(br.unloading.x) > 0)
    assert br.loading.x[-1] == br.s_max


def test_rebound_work_is_the_spring_back_work_up_to_where_the_deceleration_stops_pushing():
    """A linear spring-back 10 g -> 0 over 20 mm returns 0.5 * 10 g * 0.02 m; the -2 g after it (the car
    leaving, its structure ringing) does not count; a branch cut before separation says so."""
    u = np.linspace(0.0, 0.04, 401)
    a = np.where(u <= 0.02, 10 * G0 * (1 - u / 0.02), -2 * G0)
    work, peak = rebound_work(u, np.stack([a, 0.5 * a]))
    np.testing.assert_allclose(work, [0.1 * G0, 0.05 * G0], rtol=1e-9)
    assert list(peak) == [200, 200]
    assert rebound_work(u[:100], a[:100])[1] == 99  # still pushing at the end of the record
