"""The crash pulse: one vehicle deceleration history with its impact condition.

Sign convention: ``decel`` is positive while the vehicle slows (the negative of the
forward X acceleration an accelerometer reports in SAE J211 axes). ``time`` is in seconds
with t = 0 at first contact; samples are uniform and strictly increasing.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from crashfuse.errors import InputError
from crashfuse.units import G0

MIN_SAMPLES = 16
# A full-frontal pulse beyond 500 g or a speed beyond 100 m/s means the units are wrong.
MAX_DECEL = 500 * G0
MAX_SPEED = 100.0
SOURCES = ("test", "cae")


def check_samples(time, decel, where: str | os.PathLike | None = None,
                  fields: tuple[str, str] = ("time", "decel")) -> None:
    """Check the samples of a pulse: enough, finite, uniform and increasing in time, plausible in size.

    Parameters
    ----------
    time : ndarray, shape (n,)
        Sample times in s.
    decel : ndarray, shape (n,)
        Deceleration in m/s^2.
    where : str or path-like, optional
        The file the samples came from, named in the error.
    fields : (str, str)
        Names of the time and deceleration fields in that file (e.g. CSV columns), named in the error.

    Raises
    ------
    InputError
        Naming ``where`` and the field at fault. Samples are counted from 1, as the data rows of a CSV.
    """
    t, a = np.asarray(time, dtype=float), np.asarray(decel, dtype=float)
    time_field, decel_field = fields
    if t.ndim != 1 or a.ndim != 1 or t.shape != a.shape:
        raise InputError(f"expected two 1-D arrays of equal length, got shapes {t.shape} and {a.shape}", where,
                         f"{time_field}/{decel_field}")
    if t.size < MIN_SAMPLES:
        raise InputError(f"expected at least {MIN_SAMPLES} samples, got {t.size}", where, time_field)
    for name, arr in ((time_field, t), (decel_field, a)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise InputError(f"expected finite numbers, found {arr[bad[0]]} at sample {bad[0] + 1}", where, name)
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.flatnonzero(dt <= 0)[0])
        raise InputError(f"expected strictly increasing time, but sample {i + 2} ({t[i + 1]:.6g} s) does not follow "
                         f"sample {i + 1} ({t[i]:.6g} s)", where, time_field)
    if np.ptp(dt) > 1e-3 * dt.mean() + 1e-12:
        raise InputError(f"expected uniform sampling, step varies from {dt.min():.6g} to {dt.max():.6g} s", where,
                         time_field)
    peak = np.abs(a).max()
    if peak > MAX_DECEL:
        raise InputError(f"peak {peak / G0:.0f} g exceeds {MAX_DECEL / G0:.0f} g: wrong units?", where, decel_field)


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
        check_samples(t, a, self.where)
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
