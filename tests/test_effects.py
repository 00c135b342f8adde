"""The rate-aware CAE force of the effect laws (crashfuse.method.laws) on analytic rate-dependent models."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.signals.dynamics import rollout
from crashfuse.method.laws import Plant, crush_force_rate, crush_speed, simulate
from crashfuse.signals.pulse import Pulse
from crashfuse.method.surrogate import CAECurve

M = 1500.0  # kg
K = 9.4e5  # N/m: linear crush stiffness, about 0.6 m of crush at 15 m/s
C = 2.0e4  # N s/m: viscous crush force, so the model's da/dv is C / M
DT, N = 1e-4, 1200


def _force_law_rollout(v0: float, mass: float, c2: float = 0.0):
    """A vehicle of ``mass`` whose crush force is K s + C v (+ c2 v^2), loading until it stops."""
    viscous = C if c2 == 0.0 else 0.0
    return rollout(lambda st: (K * st.s + viscous * np.maximum(st.v, 0.0) + c2 * np.maximum(st.v, 0.0) ** 2) / mass,
                   v0, DT, N)


def _runs(v0: float, c2: float = 0.0) -> list:
    """16 CAE runs of the force law at 0.6-1.4 times ``v0``, their mass varied independently (+-10 %)."""
    out = []
    for j, f in enumerate(np.linspace(0.6, 1.4, 16)):
        w = 1.0 + 0.1 * np.sin(2.4 * j)
        tr = _force_law_rollout(f * v0, M * w, c2)
        out.append(Pulse(tr.time, tr.decel[0], f * v0, 0.6 * M * w, 0.4 * M * w, f"C{j}", "cae"))
    return out


def _curve(v0: float) -> CAECurve:
    """The CAE curve of the nominal vehicle at ``v0``: its loading branch, a short elastic unloading."""
    return _curve_of(v0, 0.0)


def _curve_of(v0: float, c2: float) -> CAECurve:
    tr = _force_law_rollout(v0, M, c2)
    moving = tr.v[0] > 0.0
    s, a = tr.s[0][moving], tr.decel[0][moving]
    a_stop = K * s[-1] / M
    return CAECurve(s, a, np.array([0.0, 0.02]), np.array([a_stop, 0.0]), float(s[-1]), 0.02, v0)


def _plant(curve: CAECurve, runs) -> Plant:
    """The plant of ``curve``; with CAE ``runs``, rate-aware and continued beyond its crush by a faster curve."""
    if runs is None:
        return Plant.from_curves([curve], [M], [0], ("all",), 1.2)
    return Plant.from_curves([curve], [M], [0], ("all",), 1.2, [_curve_of(1.2 * curve.v0, 0.0)],
                             lambda s: crush_force_rate(runs, s))


def test_crush_speed_follows_the_energy_balance():
    curve = _curve(15.0)
    s = np.linspace(0.0, 0.7, 500)
    v = crush_speed(curve, s)
    assert v[0] == pytest.approx(15.0)
    assert np.all(v[s > curve.s_max + 1e-3] == 0.0)
    inside = s < 0.9 * curve.s_max
    exact = np.interp(s[inside], *_branch(15.0))
    assert np.abs(v[inside] - exact).max() < 0.02  # trapezoids on the curve's samples


def _branch(v0):
    tr = _force_law_rollout(v0, M)
    moving = tr.v[0] > 0.0
    return tr.s[0][moving], tr.v[0][moving]


def test_crush_force_rate_recovers_the_viscous_term():
    """Runs of several speeds and masses: the force's slope in crush speed is C, with no curvature."""
    b1, b2 = crush_force_rate(_runs(15.0), np.linspace(0.0, 0.5, 200))
    assert b1 == pytest.approx(np.full(200, C), rel=0.01)
    assert np.all(np.abs(b2 * 15.0) < 0.01 * C)


def test_the_cae_force_follows_a_curved_speed_dependence():
    """A force growing with v^2: a slower or faster rollout moves along the curve, not the tangent."""
    c2 = 1.5e3  # N s^2/m^2
    plant = _plant(_curve_of(15.0, c2), _runs(15.0, c2))
    s = np.array([0.2])
    for v in (3.0, 8.0, 14.0):
        crush, rest = plant.loading(s, np.array([v]))
        assert crush[0] == pytest.approx((K * 0.2 + c2 * v ** 2) / M, rel=0.01)
        assert rest[0] == pytest.approx(K * 0.2 / M, rel=0.01)


def test_rate_aware_plant_predicts_a_heavier_vehicle():
    """An extra mass arrives faster at every crush; the rate-aware CAE force follows, the s-only one does not."""
    v0, extra = 15.0, 200.0
    heavy = _force_law_rollout(v0, M + extra)
    base = _curve(v0)
    errors = {}
    for name, nb in (("s only", None), ("rate aware", _runs(v0))):
        got = simulate(_plant(base, nb), ("mass",), {"mass.extra": np.array([extra]), "mass.k_link": np.array([1e12])}, DT, N)
        loading = heavy.v[0] > 0.0
        errors[name] = np.abs(got.decel[0] - heavy.decel[0])[loading].max() / heavy.decel[0].max()
        if nb is not None:
            assert got.s_max[0] == pytest.approx(heavy.s_max[0], rel=0.01)
    assert errors["rate aware"] < 0.005
    assert errors["s only"] > 4 * errors["rate aware"]


def test_without_cae_runs_the_force_depends_on_crush_only():
    plant = _plant(_curve(15.0), None)
    s = np.array([0.3])
    slow, rest = plant.loading(s, np.array([3.0]))
    assert slow == pytest.approx(plant.loading(s, np.array([12.0]))[0], rel=1e-12)
    assert rest == pytest.approx(slow, rel=1e-12)


def test_rate_hardening_acts_on_the_static_strength():
    """With a viscous CAE force, the strain-rate law hardens K s only, not C v."""
    v0 = 15.0
    plant = _plant(_curve(v0), _runs(v0))
    s, v = np.array([0.2]), np.array([10.0])
    crush, rest = plant.loading(s, v)
    assert crush[0] == pytest.approx((K * 0.2 + C * 10.0) / M, rel=0.01)
    assert rest[0] == pytest.approx(K * 0.2 / M, rel=0.02)


def test_no_faster_curve_where_the_surrogate_cannot_predict():
    from crashfuse.method.effect_fit import faster_curve
    from crashfuse.errors import InputError

    class Surrogate:
        def __init__(self, v_max):
            self.v_max = v_max

        def curve(self, v0, *args):
            if v0 > self.v_max:
                raise InputError("cannot absorb the impact energy", field="v0")
            return _curve(v0)

    assert faster_curve(Surrogate(20.0), 15.0, 900.0, 600.0).v0 == pytest.approx(18.0)
    assert faster_curve(Surrogate(16.0), 15.0, 900.0, 600.0) is None
