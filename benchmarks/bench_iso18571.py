"""Time crashfuse's ISO/TS 18571 rating against the TU Graz oracle on the same pairs, in one run.

Usage: python benchmarks/bench_iso18571.py [--pairs 50] [--end-ms 60] [--seed 0]

The pairs are crash-pulse-like curves (half-sine and double-hump pulses of 60-100 ms with
random shifts, scaling and noise) on the 10 kHz window grid. Prints the time of the oracle
(one pair at a time, as it works), of ``iso_score_many`` (all pairs in one call) and of
``iso_score`` called pair by pair, the ratios, and the largest sub-score difference.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from crashfuse.signals.iso18571 import DT, iso_score, iso_score_many

KEYS = ("overall", "corridor", "phase", "magnitude", "slope")


def make_pairs(n_pairs: int, end: float, seed: int):
    """Reference pulse and ``n_pairs`` perturbed pulses on the window grid, in m/s^2.

    Returns
    -------
    t : ndarray, shape (n,)
    ref : ndarray, shape (n,)
    cmps : ndarray, shape (n_pairs, n)
    """
    rng = np.random.default_rng(seed)
    t = DT * np.arange(int(round(end / DT)) + 1)

    def pulse(duration, peak, delay, second):
        u = np.clip((t - delay) / duration, 0.0, 1.0)
        return peak * (np.sin(np.pi * u) + second * np.sin(3 * np.pi * u) ** 2)

    ref = pulse(0.08, 250.0, 0.0, 0.3)
    cmps = np.stack([
        pulse(rng.uniform(0.06, 0.1), rng.uniform(180, 320), rng.uniform(-0.01, 0.01), rng.uniform(0, 0.6))
        + rng.normal(0, 5.0, t.size)
        for _ in range(n_pairs)
    ])
    return t, ref, cmps


def oracle_scores(t, ref, cmp):
    """The oracle's unrounded scores for one pair."""
    from objective_rating_metrics.rating import ISO18571

    o = ISO18571(np.column_stack([t, ref]), np.column_stack([t, cmp]))
    return [o.overall_rating(-1), o.corridor_rating(-1), o.phase_rating(-1), o.magnitude_rating(-1),
            o.slope_rating(-1)]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=50)
    ap.add_argument("--end-ms", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    end = args.end_ms * 1e-3
    t, ref, cmps = make_pairs(args.pairs, end, args.seed)

    oracle_scores(t, ref, cmps[0])  # compile the oracle's numba kernels outside the timing
    t0 = time.perf_counter()
    theirs = np.array([oracle_scores(t, ref, c) for c in cmps])
    t1 = time.perf_counter()
    many = iso_score_many(t, ref, t, cmps, start=0.0, end=end)
    t2 = time.perf_counter()
    single = [iso_score(t, ref, t, c, start=0.0, end=end) for c in cmps]
    t3 = time.perf_counter()

    ours = np.column_stack([many[k] for k in KEYS])
    ours_single = np.array([[s[k] for k in KEYS] for s in single])
    oracle_s, many_s, single_s = t1 - t0, t2 - t1, t3 - t2
    print(f"{args.pairs} pairs, window 0-{args.end_ms:g} ms at 10 kHz ({t.size} samples)")
    print(f"oracle (objective_rating_metrics 1.3): {oracle_s:8.3f} s  ({1e3 * oracle_s / args.pairs:.2f} ms/pair)")
    print(f"crashfuse iso_score_many:              {many_s:8.3f} s  ({1e3 * many_s / args.pairs:.2f} ms/pair)")
    print(f"crashfuse iso_score, pair by pair:     {single_s:8.3f} s  ({1e3 * single_s / args.pairs:.2f} ms/pair)")
    print(f"speed-up oracle / iso_score_many: {oracle_s / many_s:.1f}x; oracle / iso_score: {oracle_s / single_s:.1f}x")
    print(f"max |ours - oracle| over all sub-scores: {np.abs(ours - theirs).max():.2e} "
          f"(pair by pair: {np.abs(ours_single - theirs).max():.2e})")


if __name__ == "__main__":
    main()
