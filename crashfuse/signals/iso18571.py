"""ISO/TS 18571:2014 objective rating of a compared signal against a reference signal.

Pipeline (see docs/iso18571.md): both curves are resampled by linear interpolation to the
standard's 10 kHz grid ``start + k * 0.1 ms``, cut to the window [start, end] (both ends
included), and rated with the four sub-scores of the standard:

- corridor: inner/outer corridor half widths a0 = 5 % and b0 = 50 % of max|reference|, kz = 2;
- phase: time shift n that maximises the Pearson correlation of the overlapping parts, searched
  up to 20 % of the window length, kp = 1;
- magnitude (EEARTH): on the shifted curves, dynamic time warping with a Sakoe-Chiba band of
  10 % of their length, then the L1 error along the warping path, eps_mag = 0.5, km = 1;
- slope: on the shifted curves, central-difference derivatives smoothed by a 9-point moving
  average (shrinking centred windows at the ends), L1 error, eps_slope = 2.0, ks = 1;

overall = 0.4 corridor + 0.2 phase + 0.2 magnitude + 0.2 slope. Implementation details the
standard leaves open follow the TU Graz reference implementation (PyPI
``objective_rating_metrics`` 1.3), which the tests use as an oracle.

Everything is vectorised over many compared curves; the dynamic time warping runs as an
anti-diagonal wavefront over the band, so its Python loop is over anti-diagonals, not cells.
"""

from __future__ import annotations

import math

import numpy as np

from crashfuse.errors import InputError

DT = 1e-4  # s, the standard's sampling interval (10 kHz)
A0, B0, KZ = 0.05, 0.5, 2  # corridor: inner and outer relative half widths, exponent
MAX_SHIFT, KP = 0.2, 1  # phase: largest shift as a fraction of the window length, exponent
DTW_BAND, EPS_MAG, KM = 0.1, 0.5, 1  # magnitude: Sakoe-Chiba band fraction, max error, exponent
EPS_SLOPE, KS = 2.0, 1  # slope: max error, exponent
WEIGHTS = {"corridor": 0.4, "phase": 0.2, "magnitude": 0.2, "slope": 0.2}
MIN_SAMPLES = 11  # 1 ms: the shifted curves keep the 9 samples the slope smoothing needs
SMOOTH = 9  # moving-average length of the slope score
_TIME_TOL = 1e-3 * DT  # s, slack when checking that the data cover the window
_RHO_TIE = 1e-12  # correlations closer than this to the best are ties (rounding)
_DTW_CELLS = 1 << 22  # band cells of back-pointers kept at once (int32, 16 MB): sets how many curves go together
_DTW_BLOCK = 1 << 19  # band cells whose squared differences are prepared at once (4 MB)


# --- public API -------------------------------------------------------------------------


def iso_score(t_ref, ref, t_cmp, cmp, start: float = 0.0, end: float = 0.06) -> dict[str, float]:
    """ISO/TS 18571 rating of one compared curve against a reference.

    Parameters
    ----------
    t_ref : array_like, shape (n,)
        Reference sample times in s, strictly increasing.
    ref : array_like, shape (n,)
        Reference signal (any unit, the same as ``cmp``).
    t_cmp : array_like, shape (m,)
        Compared sample times in s, strictly increasing.
    cmp : array_like, shape (m,)
        Compared signal, e.g. a prediction.
    start, end : float
        Rating window in s; both ends are included. Both curves must cover it.

    Returns
    -------
    dict
        Floats in [0, 1] under ``overall``, ``corridor``, ``phase``, ``magnitude``, ``slope``.

    Raises
    ------
    InputError
        If an array is malformed, the window is not covered by both curves or is shorter
        than 1 ms, or the reference is constant over the window.
    """
    cmp = _as_1d(cmp, "compared signal")
    scores = iso_score_many(t_ref, ref, t_cmp, cmp[np.newaxis], start=start, end=end)
    return {key: float(val[0]) for key, val in scores.items()}


def iso_score_many(t_ref, ref, t_cmp, cmps, start: float = 0.0, end: float = 0.06) -> dict[str, np.ndarray]:
    """ISO/TS 18571 ratings of many compared curves, sampled at common times, against one reference.

    Parameters
    ----------
    t_ref : array_like, shape (n,)
        Reference sample times in s, strictly increasing.
    ref : array_like, shape (n,)
        Reference signal.
    t_cmp : array_like, shape (m,)
        Sample times in s shared by all compared curves, strictly increasing.
    cmps : array_like, shape (k, m)
        Compared curves, one per row, in the unit of ``ref``.
    start, end : float
        Rating window in s; both ends are included.

    Returns
    -------
    dict
        Arrays of shape (k,) under ``overall``, ``corridor``, ``phase``, ``magnitude``, ``slope``.

    Raises
    ------
    InputError
        As :func:`iso_score`.
    """
    grid = window_grid(start, end)
    ref_w = resample(t_ref, ref, grid, "reference")
    cmps = np.asarray(cmps, dtype=float)
    if cmps.ndim != 2 or cmps.shape[0] == 0:
        raise InputError(f"expected a 2-D array (curves, samples) with at least one curve, got shape {cmps.shape}",
                         field="compared signal")
    cmp_w = resample(t_cmp, cmps, grid, "compared signal")
    return rate(ref_w, cmp_w)


def window_grid(start: float, end: float) -> np.ndarray:
    """The standard's 10 kHz sample times of the window [start, end], both ends included.

    Parameters
    ----------
    start, end : float
        Window limits in s.

    Returns
    -------
    ndarray, shape (n,)
        ``start + k * DT`` for k = 0 .. floor((end - start) / DT), in s.
    """
    if not (np.isfinite(start) and np.isfinite(end) and end > start):
        raise InputError(f"expected a finite window with end > start, got [{start}, {end}] s", field="window")
    n = int(math.floor((end - start) / DT + 1e-6)) + 1
    if n < MIN_SAMPLES:
        raise InputError(f"window [{start * 1e3:g}, {end * 1e3:g}] ms is shorter than "
                         f"{(MIN_SAMPLES - 1) * DT * 1e3:g} ms ({MIN_SAMPLES} samples at 10 kHz)", field="window")
    return start + DT * np.arange(n)


def resample(t, y, grid: np.ndarray, name: str) -> np.ndarray:
    """Linear interpolation of curves onto the window grid, after checking the inputs.

    Parameters
    ----------
    t : array_like, shape (m,)
        Sample times in s, strictly increasing, covering ``grid``.
    y : array_like, shape (m,) or (k, m)
        One curve, or k curves sampled at ``t``.
    grid : ndarray, shape (n,)
        Target times in s (from :func:`window_grid`).
    name : str
        What the curve is, for error messages.

    Returns
    -------
    ndarray, shape (n,) or (k, n)
        The curves at ``grid``.
    """
    t = _as_1d(t, f"{name} time")
    y = np.asarray(y, dtype=float)
    if y.shape[-1:] != t.shape or t.size < 2:
        raise InputError(f"expected at least 2 samples and as many values as times ({t.size}), "
                         f"got shape {y.shape}", field=name)
    _check_finite(y, name)
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0])
        raise InputError(f"expected strictly increasing times, but t[{i + 1}]={t[i + 1]} <= t[{i}]={t[i]}",
                         field=f"{name} time")
    if t[0] > grid[0] + _TIME_TOL or t[-1] < grid[-1] - _TIME_TOL:
        raise InputError(f"data span [{t[0] * 1e3:g}, {t[-1] * 1e3:g}] ms does not cover the rating window "
                         f"[{grid[0] * 1e3:g}, {grid[-1] * 1e3:g}] ms", field=f"{name} time")
    if y.ndim == 1:
        return np.interp(grid, t, y)
    return np.stack([np.interp(grid, t, row) for row in y])


def rate(ref: np.ndarray, cmp: np.ndarray) -> dict[str, np.ndarray]:
    """ISO/TS 18571 sub-scores and overall rating of curves already on the 10 kHz window grid.

    Parameters
    ----------
    ref : ndarray, shape (n,)
        Reference at 10 kHz over the window, not constant.
    cmp : ndarray, shape (k, n)
        Compared curves on the same samples.

    Returns
    -------
    dict
        Arrays of shape (k,) under ``overall``, ``corridor``, ``phase``, ``magnitude``, ``slope``.
    """
    ref = np.asarray(ref, dtype=float)
    cmp = np.asarray(cmp, dtype=float)
    if ref.ndim != 1 or cmp.ndim != 2 or cmp.shape[1] != ref.size or ref.size < MIN_SAMPLES:
        raise InputError(f"expected a reference of n >= {MIN_SAMPLES} samples and curves of shape (k, n), "
                         f"got {ref.shape} and {cmp.shape}", field="compared signal")
    _check_finite(ref, "reference")
    _check_finite(cmp, "compared signal")
    if ref.max() == ref.min():
        raise InputError("the reference is constant over the rating window: phase and slope are undefined",
                         field="reference")
    n = ref.size
    chunk = max(1, _DTW_CELLS // ((2 * n + 1) * (math.ceil(DTW_BAND * n) + 2)))
    parts = [_rate_chunk(ref, cmp[i:i + chunk]) for i in range(0, cmp.shape[0], chunk)]
    scores = {key: np.concatenate([p[key] for p in parts]) for key in WEIGHTS}
    overall = sum(WEIGHTS[key] * scores[key] for key in WEIGHTS)
    return {"overall": overall, **scores}


# --- the four sub-scores ------------------------------------------------------------------


def _rate_chunk(ref: np.ndarray, cmp: np.ndarray) -> dict[str, np.ndarray]:
    """The four sub-scores, arrays of shape (k,), of curves ``cmp`` (k, n) against ``ref`` (n,)."""
    n = ref.size
    shift = phase_shift(ref, cmp)
    x, y, length = _shifted(ref, cmp, shift)
    num, den = _dtw_l1(x, y, length)
    return {
        "corridor": corridor_score(ref, cmp),
        "phase": _phase_score(shift, n),
        "magnitude": _ramp(num / den, EPS_MAG, KM),
        "slope": _ramp(_slope_error(x, y, length), EPS_SLOPE, KS),
    }


def corridor_score(ref: np.ndarray, cmp: np.ndarray) -> np.ndarray:
    """Corridor score: mean over samples of the rating between the inner and outer corridor.

    Parameters
    ----------
    ref : ndarray, shape (n,)
        Reference curve.
    cmp : ndarray, shape (k, n)
        Compared curves.

    Returns
    -------
    ndarray, shape (k,)
        1 inside the inner corridor, 0 outside the outer one, ((b - |d|) / (b - a))**kz between.
    """
    t_norm = np.abs(ref).max()
    inner, outer = A0 * t_norm, B0 * t_norm
    dev = np.abs(cmp - ref)
    return (np.clip((outer - dev) / (outer - inner), 0.0, 1.0) ** KZ).mean(axis=1)


def phase_shift(ref: np.ndarray, cmp: np.ndarray) -> np.ndarray:
    """Time shift in samples that maximises the correlation of the overlapping parts.

    A positive shift s pairs ``cmp[s:]`` with ``ref[:-s]`` (the compared curve is late), a
    negative one pairs ``cmp[:s]`` with ``ref[-s:]``. Shifts up to floor(0.2 n) are searched in
    the order 0, +1, -1, +2, -2, ... and the first maximum wins, so that among equally good
    shifts (equal to 1e-12) the smallest one is taken, the compared curve moved left first.
    Overlaps on which a curve is constant have no correlation and are never chosen.

    Parameters
    ----------
    ref : ndarray, shape (n,)
        Reference curve, not constant.
    cmp : ndarray, shape (k, n)
        Compared curves.

    Returns
    -------
    ndarray of int, shape (k,)
        The shift of each compared curve, in samples.
    """
    n = ref.size
    m = int(math.floor(n * MAX_SHIFT))
    lags = np.arange(m + 1)
    r = (ref - ref.mean()) / ref.std()
    c = cmp - cmp.mean(axis=1, keepdims=True)
    scale = c.std(axis=1, keepdims=True)
    c = c / np.where(scale > 0, scale, 1.0)
    # cross[s] of lag +s: sum_t r[t] c[t + s]; lag -s: sum_t r[t + s] c[t]. Zero padding makes
    # both a product with a small (2m + 1, n) matrix of shifted references.
    pad = np.zeros(m)
    late = np.lib.stride_tricks.sliding_window_view(np.r_[pad, r], n)[::-1]  # row s: r[t - s]
    early = np.lib.stride_tricks.sliding_window_view(np.r_[r, pad], n)[:m + 1]  # row s: r[t + s]
    # einsum rather than matmul: a product this small is slower through a multithreaded BLAS
    cross_late, cross_early = np.einsum("kt,st->ks", c, late), np.einsum("kt,st->ks", c, early)  # (k, m + 1)
    rho_late = _pearson(cross_late, _head(r, n - lags), _tail(c, lags))
    rho_early = _pearson(cross_early, _tail(r, lags), _head(c, n - lags))
    const_late = _const_head(ref, n - lags)[None] | _const_tail(cmp, lags)
    const_early = _const_tail(ref, lags)[None] | _const_head(cmp, n - lags)
    rho_late[const_late] = -np.inf
    rho_early[const_early] = -np.inf
    order = np.empty((cmp.shape[0], 2 * m + 1))  # candidates 0, +1, -1, +2, -2, ...
    order[:, 0] = rho_late[:, 0]
    order[:, 1::2] = rho_late[:, 1:]
    order[:, 2::2] = rho_early[:, 1:]
    # a rounding-negative variance gives NaN: no correlation. Correlations within rounding of the
    # best count as ties, so that the smallest shift wins as the standard asks.
    order = np.where(np.isnan(order), -np.inf, order)
    best = np.argmax(order >= order.max(axis=1, keepdims=True) - _RHO_TIE, axis=1)
    return np.where(best % 2 == 1, (best + 1) // 2, -(best // 2))


def _sums(z: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sums of z and z**2 over the first idx samples (prefix sums), along the last axis."""
    lead = np.zeros(z.shape[:-1] + (1,))
    s1 = np.concatenate([lead, np.cumsum(z, axis=-1)], axis=-1)
    s2 = np.concatenate([lead, np.cumsum(z * z, axis=-1)], axis=-1)
    return s1[..., idx], s2[..., idx]


def _head(z, count):
    """(count, sum, sum of squares) of the first ``count`` samples."""
    s1, s2 = _sums(z, count)
    return count, s1, s2


def _tail(z, skip):
    """(count, sum, sum of squares) of the samples after the first ``skip``."""
    n = z.shape[-1]
    h1, h2 = _sums(z, skip)
    t1, t2 = _sums(z, np.array([n]))
    return n - skip, t1 - h1, t2 - h2


def _pearson(cross, a, b):
    """Pearson correlation from the cross sum and the (count, sum, sum of squares) of each side."""
    count, sa, saa = a
    _, sb, sbb = b
    cov = cross - sa * sb / count
    var = (saa - sa * sa / count) * (sbb - sb * sb / count)
    with np.errstate(invalid="ignore", divide="ignore"):
        return cov / np.sqrt(var)


def _const_head(z, count):
    """Whether the first ``count`` samples of z are all equal (exact: running max == min)."""
    hi, lo = np.maximum.accumulate(z, axis=-1), np.minimum.accumulate(z, axis=-1)
    return (hi == lo)[..., count - 1]


def _const_tail(z, skip):
    """Whether the samples of z after the first ``skip`` are all equal."""
    return _const_head(z[..., ::-1], z.shape[-1] - skip)


def _phase_score(shift: np.ndarray, n: int) -> np.ndarray:
    """Phase score from the shift in samples: linear from 1 at no shift to 0 at 20 % of n."""
    limit = n * MAX_SHIFT
    return np.clip((limit - np.abs(shift)) / limit, 0.0, 1.0) ** KP


def _ramp(error: np.ndarray, eps_max: float, k: int) -> np.ndarray:
    """Score ((eps_max - error) / eps_max)**k, clipped to [0, 1]."""
    return np.clip((eps_max - error) / eps_max, 0.0, 1.0) ** k


def _shifted(ref: np.ndarray, cmp: np.ndarray, shift: np.ndarray):
    """The overlapping parts after the phase shift, left-aligned.

    Returns
    -------
    x : ndarray, shape (k, n)
        Shifted compared curves; samples beyond ``length`` repeat the last one.
    y : ndarray, shape (k, n)
        The matching parts of the reference, likewise.
    length : ndarray of int, shape (k,)
        n - |shift|.
    """
    n = ref.size
    length = n - np.abs(shift)
    t = np.minimum(np.arange(n)[None], length[:, None] - 1)
    x = np.take_along_axis(cmp, t + np.maximum(shift, 0)[:, None], axis=1)
    y = ref[t + np.maximum(-shift, 0)[:, None]]
    return x, y, length


def _dtw_l1(x: np.ndarray, y: np.ndarray, length: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L1 error along the dynamic-time-warping path of each pair, and the L1 norm of the reference on it.

    The warping minimises the summed squared difference over paths from (0, 0) to
    (L - 1, L - 1) with unit steps (i+1, j), (i, j+1), (i+1, j+1) inside the Sakoe-Chiba
    band |i - j| <= ceil(0.1 L) - 1. The path is traced back from the end through the
    predecessor each cell chose, as the oracle does: (i-1, j), else (i, j-1), else (i-1, j-1),
    whichever has the least accumulated cost, the first one on ties.

    Parameters
    ----------
    x : ndarray, shape (p, n)
        Compared curves (rows i of the cost matrix), valid up to ``length``.
    y : ndarray, shape (p, n)
        Reference parts (columns j), valid up to ``length``.
    length : ndarray of int, shape (p,)
        Number of valid samples L of each pair.

    Returns
    -------
    num, den : ndarray, shape (p,)
        sum |x_i - y_j| and sum |y_j| over the warping path.
    """
    p = x.shape[0]
    band = np.array([math.ceil(DTW_BAND * n) - 1 for n in length.tolist()])
    back, j0 = _dtw_back(x, y, length, band)
    width = back.shape[2]
    end_k = 2 * length - 2
    path = [(end_k * p + np.arange(p)) * width + length - 1 - j0[end_k + 2]]
    flat = back.ravel()
    for _ in range(back.shape[0] - 1):  # enough steps for the longest path; finished ones stay at (0, 0)
        path.append(path[-1] - flat[path[-1]])
    path = np.stack(path)  # (steps, p) flat cell indices
    k = path // (p * width)
    j = j0[k + 2] + path % width
    i = k - j
    fresh = np.ones(path.shape, dtype=bool)
    fresh[1:] = path[1:] != path[:-1]
    rows = np.arange(p)
    num = (fresh * np.abs(x[rows, i] - y[rows, j])).sum(axis=0)
    den = (fresh * np.abs(y[rows, j])).sum(axis=0)
    return num, den


def _dtw_back(x, y, length, band):
    """Accumulated DTW costs swept one anti-diagonal i + j = k at a time, all pairs at once.

    Returns
    -------
    back : ndarray of int32, shape (2 max(L) - 1, p, max(band) + 1)
        For cell j = j0[k + 2] + c of anti-diagonal k (at [k, pair, c]), how far back its
        chosen predecessor lies in ``back.ravel()``; 0 at (0, 0), meaningless outside the band.
    j0 : ndarray of int, shape (2 max(L) + 1,)
        First j stored for anti-diagonals -2 .. 2 max(L) - 2.
    """
    p = x.shape[0]
    width = int(band.max()) + 1  # band cells on one anti-diagonal, at most
    kmax = int(2 * length.max() - 2)  # anti-diagonal of the last end cell
    j0 = -((width - 1 - np.arange(-2, kmax + 1)) // 2)
    back = np.empty((kmax + 1, p, width), dtype=np.int32)
    row = p * width  # flat distance between the same cell of consecutive anti-diagonals
    # accumulated cost on anti-diagonals k-2, k-1, k, with an inf sentinel column at each end
    prev2, prev, cur = (np.full((p, width + 2), np.inf) for _ in range(3))
    prev2[:, -j0[0]] = 0.0  # virtual cell (-1, -1) that starts every path at (0, 0)
    left_or_diag, not_up, is_diag = np.empty((p, width)), np.empty((p, width), bool), np.empty((p, width), bool)
    code = np.empty((p, width), dtype=np.int32)
    block = max(1, _DTW_BLOCK // row)
    for k in range(kmax + 1):
        if k % block == 0:
            steps = _band_steps(x, y, length, band, np.arange(k, min(k + block, kmax + 1)), j0[k + 2:], width)
        d1 = int(j0[k + 2] - j0[k + 1])  # 0 or 1: shift of the same j from anti-diagonal k-1 to k
        up, left, diag = prev[:, 1 + d1:1 + d1 + width], prev[:, d1:d1 + width], prev2[:, 1:1 + width]
        np.minimum(left, diag, out=left_or_diag)
        np.minimum(up, left_or_diag, out=cur[:, 1:-1])
        cur[:, 1:-1] += steps[k % block]
        # flat distance back to the predecessor: row - d1 (up), row - d1 + 1 (left), 2 row (diagonal)
        np.greater(up, left_or_diag, out=not_up)
        np.greater(left, diag, out=is_diag)
        np.multiply(is_diag, row + d1 - 1, out=code)
        code += 1
        code *= not_up
        np.add(code, row - d1, out=back[k])
        prev2, prev, cur = prev, cur, prev2
    back[0, :, -j0[2]] = 0
    return back, j0


def _band_steps(x, y, length, band, ks, j0s, width) -> np.ndarray:
    """Squared differences (x_i - y_j)**2 on anti-diagonals ``ks``, inf outside each pair's band.

    Returns
    -------
    ndarray, shape (len(ks), p, width)
    """
    p, n = x.shape
    j = j0s[:ks.size, None] + np.arange(width)
    i = ks[:, None] - j
    pairs = np.arange(p)[None, :, None]
    diff = x[pairs, np.clip(i, 0, n - 1)[:, None]] - y[pairs, np.clip(j, 0, n - 1)[:, None]]
    outside = ((np.minimum(i, j) < 0)[:, None] | (np.maximum(i, j)[:, None] >= length[None, :, None])
               | (np.abs(i - j)[:, None] > band[None, :, None]))
    diff *= diff
    diff[outside] = np.inf
    return diff


def _slope_error(x: np.ndarray, y: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Relative L1 error of the smoothed derivatives, sum|x' - y'| / sum|y'|, over each pair's length."""
    dx, dy = _smoothed_slope(x, length), _smoothed_slope(y, length)
    return np.abs(dx - dy).sum(axis=1) / np.abs(dy).sum(axis=1)


def _smoothed_slope(z: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Derivative in units/s, central differences (one-sided at the ends) smoothed by a moving average.

    Sample i gets the mean over a centred window of 9 samples, shrunk to 2i + 1 samples near
    the start and symmetrically near the end. Entries at or beyond ``length`` are zero.

    Parameters
    ----------
    z : ndarray, shape (p, n)
        Curves at DT spacing, valid up to ``length`` (>= 9).
    length : ndarray of int, shape (p,)
        Number of valid samples of each curve.

    Returns
    -------
    ndarray, shape (p, n)
    """
    p, n = z.shape
    rows = np.arange(p)
    g = np.zeros((p, n))
    g[:, 1:-1] = (z[:, 2:] - z[:, :-2]) / (2 * DT)
    g[:, 0] = (z[:, 1] - z[:, 0]) / DT
    g[rows, length - 1] = (z[rows, length - 1] - z[rows, length - 2]) / DT
    g[np.arange(n)[None] >= length[:, None]] = 0.0
    half = SMOOTH // 2
    out = np.zeros((p, n))
    out[:, half:n - half] = np.lib.stride_tricks.sliding_window_view(g, SMOOTH, axis=1).mean(axis=2)
    tail = np.take_along_axis(g, length[:, None] - SMOOTH + 1 + np.arange(SMOOTH - 1), axis=1)
    for i in range(half):
        out[:, i] = g[:, :2 * i + 1].mean(axis=1)
        out[rows, length - 1 - i] = tail[:, SMOOTH - 2 - 2 * i:].mean(axis=1)
    out[np.arange(n)[None] >= length[:, None]] = 0.0
    return out


# --- input checks -------------------------------------------------------------------------


def _as_1d(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 1:
        raise InputError(f"expected a 1-D array, got shape {a.shape}", field=name)
    _check_finite(a, name)
    return a


def _check_finite(a: np.ndarray, name: str) -> None:
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        raise InputError(f"expected finite numbers, found {a[tuple(bad[0])]} at index {tuple(bad[0].tolist())}",
                         field=name)
