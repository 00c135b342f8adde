"""One bias-corrected prediction: wall time of a 1000-sample rollout, its parts, peak memory, and
the naive per-sample, per-step Python loop as the baseline ratio.

    .venv/bin/python benchmarks/bench_rollout.py [CAMPAIGN] [--samples 1000] [--naive 20]

Without CAMPAIGN the `paper` campaign (seed 0) is generated in memory with 200 CAE runs (the
rollout's cost does not depend on how many runs the surrogate learnt from).
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc

import numpy as np

from crashfuse.signals.dynamics import rollout
from crashfuse.io.campaign import read_campaign
from crashfuse.method.config import MethodConfig
from crashfuse.method.model import fit_model
from crashfuse.method.rollout import _BranchBias, _decel_fn, _prepare, predict


def _campaign(folder):
    if folder:
        return read_campaign(folder)
    from crashfuse.world.generate import build  # benchmarks may use the world; method code never does
    from crashfuse.world.presets import resolve
    return build(resolve("paper"), seed=0, n_cae=200)[0]


def _best(fn, repeat=3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("campaign", nargs="?")
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--naive", type=int, default=20, help="samples the naive loop runs (then scaled)")
    ap.add_argument("--inputs", default="state")
    ap.add_argument("--k", type=int, default=2)
    args = ap.parse_args(argv)
    campaign = _campaign(args.campaign)
    test = campaign.pulses["T05"]
    model = fit_model(campaign, MethodConfig(k=args.k, inputs=args.inputs), holdout="T05")
    cond = model.condition(test.v0, test.front_weight, test.rear_weight, test.meta.get("powertrain"),
                           test.meta.get("drive"))
    dt, n_steps = test.dt, test.time.size - 1

    def full():
        return predict(model, cond.v0, cond.front_weight, cond.rear_weight, cond.powertrain, cond.drive,
                       n_samples=args.samples, random_state=0, duration=n_steps * dt, dt=dt)

    full()  # warm caches
    t_full = _best(full)
    rng = np.random.RandomState(0)
    t0 = time.perf_counter()
    curve, draws, _, _ = _prepare(model, cond, args.samples, rng, dt, n_steps)
    t_prep = time.perf_counter() - t0
    t_mc = _best(lambda: rollout(_decel_fn(curve, draws), np.full(args.samples, cond.v0), dt, n_steps))
    mc = rollout(_decel_fn(curve, draws), np.full(args.samples, cond.v0), dt, n_steps)

    t0 = time.perf_counter()
    naive = []
    for j in range(args.naive):
        row = {b: None if d is None else _BranchBias(d.x_hi, d.mean_table, d.v_grid, d.dev[j:j + 1])
               for b, d in draws.items()}
        naive.append(rollout(_decel_fn(curve, row), cond.v0, dt, n_steps).decel[0])
    t_naive = (time.perf_counter() - t0) * args.samples / args.naive
    same = max(float(np.abs(naive[j] - mc.decel[j]).max()) for j in range(args.naive))

    tracemalloc.start()
    full()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()

    print(f"condition T05 ({args.inputs} inputs, K={args.k}), {args.samples} samples x {n_steps + 1} steps")
    print(f"predict, all in (best of 3):   {t_full:.3f} s (target <= 1 s)")
    print(f"  draws, mean and CAE rollouts: {t_prep:.3f} s")
    print(f"  the {args.samples}-sample rollout:     {t_mc:.3f} s")
    print(f"naive per-sample loop (scaled from {args.naive}): {t_naive:.1f} s -> vectorised is {t_naive / t_mc:.0f}x "
          f"faster; same samples to {same:.1e} m/s^2")
    print(f"peak traced memory of predict: {peak / 2**20:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
