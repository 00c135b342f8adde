"""The crash pulse: one vehicle deceleration history with its impact condition.

Sign convention: ``decel`` is positive while the vehicle slows (the negative of the
forward X acceleration an accelerometer reports in SAE J211 axes). ``time`` is in seconds
with t = 0 at first contact; samples are uniform and strictly increasing.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from crashfuse.errors import InputError
from crashfuse.units import G0

MIN_SAMPLES = 16
# A full-frontal pulse beyond 500 g or a speed beyond 100 m/s means the units are wrong.
MAX_DECEL = 500 * G0
MAX_SPEED = 100.0
SOURCES = ("test", "cae")


@dataclasses.dataclass(frozen=True, eq=False)
class Pulse:
    """A vehicle crash pulse in SI units.

    Parameters
    ----------
    time : ndarray, shape (n,)
        Sample times in s, uniform and strictly increasing; t = 0 at first contact.
    decel : ndarray, shape (n,)
        Vehicle deceleration in m/s^2, positive while slowing down.
    v0 : float
        Impact speed in m/s (> 0).
    front_weight, rear_weight : float
        Front and rear axle masses in kg (> 0).
    run_id : str
        Identifier of the run within its campaign.
    source : {"test", "cae"}
        Physical test or CAE simulation.
    meta : dict
        Anything else the file carried (powertrain, drive, cae_run_id, provenance ...).
    where : str, optional
        File the pulse came from, used only to locate validation errors.
    """

    time: np.ndarray
    decel: np.ndarray
    v0: float
    front_weight: float
    rear_weight: float
    run_id: str = "run"
    source: str = "test"
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    where: str | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self):
        t = np.asarray(self.time, dtype=float)
        a = np.asarray(self.decel, dtype=float)
        object.__setattr__(self, "time", t)
        object.__setattr__(self, "decel", a)
        self._validate(t, a)

    def _fail(self, field: str, message: str):
        raise InputError(message, self.where, field)

    def _validate(self, t: np.ndarray, a: np.ndarray) -> None:
        if t.ndim != 1 or a.ndim != 1 or t.shape != a.shape:
            self._fail("time/decel", f"expected two 1-D arrays of equal length, got shapes {t.shape} and {a.shape}")
        if t.size < MIN_SAMPLES:
            self._fail("time", f"expected at least {MIN_SAMPLES} samples, got {t.size}")
        for name, arr in (("time", t), ("decel", a)):
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                self._fail(name, f"expected finite numbers, found {arr[bad[0]]} at sample {bad[0]}")
        dt = np.diff(t)
        if np.any(dt <= 0):
            i = int(np.flatnonzero(dt <= 0)[0])
            self._fail("time", f"expected strictly increasing time, but t[{i + 1}]={t[i + 1]} <= t[{i}]={t[i]}")
        if np.ptp(dt) > 1e-3 * dt.mean() + 1e-12:
            self._fail("time", f"expected uniform sampling, step varies from {dt.min():.6g} to {dt.max():.6g} s")
        if np.abs(a).max() > MAX_DECEL:
            self._fail("decel", f"peak {np.abs(a).max() / G0:.0f} g exceeds {MAX_DECEL / G0:.0f} g: wrong units?")
        if not (0 < self.v0 <= MAX_SPEED) or not np.isfinite(self.v0):
            self._fail("v0", f"expected an impact speed in (0, {MAX_SPEED}] m/s, got {self.v0}")
        for name in ("front_weight", "rear_weight"):
            w = getattr(self, name)
            if not (np.isfinite(w) and 0 < w < 1e5):
                self._fail(name, f"expected an axle mass in kg in (0, 100000), got {w}")
        if self.source not in SOURCES:
            self._fail("source", f"expected one of {SOURCES}, got {self.source!r}")

    @property
    def dt(self) -> float:
        """Sampling interval in s."""
        return float((self.time[-1] - self.time[0]) / (self.time.size - 1))

    @property
    def mass(self) -> float:
        """Total vehicle mass in kg."""
        return self.front_weight + self.rear_weight

    def replace(self, **changes) -> "Pulse":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def after_contact(self) -> "Pulse":
        """The samples from first contact (t >= 0) on, as the kinematics need them.

        Readers keep pre-impact samples so that filters have lead-in data; crop after filtering.
        """
        keep = self.time >= -0.5 * self.dt
        return self if keep.all() else self.replace(time=self.time[keep], decel=self.decel[keep])
