"""The rate-aware CAE force of the effect laws (crashfuse.effects) on an analytic rate-dependent model."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.dynamics import rollout
from crashfuse.effects import Plant, crush_speed, rate_sensitivity, simulate
from crashfuse.surrogate import CAECurve

M = 1500.0  # kg
K = 9.4e5  # N/m: linear crush stiffness, about 0.6 m of crush at 15 m/s
C = 2.0e4  # N s/m: viscous crush force, so the model's da/dv is C / M
DT, N = 1e-4, 1200


def _force_law_rollout(v0: float, mass: float):
    """A vehicle of ``mass`` whose crush force is K s + C v, loading until it stops."""
    return rollout(lambda st: (K * st.s + C * np.maximum(st.v, 0.0)) / mass, v0, DT, N)


def _curve(v0: float) -> CAECurve:
    """The CAE curve of the nominal vehicle at ``v0``: its loading branch, a short elastic unloading."""
    tr = _force_law_rollout(v0, M)
    moving = tr.v[0] > 0.0
    s, a = tr.s[0][moving], tr.decel[0][moving]
    a_stop = K * s[-1] / M
    return CAECurve(s, a, np.array([0.0, 0.02]), np.array([a_stop, 0.0]), float(s[-1]), 0.02, v0)


def _plant(curve: CAECurve, neighbours) -> Plant:
    return Plant.from_curves([curve], [M], [0], ("all",), 1.2, None if neighbours is None else [neighbours])


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


def test_rate_sensitivity_recovers_the_viscous_term():
    curves = [_curve(f * 15.0) for f in (0.9, 1.0, 1.1)]
    s = np.linspace(0.0, 0.5, 200)
    assert rate_sensitivity(curves, s) == pytest.approx(np.full(s.size, C / M), rel=0.02)


def test_rate_aware_plant_predicts_a_heavier_vehicle():
    """An extra mass arrives faster at every crush; the rate-aware CAE force follows, the s-only one does not."""
    v0, extra = 15.0, 200.0
    heavy = _force_law_rollout(v0, M + extra)
    base = _curve(v0)
    errors = {}
    for name, nb in (("s only", None), ("rate aware", [_curve(f * v0) for f in (0.9, 1.0, 1.1)])):
        got = simulate(_plant(base, nb), ("mass",), {"mass.extra": np.array([extra])}, DT, N)
        loading = heavy.v[0] > 0.0
        errors[name] = np.abs(got.decel[0] - heavy.decel[0])[loading].max() / heavy.decel[0].max()
        if nb is not None:
            assert got.s_max[0] == pytest.approx(heavy.s_max[0], rel=0.01)
    assert errors["rate aware"] < 0.005
    assert errors["s only"] > 4 * errors["rate aware"]


def test_without_neighbours_the_force_depends_on_crush_only():
    plant = _plant(_curve(15.0), None)
    s = np.array([0.3])
    slow, rest = plant.loading(s, np.array([3.0]))
    assert slow == pytest.approx(plant.loading(s, np.array([12.0]))[0], rel=1e-12)
    assert rest == pytest.approx(slow, rel=1e-12)


def test_rate_hardening_acts_on_the_static_strength():
    """With a viscous CAE force, the strain-rate law hardens K s only, not C v."""
    v0 = 15.0
    plant = _plant(_curve(v0), [_curve(f * v0) for f in (0.9, 1.0, 1.1)])
    s, v = np.array([0.2]), np.array([10.0])
    crush, rest = plant.loading(s, v)
    assert crush[0] == pytest.approx((K * 0.2 + C * 10.0) / M, rel=0.01)
    assert rest[0] == pytest.approx(K * 0.2 / M, rel=0.02)


def test_neighbours_leave_out_speeds_the_surrogate_cannot_predict():
    from types import SimpleNamespace

    from crashfuse.effect_fit import _neighbours
    from crashfuse.errors import InputError

    class Surrogate:
        def __init__(self, v_max):
            self.v_max = v_max

        def curve(self, v0, *args):
            if v0 > self.v_max:
                raise InputError("cannot absorb the impact energy", field="v0")
            return _curve(v0)

    test = SimpleNamespace(v0=15.0, front_weight=900.0, rear_weight=600.0, meta={})
    assert [c.v0 for c in _neighbours(Surrogate(16.0), test)] == pytest.approx([12.0, 15.0])
    assert _neighbours(Surrogate(14.0), test) == []
