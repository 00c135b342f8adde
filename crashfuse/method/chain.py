"""The tests' measurement chain: an accelerometer mount resonance fitted between tests and their CAE runs.

A test's accelerometer sits on a structure (a seat crossmember, a sill) that rings when the pulse
steps: its record is the body's deceleration passed through the mount, a base-excited single degree
of freedom seat::

    H(s) = (2 zeta w s + w^2) / (s^2 + 2 zeta w s + w^2),   w = 2 pi f_res

A CAE model reads the node's deceleration, without the mount. The ringing is locked in time, not in
crush, so the bias model (which learns in the displacement domain) cannot carry it from a fast test
to a slow one; the chain is fitted here instead, in the time domain, on the training tests and
their companion CAE runs over the first :data:`CHAIN_WINDOW` after contact (where the pulse's step
excites the mount most and the unmodelled physics has acted least). A force the CAE lacks is not the
mount's: each test's body deceleration is taken as its CAE pulse times a gain plus a force stepping
on at contact (a rate effect scales the pulse, damping or a stiffer contact steps it up), both read
through the mount, their two coefficients by linear least squares inside the fit. The bias model
then learns the bias of each test's body deceleration - its record with the fitted mount taken out
(:meth:`MountResonance.body`) - and a rollout (the body's motion) is read through the mount at the end.

The family holds the identity in its limit (a stiff, heavily damped mount): a campaign whose tests
do not ring fits one at its bounds. That limit is not applied (:attr:`MountResonance.removes_nothing`):
it is not the identity at a pulse's onset (a prediction read through it, started at rest, dips at
contact and lags), and where the tests do not ring that is all it would add.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np
from scipy import optimize, signal

from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.signals.pulse import Pulse

CHAIN_WINDOW = 0.030  # s after contact: the mount rings at the pulse's onset
F_BOUNDS = (20.0, 2000.0)  # Hz, mount frequencies searched (the top: a mount stiffer than CFC 60 sees)
ZETA_BOUNDS = (0.02, 5.0)  # -, damping ratios searched
_STARTS = ((60.0, 0.1), (110.0, 0.1), (200.0, 0.1), (110.0, 0.5))  # (Hz, -): fixed, so fits repeat
# A fitted mount that removes less than this share of the tests' squared difference from their runs explains
# nothing: the identity's limit (0 on the noise controls; 0.08-0.97 wherever the worlds' mounts ring).
MIN_GAIN = 0.01


class MountResonance:
    """Accelerometer mount resonance ``H(s)`` fitted to pairs of test and CAE pulses.

    Parameters
    ----------
    window : float
        Seconds after contact the fit compares (default :data:`CHAIN_WINDOW`).

    Attributes
    ----------
    f_res_ : float
        Mount frequency in Hz.
    zeta_res_ : float
        Damping ratio.
    gain_ : float
        Fraction of the squared test-minus-CAE difference over the window that the chain removes
        (each pulse with its own gain and step in both), 0-1.
    n_tests_ : int
        Test pulses fitted on.
    """

    def __init__(self, window: float = CHAIN_WINDOW):
        self.window = window

    def fit(self, pairs):
        """Fit ``(f_res, zeta)`` by least squares over every pair's window.

        Parameters
        ----------
        pairs : sequence of (time, test, cae)
            Arrays of shape (n,) each, SI (s, m/s^2), from contact on, uniformly sampled; the test's
            deceleration and its companion CAE run's on the same times.

        Returns
        -------
        self
        """
        pairs = [_windowed(t, a, c, self.window) for t, a, c in pairs]
        if not pairs:
            raise InputError("the measurement chain needs at least one test with a companion CAE run",
                             field="chain")

        def residual(p):
            return np.concatenate([_unexplained(a, _filter(body, fs, *np.exp(p))) for fs, a, body in pairs])

        lo, hi = np.log([F_BOUNDS[0], ZETA_BOUNDS[0]]), np.log([F_BOUNDS[1], ZETA_BOUNDS[1]])
        fits = [optimize.least_squares(residual, np.log(start), bounds=(lo, hi)) for start in _STARTS]
        best = min(fits, key=lambda r: r.cost)
        self.f_res_, self.zeta_res_ = (float(v) for v in np.exp(best.x))
        plain = np.concatenate([_unexplained(a, body) for _, a, body in pairs])
        self.gain_ = float(max(0.0, 1.0 - 2 * best.cost / max(plain @ plain, np.finfo(float).tiny)))
        self.n_tests_ = len(pairs)
        return self

    @property
    def removes_nothing(self) -> bool:
        """Whether the fitted mount removes less than :data:`MIN_GAIN` of the tests' difference from their runs."""
        return self.gain_ < MIN_GAIN

    def apply(self, time, decel):
        """Read decelerations through the fitted mount.

        Parameters
        ----------
        time : ndarray, shape (n,)
            Seconds from contact, uniform; the motion is at rest before it.
        decel : ndarray, shape (n,) or (m, n)
            m/s^2.

        Returns
        -------
        ndarray, the shape of ``decel``
        """
        return _filter(np.asarray(decel, float), 1.0 / (time[1] - time[0]), self.f_res_, self.zeta_res_)

    def body(self, time, decel):
        """The body deceleration the fitted mount reads as ``decel``: :meth:`apply` inverted.

        The digital mount has a zero at the Nyquist frequency (the bilinear transform's), which the
        inverse would turn into an undamped pole; it is inverted without it, so that reading the
        result through the mount gives ``decel`` back averaged over two samples (0.3 % at 300 Hz
        and 12.5 kHz). Shapes and units as :meth:`apply`.
        """
        b, a = _coefficients(1.0 / (time[1] - time[0]), self.f_res_, self.zeta_res_)
        rest, _ = np.polydiv(b, [1.0, 1.0])  # b = (1 + z^-1) rest: the Nyquist zero taken out
        decel = np.asarray(decel, float)
        # A record starts at contact already off zero (its filter's lead-in): the inverse starts in
        # its steady state there, not with a step, which it would turn into a spike.
        zi = signal.lfilter_zi(a, 2.0 * rest) * decel[..., :1]
        return signal.lfilter(a, 2.0 * rest, decel, axis=-1, zi=zi)[0]


def body_campaign(campaign: Campaign, chain: MountResonance, tests) -> Campaign:
    """``campaign`` with the pulses of ``tests`` replaced by their body decelerations (:meth:`MountResonance.body`)."""
    pulses = _Overlay(campaign.pulses, {t: _body_pulse(campaign.pulses[t], chain) for t in tests})
    return dataclasses.replace(campaign, pulses=pulses, source=None, known_hash=None)


def _body_pulse(pulse: Pulse, chain: MountResonance) -> Pulse:
    return dataclasses.replace(pulse, decel=chain.body(pulse.time, pulse.decel))


class _Overlay(Mapping):
    """A campaign's pulses with some replaced, the others read from the original on use."""

    def __init__(self, base: Mapping, replaced: dict):
        self._base, self._replaced = base, replaced

    def __getitem__(self, run_id: str) -> Pulse:
        return self._replaced[run_id] if run_id in self._replaced else self._base[run_id]

    def __iter__(self):
        return iter(self._base)

    def __len__(self) -> int:
        return len(self._base)


def _coefficients(fs: float, f_res: float, zeta: float):
    """``H(s)`` by the bilinear transform ``s = 2 fs (1 - 1/z) / (1 + 1/z)`` at ``fs`` Hz: ``(b, a)``
    for ``lfilter``, written out for the second order (``signal.bilinear`` multiplies polynomial
    objects: 4 ms a call, most of a fit's time)."""
    w = 2 * np.pi * f_res
    k, c, w2 = 2.0 * fs, 2.0 * zeta * w, w * w
    d0 = k * k + c * k + w2
    return (np.array([c * k + w2, 2.0 * w2, w2 - c * k]) / d0,
            np.array([d0, 2.0 * (w2 - k * k), k * k - c * k + w2]) / d0)


def _filter(x, fs: float, f_res: float, zeta: float):
    """``H(s)`` along the last axis, at rest before the first sample."""
    return signal.lfilter(*_coefficients(fs, f_res, zeta), x, axis=-1)


def _windowed(t, a, c, window: float):
    n = min(len(t), len(a), len(c))
    t, a, c = (np.asarray(x[:n], float) for x in (t, a, c))
    keep = t <= t[0] + window  # the filter is causal: the window's samples need nothing after it
    return 1.0 / (t[1] - t[0]), a[keep], np.vstack([c[keep], np.ones(keep.sum())])


def _unexplained(a, basis):
    """What of ``a`` the rows of ``basis`` (the CAE pulse and a step, read through the mount) leave by
    linear least squares."""
    coef, *_ = np.linalg.lstsq(basis.T, a, rcond=None)
    return a - basis.T @ coef
