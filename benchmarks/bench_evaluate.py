"""Full leave-one-test-out evaluation on the `paper` campaign: wall time, peak memory, the
Table-2-shaped ISO/TS 18571 result for both input modes, band coverage and the targets (wall time
<= 300 s on 2 jobs, <= 4 GiB per process, coverage 0.90-0.99, each K's margin against CAE).

    .venv/bin/python benchmarks/bench_evaluate.py [CAMPAIGN] [--out DIR] [--jobs 2] [--samples 1000]
                                                  [--[no-]use-companion]

Without CAMPAIGN the `paper` campaign (seed 0, 1009 CAE runs) is generated in memory.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np
import psutil

from crashfuse.evaluation.loto import evaluate
from crashfuse.io.campaign import read_campaign
from crashfuse.method.config import MethodConfig
from crashfuse.method.model import fit_model
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.reporting.plots import plot_evaluation

DEFAULT_K = 1  # the timed single fold (the auto model picks K1 in nearly every fold: docs/bias-model.md)


def _campaign(folder):
    if folder:
        return read_campaign(folder)
    from crashfuse.world.generate import build  # benchmarks may use the world; method code never does
    from crashfuse.world.presets import resolve
    return build(resolve("paper"), seed=0)[0]


def _peak_mib() -> tuple[float, float]:
    """Peak resident memory (MiB) of this process and of its largest finished child (Linux: KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return own, child


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its children, live (the joblib workers) or reaped.

    Wall time on the shared machine depends on what else runs; the CPU seconds of the evaluation
    do much less, so comparisons between runs use them.
    """
    me = psutil.Process()
    reaped = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = reaped.ru_utime + reaped.ru_stime
    for proc in [me, *me.children(recursive=True)]:
        try:
            times = proc.cpu_times()
        except psutil.NoSuchProcess:  # ended between the listing and the reading: counted as reaped
            continue
        total += times.user + times.system
    return total


def _targets(iso, coverage) -> None:
    wide = iso.pivot_table(index=["inputs", "test_id", "window_ms"], columns="model", values="overall")
    for mode in sorted(set(iso["inputs"])):
        w = wide.loc[mode]
        for k in [c for c in w.columns if c != "CAE"]:
            margin = (w[k] - w["CAE"]).min()
            mean60 = w.xs("0-60", level="window_ms")[k].mean()
            losses = int((w[k] < w["CAE"] - 0.01).sum())
            print(f"  {mode:5s} {k}: mean ISO(0-60) {mean60:.3f} (CAE {w.xs('0-60', level='window_ms')['CAE'].mean():.3f}); "
                  f"worst margin vs CAE {margin:+.3f}; test-windows worse than CAE by > 0.01: {losses}/{len(w)}")
    cov = coverage.groupby(["inputs", "model"])["coverage"].agg(["mean", "min", "max"])
    print("\n95 % band coverage of held-out test points in 0-60 ms (target 0.90-0.99):")
    print(cov.round(3).to_string())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("campaign", nargs="?")
    ap.add_argument("--out", default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--inputs", nargs="+", default=["paper", "state"])
    ap.add_argument("--use-companion", action=argparse.BooleanOptionalAction, default=None)
    ap.add_argument("--assignment", choices=("select", "blend"), default="select")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    campaign = _campaign(args.campaign)
    t1 = time.perf_counter()
    surrogate = CAESurrogate(random_state=0).fit(campaign)
    t2 = time.perf_counter()
    fit_model(campaign, MethodConfig(k=DEFAULT_K, inputs="state"), holdout=campaign.tests[0], surrogate=surrogate)
    t3 = time.perf_counter()
    print(f"campaign: {len(campaign.tests)} tests, {len(campaign.cae)} CAE runs ({t1 - t0:.1f} s)")
    print(f"surrogate fit (once, shared by all folds): {t2 - t1:.1f} s; one fold fit (K={DEFAULT_K}, state): "
          f"{t3 - t2:.1f} s")
    cpu0 = _cpu_seconds()
    result = evaluate(campaign, ks=args.ks, inputs=args.inputs, out=args.out, n_samples=args.samples,
                      n_jobs=args.jobs, surrogate=surrogate, use_companion=args.use_companion,
                      assignment=args.assignment,
                      progress=lambda line: print(line, file=sys.stderr))
    if args.out:
        plot_evaluation(result, args.out, campaign)  # the fold figures, as `crashfuse evaluate` draws them
    cpu = _cpu_seconds() - cpu0
    own, child = _peak_mib()
    n_folds = len(result.coverage)
    print(f"\nfull evaluation: {n_folds} folds in {result.wall_time:.1f} s on {args.jobs} jobs "
          f"(target <= 300 s); {cpu:.0f} s CPU with the workers (outputs included), {cpu / args.jobs:.0f} s per job; "
          f"peak RSS main {own:.0f} MiB, largest worker {child:.0f} MiB (target <= 4096)")
    print(f"per fold: fit {result.coverage['fit_s'].mean():.2f} s, predict {result.coverage['predict_s'].mean():.2f} s "
          f"({args.samples} samples)")
    iso = result.iso_table
    print("\nISO/TS 18571 overall (Table-2 shape):")
    table = iso.pivot_table(index=["inputs", "test_id"], columns=["window_ms", "model"], values="overall")
    print(table.round(3).to_string())
    print("\nmean over tests:")
    print(iso.pivot_table(index=["inputs", "model"], columns="window_ms", values="overall").round(3).to_string())
    print("\ntargets:")
    _targets(iso, result.coverage)
    print(f"\nextrapolating folds: {int(result.coverage['extrapolation'].sum())}/{n_folds}; "
          f"GPs per branch after merging: loading {sorted(set(result.coverage['n_gps_loading']))}, "
          f"unloading {sorted(set(result.coverage['n_gps_unloading']))}")
    switches = result.coverage.groupby(["inputs", "model"])["cluster_switches"].agg(["mean", "max"])
    print("\nselected-GP switches along the mean-function rollout (per fold):")
    print(switches.round(2).to_string())
    print(f"total {time.perf_counter() - t0:.1f} s; every ISO score finite: {np.isfinite(iso['overall']).all()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
