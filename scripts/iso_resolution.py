"""The resolution of ISO/TS 18571 on a campaign: how far a test's rating of its own CAE run moves when that
run is perturbed by a smooth error of a given size.

A bias correction can only add its estimate's error to a CAE pulse that is already right. This measures
what an error of ``--rms`` g costs in the ratings the method is judged by: per test with a companion CAE
run, the run is rated against the test over ``--window`` (as ``evaluate``'s CAE rows), then ``--draws``
times with white noise added, filtered at CFC 60 and scaled to ``--rms`` g rms over the window. Printed
per test and size: the CAE's rating, the fraction of draws rated more than 0.01 below it (a window
"lost" in issue 16's sense), and the median and 5 % quantile of the change. Run from the project folder::

    .venv/bin/python scripts/iso_resolution.py CAMPAIGN [--rms 0.05 0.1 0.2] [--window 0-20] [--draws 200] [--seed 0]
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.evaluation.fold import check_windows
from crashfuse.evaluation.iso_table import window_bounds
from crashfuse.io.campaign import read_campaign
from crashfuse.signals.filters import filtered_noise
from crashfuse.signals.iso18571 import iso_score_many
from crashfuse.units import G0, MS

LOST = 0.01  # a window lost: rated more than this below the CAE


def smooth_errors(n: int, dt: float, inside, rms: float, draws: int, rng) -> np.ndarray:
    """``draws`` white-noise records of ``n`` samples at ``dt`` s, filtered at CFC 60 and scaled to ``rms``
    (m/s^2) over the samples ``inside``; shape (draws, n)."""
    noise = filtered_noise(rng, (draws, n), dt, 60)
    return noise * (rms / noise[:, inside].std(axis=1, keepdims=True))


def resolution(campaign, sizes_g, window: str, draws: int, seed: int) -> pd.DataFrame:
    """One row per test with a companion and size: ``cae`` rating, ``lost`` fraction, ``median``, ``p05``."""
    start, end = (b * MS for b in window_bounds(window))
    rows = []
    for i, test_id in enumerate(campaign.tests):
        companion = campaign.companion(test_id)
        if companion is None:
            continue
        test, cae = campaign.pulses[test_id].after_contact(), companion.after_contact()
        base = iso_score_many(test.time, test.decel, cae.time, cae.decel[None], start, end)["overall"][0]
        inside = (cae.time >= start) & (cae.time <= end)
        for size in sizes_g:
            rng = np.random.default_rng([seed, i, round(size * 1e6)])  # a test's draws: the same whatever else is asked
            errors = smooth_errors(cae.time.size, float(cae.time[1] - cae.time[0]), inside,
                                   size * G0, draws, rng)
            change = iso_score_many(test.time, test.decel, cae.time, cae.decel + errors, start, end)["overall"] - base
            rows.append(dict(test_id=test_id, rms_g=size, cae=base, lost=np.mean(change < -LOST),
                             median=np.median(change), p05=np.quantile(change, 0.05)))
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("campaign")
    p.add_argument("--rms", type=float, nargs="+", default=[0.05, 0.1, 0.2],
                   help="error sizes, g rms (default 0.05 0.1 0.2)")
    p.add_argument("--window", default="0-20", help="ISO window in ms (default 0-20)")
    p.add_argument("--draws", type=int, default=200, help="perturbed runs per test and size (default 200)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    try:
        (window,) = check_windows([args.window])
        table = resolution(read_campaign(args.campaign), args.rms, window, args.draws, args.seed)
    except InputError as err:
        raise SystemExit(f"iso_resolution: {err}") from None
    if table.empty:
        raise SystemExit(f"{args.campaign}: no test names a companion CAE run (cae_run_id)")
    print(table.round(3).to_string(index=False))
    print("\nover the tests:")
    print(table.groupby("rms_g")[["lost", "median", "p05"]].mean().round(3).to_string())


if __name__ == "__main__":
    main()
