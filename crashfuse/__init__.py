"""crashfuse: correct the bias of a crash CAE model with physical crash tests.

Conventions, written down once (see also the README):

* SI inside the package: seconds, metres, m/s, m/s^2, kilograms, newtons.
  mph, km/h, lb, g and ms appear only at I/O and report boundaries (:mod:`crashfuse.units`).
* Deceleration is positive while the vehicle slows down. Displacement ``s`` is the
  vehicle's forward travel since first contact (t = 0), so crush grows positive.
* "Weights" front/rear are axle masses in kilograms (the paper's w_f, w_r).
"""

from crashfuse.errors import InputError

__all__ = ["InputError", "Pulse"]
__version__ = "0.1.0"


def __getattr__(name):
    # Pulse on first use: a `crashfuse` command handed to the fork server never imports numpy.
    if name == "Pulse":
        from crashfuse.signals.pulse import Pulse

        return Pulse
    raise AttributeError(f"module 'crashfuse' has no attribute {name!r}")
