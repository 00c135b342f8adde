"""SAE J211-1 channel frequency class (CFC) filters.

The filter is the one SAE J211-1 (Appendix C) and ISO 6487 (Annex A) prescribe: a 2-pole
Butterworth low-pass, designed digitally by the bilinear transform with the pre-warped design
frequency 2.0775 * CFC Hz, run forward and then backward over the record. The two passes cancel
the phase lag and give a 4-pole, zero-phase response whose gain is about -0.45 dB at F_H = CFC Hz
and -3 dB near 1.65 * CFC Hz.

End handling: before the passes the record is extended at both ends by an odd (point)
reflection about its end samples, ``2 x[0] - x[k:0:-1]``, and each pass starts from the filter's
steady state for the first sample. This is the "mirroring" ISO 6487 recommends and commercial
J211 implementations use: it keeps the value and slope continuous at the ends, so a record that
starts or ends mid-pulse does not ring as it would with zero padding or a cold start. The
extension is one period of F_H (``fs / CFC`` samples), by which time the 2-pole impulse response
has decayed to about 1e-4 of its peak. The padding is cropped again, so the output has the
input's length. Raw crash records carry pre-impact samples: filter the full record and crop at
t = 0 afterwards (:meth:`crashfuse.signals.pulse.Pulse.after_contact`).
"""

from __future__ import annotations

import math

import numpy as np

from crashfuse.errors import InputError
from crashfuse.signals.pulse import Pulse

CFC_CLASSES = (60, 180, 600, 1000)
# SAE J211-1 Appendix C: design frequency of each 2-pole pass, in multiples of the class number.
DESIGN_FACTOR = 2.0775
# Lowest sampling rate accepted, in multiples of the class: SAE J211-1 recommends at least 10 x F_H
# where only simple reconstruction is used, and ISO 6487 filter implementations ask the same.
MIN_RATE_FACTOR = 10.0


def j211_coefficients(cfc: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of one 2-pole pass as written in SAE J211-1 Appendix C.

    Parameters
    ----------
    cfc : {60, 180, 600, 1000}
        Channel frequency class.
    dt : float
        Sampling interval in s.

    Returns
    -------
    b : ndarray, shape (3,)
        Numerator (a0, a1, a2 in J211's naming).
    a : ndarray, shape (3,)
        Denominator ``[1, -b1, -b2]`` in J211's naming, i.e. scipy's ``lfilter`` convention for
        ``Y[t] = a0 X[t] + a1 X[t-1] + a2 X[t-2] + b1 Y[t-1] + b2 Y[t-2]``.
    """
    cfc, dt = _check_class_and_rate(cfc, dt)
    wd = 2.0 * math.pi * cfc * DESIGN_FACTOR
    wa = math.tan(wd * dt / 2.0)
    den = 1.0 + math.sqrt(2.0) * wa + wa * wa
    a0 = wa * wa / den
    b1 = -2.0 * (wa * wa - 1.0) / den
    b2 = (-1.0 + math.sqrt(2.0) * wa - wa * wa) / den
    return np.array([a0, 2.0 * a0, a0]), np.array([1.0, -b1, -b2])


def cfc_filter(x, dt: float, cfc: int, axis: int = -1) -> np.ndarray:
    """Filter one or many signals with SAE J211-1 CFC ``cfc`` (zero phase, 4-pole overall).

    Parameters
    ----------
    x : array_like, shape (..., n, ...)
        Signals sampled every ``dt`` along ``axis``; any units, any other axes.
    dt : float
        Sampling interval in s (uniform).
    cfc : {60, 180, 600, 1000}
        Channel frequency class.
    axis : int, default -1
        Time axis of ``x``.

    Returns
    -------
    ndarray, same shape as ``x``
        The filtered signals (float).

    Raises
    ------
    InputError
        Unknown class, sampling slower than 10 x CFC, fewer than 2 samples or non-finite values.
    """
    b, a = j211_coefficients(cfc, dt)
    x = np.asarray(x, dtype=float)
    n = x.shape[axis] if x.ndim else 0
    if n < 2:
        raise InputError(f"expected at least 2 samples along axis {axis}, got {n}", field="decel")
    if not np.isfinite(x).all():
        raise InputError("expected finite samples to filter, found NaN or infinity", field="decel")
    from scipy import signal  # ~1 s to import: only jobs that filter raw records pay it

    pad = min(n - 1, math.ceil(1.0 / (cfc * dt)))
    return signal.filtfilt(b, a, x, axis=axis, padtype="odd", padlen=pad)


def filtered_noise(rng, shape, dt: float, cfc: int, std: float = 1.0, pad: int = 2000) -> np.ndarray:
    """White noise of ``std`` (before the filter) filtered at CFC ``cfc`` along the last axis, ``shape`` samples at
    ``dt`` s; drawn ``pad`` samples longer at each end and cut, so that no filter transient reaches the samples
    kept (a test's noise runs before and after its record)."""
    shape = (shape,) if np.isscalar(shape) else tuple(shape)
    noise = rng.normal(0.0, std, shape[:-1] + (shape[-1] + 2 * pad,))
    return cfc_filter(noise, dt, cfc)[..., pad:-pad]


def filter_pulse(pulse: Pulse, cfc: int) -> Pulse:
    """The pulse at CFC ``cfc``, never filtering twice.

    ``pulse.meta['cfc']`` records the class the decel already carries: None (absent) means raw,
    so it is filtered and the class recorded. A pulse already at an equal or heavier class
    (meta cfc <= ``cfc``) is returned unchanged. A lighter class (e.g. CFC 180 data asked for
    at CFC 60) is filtered down to ``cfc``.

    Parameters
    ----------
    pulse : Pulse
        Full record; keep the pre-impact samples so the filter has lead-in data.
    cfc : {60, 180, 600, 1000}
        Requested channel frequency class.

    Returns
    -------
    Pulse
        Same times; ``decel`` filtered; ``meta['cfc'] == cfc`` unless returned unchanged.
    """
    try:
        _check_class(cfc)
        have = _meta_cfc(pulse)
        if have is not None and have <= cfc:
            return pulse
        decel = cfc_filter(pulse.decel, pulse.dt, cfc)
    except InputError as err:
        raise err.at(pulse.where) from None
    return pulse.replace(decel=decel, meta={**pulse.meta, "cfc": cfc})


def _meta_cfc(pulse: Pulse) -> float | None:
    """The class recorded in ``pulse.meta['cfc']`` (None: raw)."""
    have = pulse.meta.get("cfc")
    if have is None:
        return None
    try:
        return float(have)
    except (TypeError, ValueError):
        raise InputError(f"expected a numeric channel frequency class or none, got {have!r}", field="cfc") from None


def _check_class(cfc) -> int:
    """The class as an int, if it is one SAE J211-1 defines a filter for."""
    if cfc not in CFC_CLASSES:
        raise InputError(f"expected a channel frequency class in {CFC_CLASSES}, got {cfc!r}", field="cfc")
    return int(cfc)


def _check_class_and_rate(cfc, dt) -> tuple[int, float]:
    """Validate the class and the sampling interval; return them as (int, float)."""
    cfc = _check_class(cfc)
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise InputError(f"expected a positive sampling interval in s, got {dt}", field="time")
    if 1.0 / dt < MIN_RATE_FACTOR * cfc * (1 - 1e-9):
        raise InputError(
            f"sampling at {1.0 / dt:.6g} Hz is too slow for CFC {cfc}: expected at least "
            f"{MIN_RATE_FACTOR * cfc:.6g} Hz ({MIN_RATE_FACTOR:g} x CFC)", field="time")
    return cfc, dt
