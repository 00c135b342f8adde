"""Channel handling shared by the test-data readers (NHTSA EV5, ISO-MME)."""

from __future__ import annotations

import numpy as np

from crashfuse.errors import InputError


def combine_x_channels(channels: list[tuple[np.ndarray, np.ndarray]], names: list[str], warnings: list[str]):
    """Vehicle deceleration from X accelerations: per-channel offset removed, mean, sign flipped.

    Parameters
    ----------
    channels : list of (time, accel)
        time in s (uniform, same step for all channels), accel in m/s^2, X positive forward.
    names : list of str
        Channel names used in warnings.
    warnings : list of str
        Appended to: channels without pre-impact samples, record cut to the common span.

    Returns
    -------
    time : ndarray, shape (n,)
        s, the span common to all channels.
    decel : ndarray, shape (n,)
        m/s^2, positive while slowing: ``-mean(accel - mean(accel[t < 0]))``.
    offsets : dict
        Channel name -> removed offset in m/s^2.
    """
    short = [name for (t, _), name in zip(channels, names) if t.size < 2]
    if not channels or short:
        raise InputError(f"expected channels of at least 2 samples, got {short or 'none'}", field="channels")
    dt = channels[0][0][1] - channels[0][0][0]
    starts = [int(round(t[0] / dt)) for t, _ in channels]
    for (t, _), name, k in zip(channels, names, starts):
        if abs(t[1] - t[0] - dt) > 1e-6 * dt or abs(t[0] - k * dt) > 1e-3 * dt:
            raise InputError(f"channel {name} is not on the time grid of channel {names[0]} (step {dt} s)",
                             field="channels")
    first, last = max(starts), min(k + t.size for k, (t, _) in zip(starts, channels))
    if last - first < 2:
        raise InputError(f"channels {', '.join(names)} share no common time span", field="channels")
    rows, offsets = [], {}
    for (t, a), name, k in zip(channels, names, starts):
        pre = t < -0.5 * dt  # t < 0, robust to float noise in a time of exactly 0
        offsets[name] = float(a[pre].mean()) if pre.any() else 0.0
        if not pre.any():
            warnings.append(f"channel {name} has no pre-impact samples (t < 0): offset not removed")
        if k + t.size > last or k < first:
            warnings.append(f"channel {name} cut to the common span {first * dt:.6g} to {(last - 1) * dt:.6g} s")
        rows.append(a[first - k : last - k] - offsets[name])
    time = channels[int(np.argmax(starts))][0][: last - first]
    return time, -np.mean(rows, axis=0), offsets
