"""The one stepping loop of a rollout (paper Eq. 23), vectorised over Monte Carlo samples.

Each of ``m`` samples carries a state: displacement ``s`` (m), velocity ``v`` (m/s), maximum
crush so far ``s_max`` (m), its branch and whether it has separated from the barrier. Steps use
:func:`crashfuse.signals.domain.position_step` / :func:`crashfuse.signals.domain.velocity_step` (velocity
Verlet), the integrator that turned the data into the displacement domain, so a rollout whose
deceleration is a pulse's own branch curves gives that pulse back.

Branches follow :func:`crashfuse.signals.domain.displacement_branches`:

* loading while the displacement advances beyond every earlier one (``x = s``);
* the first step where it does not (the velocity has reached zero: maximum crush) switches the
  sample to unloading for good, with ``x = u = s_max - s``;
* on unloading the barrier cannot pull: the deceleration is clipped at >= 0, and once it reaches
  zero while the vehicle moves away (``v < 0``) the sample has separated and its deceleration
  stays 0 (no re-contact).

Velocity Verlet needs the new deceleration at the new position before the new velocity exists.
When the deceleration also depends on the velocity (the ``state`` inputs), the state handed to
``decel_fn`` carries the explicit prediction ``v_pred = v - a dt``: the scheme stays explicit and
second order in ``s`` (the position update does not use the new deceleration), first order in
the velocity fed to the model; for a deceleration independent of ``v`` it is exactly Verlet.

This loop serves any deceleration function, one array operation per step for all samples. The
effect laws' rollout (:func:`crashfuse.method.laws.simulate`), which the effect fits repeat
thousands of times on small batches, runs the same scheme compiled, one sample at a time, with the
same numbers (tests/test_diagnose.py checks them against this loop bit for bit).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from crashfuse.signals.domain import position_step, velocity_step
from crashfuse.errors import InputError


@dataclasses.dataclass(frozen=True)
class State:
    """What a deceleration function sees at one step (all arrays shape (m,)).

    Attributes
    ----------
    s : ndarray
        Displacement since contact in m.
    v : ndarray
        Velocity in m/s (at step 0 the impact speed; later the explicit prediction ``v - a dt``).
    u : ndarray
        Unloading coordinate ``s_max - s`` in m (>= 0; 0 on the loading branch's front).
    s_max : ndarray
        Maximum displacement reached so far in m.
    loading : ndarray of bool
        True where the sample is on the loading branch (use ``x = s``), False on unloading
        (use ``x = u``).
    step : int
        Step index ``i``; the time is ``i * dt``.
    time : float
        Time since contact in s.
    """

    s: np.ndarray
    v: np.ndarray
    u: np.ndarray
    s_max: np.ndarray
    loading: np.ndarray
    step: int
    time: float

    @property
    def x(self) -> np.ndarray:
        """Branch coordinate in m: ``s`` on loading, ``u`` on unloading, shape (m,)."""
        return np.where(self.loading, self.s, self.u)


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A rolled-out pulse for ``m`` samples over ``n = n_steps + 1`` time samples.

    Attributes
    ----------
    time : ndarray, shape (n,)
        Time since contact in s.
    s, v, decel : ndarray, shape (m, n)
        Displacement (m), velocity (m/s) and deceleration (m/s^2, positive slowing).
    branch : ndarray of int8, shape (m, n)
        0 loading, 1 unloading, 2 separated.
    s_max : ndarray, shape (m,)
        Maximum displacement (crush) of each sample in m.
    """

    time: np.ndarray
    s: np.ndarray
    v: np.ndarray
    decel: np.ndarray
    branch: np.ndarray
    s_max: np.ndarray

    LOADING = 0
    UNLOADING = 1
    SEPARATED = 2

    def on_branch(self, branch: str, sample: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where sample ``sample`` is on ``branch`` ('loading' | 'unloading'), and its coordinates there.

        Returns
        -------
        on : ndarray of bool, shape (n,)
        x : ndarray, shape (n_on,)
            Branch coordinate in m: ``s`` while loading, ``s_max - s`` while unloading.
        v : ndarray, shape (n_on,)
            Velocity in m/s.
        """
        loading = branch == "loading"
        on = self.branch[sample] == (self.LOADING if loading else self.UNLOADING)
        x = self.s[sample, on] if loading else self.s_max[sample] - self.s[sample, on]
        return on, x, self.v[sample, on]


DecelFn = Callable[[State], np.ndarray]


def rollout(decel_fn: DecelFn, v0, dt: float, n_steps: int, n_samples: int = 1) -> Trajectory:
    """Integrate ``m`` pulses at once with velocity Verlet, branch switching and separation.

    Parameters
    ----------
    decel_fn : callable
        ``decel_fn(state: State) -> ndarray, shape (m,)``: the deceleration (m/s^2, positive
        slowing) of every sample at ``state``. Called ``n_steps + 1`` times.
    v0 : float or array_like, shape (m,)
        Impact speed(s) in m/s (> 0).
    dt : float
        Time step in s (> 0).
    n_steps : int
        Number of steps; the trajectory has ``n_steps + 1`` samples, from t = 0.
    n_samples : int, optional
        Number of samples ``m`` when ``v0`` is a scalar.

    Returns
    -------
    Trajectory

    Raises
    ------
    InputError
        On a non-positive ``dt``, ``n_steps`` or speed, or if ``decel_fn`` returns non-finite
        values or the wrong shape.
    """
    v = _initial_speed(v0, n_samples)
    if not (np.isfinite(dt) and dt > 0) or int(n_steps) < 1:
        raise InputError(f"expected dt > 0 and n_steps >= 1, got dt={dt}, n_steps={n_steps}", field="dt")
    m, n = v.size, int(n_steps) + 1
    out_s, out_v, out_a = (np.empty((m, n)) for _ in range(3))
    out_unloading, out_separated = np.zeros((m, n), dtype=bool), np.zeros((m, n), dtype=bool)
    s = np.zeros(m)
    s_max = np.zeros(m)
    loading = np.ones(m, dtype=bool)
    separated = np.zeros(m, dtype=bool)
    a = _decel(decel_fn, State(s, v, s_max - s, s_max, loading, 0, 0.0), loading, separated, m)
    out_s[:, 0], out_v[:, 0], out_a[:, 0] = s, v, a
    for i in range(1, n):
        s_new = position_step(s, v, a, dt)
        # A sample stops loading at the first step its displacement does not advance (v ~ 0).
        loading = loading & (s_new > s_max)
        # While every sample loads (most steps of a batch) the branch bookkeeping is the identity: skipped.
        all_loading = loading.all()
        s_max = s_new if all_loading else np.where(loading, s_new, s_max)
        v_pred = v - a * dt
        state = State(s_new, v_pred, np.maximum(s_max - s_new, 0.0), s_max, loading, i, i * dt)
        a_new = _decel(decel_fn, state, loading, separated, m, all_loading)
        v = velocity_step(v, a, a_new, dt)
        s, a = s_new, a_new
        out_s[:, i], out_v[:, i], out_a[:, i] = s, v, a
        if not all_loading:
            separated |= ~loading & (a_new <= 0) & (v < 0)
            out_unloading[:, i], out_separated[:, i] = ~loading, separated
    out_b = np.where(out_separated, Trajectory.SEPARATED,  # the branch codes once, not per step
                     np.where(out_unloading, Trajectory.UNLOADING, Trajectory.LOADING)).astype(np.int8)
    return Trajectory(np.arange(n) * dt, out_s, out_v, out_a, out_b, s_max)


def _initial_speed(v0, n_samples: int) -> np.ndarray:
    v = np.asarray(v0, dtype=float)
    if v.ndim == 0:
        v = np.full(int(n_samples), float(v))
    if v.ndim != 1 or v.size < 1 or not np.all(np.isfinite(v) & (v > 0)):
        raise InputError(f"expected impact speed(s) > 0 m/s as a scalar or 1-D array, got {v0!r}", field="v0")
    return v.copy()


def _decel(decel_fn: DecelFn, state: State, loading, separated, m: int, all_loading: bool = False) -> np.ndarray:
    """The deceleration at ``state`` with the barrier's constraints applied, shape (m,) (none while
    ``all_loading``: no sample unloads or has separated)."""
    a = np.asarray(decel_fn(state), dtype=float)
    if a.shape != (m,):
        raise InputError(f"decel_fn must return shape ({m},), got {a.shape}", field="decel_fn")
    if not np.isfinite(a).all():
        raise InputError(f"decel_fn returned a non-finite deceleration at step {state.step}", field="decel_fn")
    if all_loading:
        return a
    # The barrier cannot pull: on unloading the deceleration is >= 0, and 0 after separation.
    a = np.where(loading, a, np.maximum(a, 0.0))
    return np.where(separated, 0.0, a)
