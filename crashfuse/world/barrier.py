"""A CAE-style single-mass model of a rigid-barrier test, built from the test's own barrier force.

A CAE model of a full-frontal test reduced to its simplest form is one rigid mass ``M`` on a
crush spring: ``M dv/dt = -F``, with the force a function of the crush alone, ``F_load(s)`` while
the crush grows and ``F_unload(u)`` (``u = s_max - s``) once it springs back. A load-cell barrier
measures ``F`` directly, and the vehicle's own accelerometers give its crush ``s(t)``, so both
curves can be read off a single test:

* ``F(t)``: the sum of the barrier's load-cell X forces (:func:`crashfuse.io.nhtsa.read_barrier_force`),
  CFC 60 over the full record, as the campaign reader filters the vehicle pulse;
* ``s(t)``: the crush integrated from the vehicle pulse (rear-seat crossmember, CFC 60) by
  :func:`crashfuse.signals.domain.displacement_branches`, the integrator of the method itself;
* the loading curve is ``F`` at the loading-branch samples against ``s``; the unloading curve
  is ``F`` at the unloading-branch samples against ``u``, cut where the force first reaches zero
  (the vehicle leaves the barrier);
* ``M`` is the test weight of the EV5 header (VEHICLE VEHTWT), checked against the impulse
  mass ``int_0^t_stop F dt / v0`` (the momentum the barrier took to stop the vehicle).

Rolled out from the test's impact speed with :func:`crashfuse.signals.dynamics.rollout` this gives the
pulse a perfect single-mass CAE model would give. Where the vehicle is not one rigid mass (the
powertrain and the crushed front end stop before the rear body does) ``F / M`` differs from the
crossmember deceleration; :func:`momentum_lag` measures by how much. See docs/barrier-model.md.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from crashfuse.signals.domain import displacement_branches
from crashfuse.signals.dynamics import State, Trajectory, rollout
from crashfuse.errors import InputError
from crashfuse.signals.filters import cfc_filter
from crashfuse.io.campaign import Campaign
from crashfuse.io.campaign_write import write_campaign
from crashfuse.io.checks import prepare_pulse
from crashfuse.io.nhtsa import read_barrier_force, read_header, read_nhtsa
from crashfuse.signals.iso18571 import iso_score
from crashfuse.signals.metrics import pulse_metrics
from crashfuse.signals.pulse import Pulse

CFC = 60  # the class of campaign pulses: force and vehicle pulse are filtered alike
ISO_WINDOWS_MS = ((0, 20), (0, 40), (0, 60))
MODEL_SUFFIX = "_single_mass"


@dataclasses.dataclass(frozen=True)
class SingleMassModel:
    """One rigid mass on a crush spring with a loading and an unloading force curve.

    Attributes
    ----------
    mass : float
        M in kg.
    loading_s : ndarray, shape (k,)
        Crush in m, strictly increasing from about 0 to the measured maximum crush.
    loading_force : ndarray, shape (k,)
        Barrier force in N at ``loading_s``; beyond the last point it keeps its last value.
    unloading_u : ndarray, shape (j,)
        Spring-back ``u = s_max - s`` in m, strictly increasing from 0.
    unloading_force : ndarray, shape (j,)
        Barrier force in N at ``unloading_u``, ending at 0 (separation); 0 beyond.
    """

    mass: float
    loading_s: np.ndarray
    loading_force: np.ndarray
    unloading_u: np.ndarray
    unloading_force: np.ndarray

    def decel(self, state: State) -> np.ndarray:
        """Deceleration ``F / M`` in m/s^2 at a rollout state, shape (m,)."""
        load = np.interp(state.s, self.loading_s, self.loading_force)
        unload = np.interp(state.u, self.unloading_u, self.unloading_force, right=0.0)
        return np.where(state.loading, load, unload) / self.mass

    def rollout(self, v0: float, dt: float, n_steps: int) -> Trajectory:
        """The model's crash from impact speed ``v0`` (m/s), ``n_steps`` steps of ``dt`` (s)."""
        return rollout(self.decel, v0, dt, n_steps)


def fit_single_mass(time, force, pulse: Pulse, mass: float) -> SingleMassModel:
    """Loading and unloading force-crush curves from a barrier force and the vehicle pulse.

    Parameters
    ----------
    time : array_like, shape (n,)
        Times of the force samples in s (t = 0 at first contact), strictly increasing.
    force : array_like, shape (n,)
        Barrier force on the vehicle in N, positive while pushing it back, filtered as ``pulse``.
    pulse : Pulse
        Vehicle pulse (deceleration in m/s^2); its crush comes from
        :func:`crashfuse.signals.domain.displacement_branches`.
    mass : float
        M in kg.

    Returns
    -------
    SingleMassModel

    Raises
    ------
    InputError
        A non-positive mass, a force record that does not cover the pulse's contact phase, or a
        vehicle that never stops within the record (no maximum crush, no unloading curve).
    """
    if not (np.isfinite(mass) and mass > 0):
        raise InputError(f"expected a mass > 0 kg, got {mass}", pulse.where, "mass")
    branches = displacement_branches(pulse)
    if not branches.stopped:
        raise InputError("the vehicle does not reach zero velocity within the record: no maximum crush, so no "
                         "unloading curve", pulse.where, "decel")
    at = _force_at(time, force, pulse)
    u, f_u = branches.unloading.x, at(branches.unloading.time)
    released = np.flatnonzero(f_u <= 0)
    if released.size:  # the vehicle leaves the barrier: the curve ends at zero force
        u, f_u = u[: released[0] + 1], np.r_[f_u[: released[0]], 0.0]
    loading = branches.loading
    return SingleMassModel(float(mass), loading.x, at(loading.time), u, f_u)


def _force_at(time, force, pulse: Pulse):
    """Interpolator of the force at pulse times; InputError if the force does not cover them."""
    t, f = np.asarray(time, dtype=float), np.asarray(force, dtype=float)
    if t.ndim != 1 or t.shape != f.shape or t.size < 2 or not np.all(np.diff(t) > 0):
        raise InputError(f"expected force times and values of equal shape, times increasing; got {t.shape} and "
                         f"{f.shape}", field="force")
    if not np.isfinite(f).all():
        raise InputError("expected finite barrier forces", field="force")
    p = pulse.after_contact()
    slack = 0.5 * p.dt
    if t[0] > p.time[0] + slack or t[-1] < p.time[-1] - slack:
        raise InputError(f"the barrier force covers {t[0]:.6g} to {t[-1]:.6g} s, the vehicle pulse "
                         f"{p.time[0]:.6g} to {p.time[-1]:.6g} s: expected the force to cover the pulse",
                         pulse.where, "force")
    return lambda at: np.interp(at, t, f)


def impulse_mass(time, force, pulse: Pulse) -> float:
    """The mass the barrier impulse implies: ``int_0^t_stop F dt / v0`` in kg.

    Until the vehicle pulse reaches zero velocity (``t_stop``) the barrier has taken all the
    vehicle's momentum ``M v0`` if the vehicle is one mass and both instruments agree.
    """
    branches = displacement_branches(pulse)
    if not branches.stopped:
        raise InputError("the vehicle does not reach zero velocity within the record", pulse.where, "decel")
    t, f = np.asarray(time, dtype=float), np.asarray(force, dtype=float)
    inside = (t >= 0) & (t < branches.t_stop)
    tt = np.r_[t[inside], branches.t_stop]
    ff = np.r_[f[inside], np.interp(branches.t_stop, t, f)]
    return float(np.trapezoid(ff, tt) / pulse.v0)


def momentum_lag(time, force, pulse: Pulse, mass: float) -> np.ndarray:
    """``int_0^t (F - M a) dt`` in N s at the pulse's times after contact, shape (n,).

    The momentum the barrier has taken beyond what a rigid mass ``M`` moving with the
    accelerometers would have lost: ``sum_i m_i (v_body - v_i)``, the momentum of parts that
    move slower than the rear body (a powertrain or crushed front end already stopped on the
    barrier). Zero throughout for a true single mass; back to zero once every part moves
    together again, up to the two instruments' calibration difference.
    """
    p = pulse.after_contact()
    excess = _force_at(time, force, pulse)(p.time) - mass * p.decel
    return np.r_[0.0, np.cumsum(0.5 * (excess[1:] + excess[:-1]) * np.diff(p.time))]


def model_pulse(model: SingleMassModel, pulse: Pulse) -> Pulse:
    """The model's pulse from the test's impact speed, on the test's time grid after contact.

    Returns
    -------
    Pulse
        ``source='cae'``, same ``v0`` and axle masses as ``pulse``, ``meta['cfc'] = CFC`` (the
        force curves carry that class), run_id ``<test run_id>_single_mass``.
    """
    p = pulse.after_contact()
    traj = model.rollout(p.v0, p.dt, p.time.size - 1)
    meta = {k: pulse.meta[k] for k in ("powertrain", "drive") if k in pulse.meta}
    return Pulse(traj.time, traj.decel[0], p.v0, p.front_weight, p.rear_weight,
                 run_id=f"{pulse.run_id}{MODEL_SUFFIX}", source="cae", meta={**meta, "cfc": CFC})


# --- an NHTSA EV5 test ------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BarrierModel:
    """The single-mass model of one load-cell barrier test, with what it was built from.

    Attributes
    ----------
    test : Pulse
        The measured vehicle pulse at CFC 60 from contact on, as a campaign reads it.
    cae : Pulse
        The single-mass model's pulse (``source='cae'``), same grid, ``v0`` and masses.
    model : SingleMassModel
        Its force curves and mass (the header's test weight VEHTWT).
    impulse_mass : float
        ``int_0^t_stop F dt / v0`` in kg.
    time, force : ndarray, shape (n,)
        The barrier force (N, CFC 60) over the full record (s), pre-impact samples included.
    """

    test: Pulse
    cae: Pulse
    model: SingleMassModel
    impulse_mass: float
    time: np.ndarray
    force: np.ndarray


def barrier_model(ev5_dir: str | os.PathLike, powertrain: str = "unknown", drive: str = "unknown") -> BarrierModel:
    """Build the single-mass model of an NHTSA load-cell barrier test.

    Parameters
    ----------
    ev5_dir : path-like
        NHTSA EV5 test folder with the vehicle's rear-floor X accelerometers and the barrier's
        load-cell Fx channels (object 0, LC, X, newtons).
    powertrain, drive : str
        Labels written into both runs' ``meta`` (the EV5 reader does not decode them).

    Returns
    -------
    BarrierModel

    Raises
    ------
    InputError
        Naming the file and field: a folder without barrier load cells, a bad header or channel.
    """
    header = read_header(ev5_dir)
    time, raw_force = read_barrier_force(ev5_dir)
    try:
        force = cfc_filter(raw_force, float((time[-1] - time[0]) / (time.size - 1)), CFC)
    except InputError as err:
        raise err.at(header.path) from None
    raw = read_nhtsa(ev5_dir)
    test = prepare_pulse(raw.replace(meta={**raw.meta, "powertrain": powertrain, "drive": drive}), CFC)
    mass = header.vehicle["test_weight_kg"]  # VEHTWT: the vehicle as tested, dummies and ballast included
    model = fit_single_mass(time, force, test, mass)
    return BarrierModel(test, model_pulse(model, test), model, impulse_mass(time, force, test), time, force)


def compare(result: BarrierModel) -> dict:
    """The single-mass pulse against the measured one, in report units.

    Returns
    -------
    dict
        ``test``, ``cae_run_id``; ``mass_kg`` (``test_weight_vehtwt``, ``impulse``, their
        ``ratio`` impulse / test weight); ``iso`` (window label ``"0-20"`` ... -> the ISO/TS
        18571 scores of the single-mass pulse against the measured one); ``measured`` and
        ``single_mass`` (:func:`crashfuse.signals.metrics.pulse_metrics` of each, g, ms, mm, km/h);
        ``momentum_lag`` (peak and end of :func:`momentum_lag`, N s, and the peak's time, ms);
        ``energy_kJ``: the kinetic energy ``M v0^2 / 2`` against the work of the barrier force
        along the measured crush to its maximum (equal for one rigid mass), and their ratio.
    """
    test, cae = result.test, result.cae
    iso = {f"{a}-{b}": iso_score(test.time, test.decel, cae.time, cae.decel, a * 1e-3, b * 1e-3)
           for a, b in ISO_WINDOWS_MS}
    lag = momentum_lag(result.time, result.force, test, result.model.mass)
    i = int(np.argmax(lag))
    model = result.model
    mass = model.mass
    kinetic = 0.5 * mass * test.v0**2
    work = float(np.trapezoid(model.loading_force, model.loading_s))
    return {
        "test": test.run_id,
        "cae_run_id": cae.run_id,
        "mass_kg": {"test_weight_vehtwt": mass, "impulse": result.impulse_mass, "ratio": result.impulse_mass / mass},
        "iso": iso,
        "measured": pulse_metrics(test),
        "single_mass": pulse_metrics(cae),
        "momentum_lag": {"peak_Ns": float(lag[i]), "t_peak_ms": float(test.after_contact().time[i] * 1e3),
                         "end_Ns": float(lag[-1])},
        "energy_kJ": {"kinetic": kinetic * 1e-3, "barrier_work": work * 1e-3, "ratio": work / kinetic},
    }


def barrier_campaign(ev5_dir: str | os.PathLike, out: str | os.PathLike, powertrain: str = "unknown",
                     drive: str = "unknown", overwrite: bool = False) -> tuple[Path, dict]:
    """Write a campaign of the test and its single-mass model as the test's companion CAE run.

    The test row points at ``ev5_dir`` through ``pulse_path`` (relative to ``out``; the data are
    not copied) and names the model run in ``cae_run_id``; the model's pulse is written to
    ``pulses/<test>_single_mass.csv`` at CFC 60 on the test's time grid.

    Returns
    -------
    folder : Path
        The written campaign.
    comparison : dict
        :func:`compare` of the two.
    """
    result = barrier_model(ev5_dir, powertrain, drive)
    out = Path(out)
    link = os.path.relpath(os.path.abspath(ev5_dir), os.path.abspath(out))
    test = result.test.replace(meta={**result.test.meta, "cae_run_id": result.cae.run_id, "pulse_path": link})
    folder = write_campaign(Campaign.from_pulses([test, result.cae]), out, speed_unit="kmh", mass_unit="kg",
                            overwrite=overwrite)
    return folder, compare(result)
