"""Physical plausibility of a read pulse: filtered, cropped at first contact, a sane velocity change."""

from __future__ import annotations

import numpy as np

from crashfuse.errors import InputError
from crashfuse.signals.pulse import Pulse

# Restitution cannot exceed 1, so the velocity change of a pulse is at most 2 v0; the slack
# absorbs noise of raw records. A decel_g column holding m/s^2 integrates to ~10 v0.
MAX_DELTA_V_RATIO = 2.2


def prepare_pulse(pulse: Pulse, cfc: int | None) -> Pulse:
    """Filter a raw pulse and crop it at first contact if ``cfc`` is given; check it is physically plausible.

    With ``cfc`` None the record is returned whole, pre-impact samples included, because whoever
    filters it later (e.g. `crashfuse.signals.metrics.pulse_metrics`) needs them as lead-in.
    """
    if cfc is not None:
        from crashfuse.signals.filters import filter_pulse  # filters only raw or lighter-class pulses

        pulse = filter_pulse(pulse, cfc).after_contact()
    if pulse.time[0] > 0.5 * pulse.dt:
        raise InputError(f"expected t = 0 at first contact, but the pulse starts at {pulse.time[0] * 1e3:.6g} ms",
                         pulse.where, "time_s")
    _check_delta_v(pulse)
    return pulse


def _check_delta_v(pulse: Pulse) -> None:
    """Velocity change must be positive and at most ~2 v0: catches flipped signs and wrong units."""
    dv = float(np.trapezoid(pulse.decel, pulse.time))
    if dv <= 0:
        raise InputError(f"expected deceleration positive while slowing, but the pulse integrates to a velocity "
                         f"change of {dv:.3g} m/s: sign flipped?", pulse.where, "decel")
    if dv > MAX_DELTA_V_RATIO * pulse.v0:
        raise InputError(f"the pulse integrates to a velocity change of {dv:.3g} m/s, more than "
                         f"{MAX_DELTA_V_RATIO} x the impact speed {pulse.v0:.3g} m/s: wrong units (m/s^2 in a "
                         f"_g column?) or wrong speed?", pulse.where, "decel")

