"""The hybrid's effect fits: one fold's `auto` effect choice; the batched CAE + effects rollout it
repeats, against each sample holding its own copy of its CAE tables (the baseline ratio); that
rollout's cost over batch sizes (``--sizes``), split into a part per rollout and a part per sample;
and a Jacobian's columns following the unshifted rollout, against a rollout per column.

    .venv/bin/python benchmarks/bench_effect_fit.py [CAMPAIGN] [--holdout T05] [--samples 1100]
                                                    [--candidates E ...] [--sizes N ...]

Without CAMPAIGN the `paper` campaign (seed 0) is generated in memory with 200 CAE runs. A fit's
rollouts hold every training set x test x Jacobian column (about 1000 samples on 11 tests).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from unittest import mock

import numpy as np

from crashfuse.catalogue import EFFECTS
from crashfuse.io.campaign import read_campaign
from crashfuse.method import effect_fit, laws
from crashfuse.method.effect_fit import DT, parameters_to_fit, test_case
from crashfuse.method.hybrid import fit_physics
from crashfuse.method.surrogate import CAESurrogate

ROLLOUT_EFFECTS = ("powertrain", "strain_rate")  # what `auto` chooses on `paper`


def _campaign(folder):
    if folder:
        return read_campaign(folder)
    from crashfuse.world.generate import build  # benchmarks may use the world; method code never does
    from crashfuse.world.presets import resolve
    return build(resolve("paper"), seed=0, n_cae=200)[0]


def _own_tables(plant: laws.Plant) -> laws.Plant:
    """``plant`` with every sample holding its own copy of its condition's tables (the layout before
    samples shared them)."""
    return dataclasses.replace(plant, load_table=plant.load_table.take(plant.row, axis=1),
                               a_unload=plant.a_unload[plant.row], row=np.arange(plant.row.size))


def _counted(name: str, record: list, size):
    """effect_fit's ``name`` (a laws function it imports) patched to append ``size(*args)`` of every call
    to ``record``."""
    real = getattr(laws, name)
    return mock.patch.object(effect_fit, name, side_effect=lambda *a: record.append(size(*a)) or real(*a))


def _best(fn, repeat=3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("campaign", nargs="?")
    ap.add_argument("--holdout", default="T05")
    ap.add_argument("--samples", type=int, default=1100)
    ap.add_argument("--candidates", nargs="+", default=list(EFFECTS), help="the effects `auto` chooses among")
    ap.add_argument("--sizes", nargs="+", type=int, default=[100, 300, 1100, 4400],
                    help="batch sizes (samples) of the rollout cost scan")
    args = ap.parse_args(argv)
    campaign = _campaign(args.campaign)
    surrogate = CAESurrogate(random_state=0).fit(campaign)
    train = [t for t in campaign.tests if t != args.holdout]
    case = test_case(campaign.subset([*train, *campaign.cae]), surrogate)

    params = parameters_to_fit(case, ROLLOUT_EFFECTS)

    def batch(n):
        rows = np.arange(n) % len(case.test_ids)
        return case.plant.subset(rows), {p.name: np.full(n, p.start[0]) for p in params}

    def roll(plant, theta):
        return laws.simulate(plant, ROLLOUT_EFFECTS, theta, DT, case.n_steps)

    shared, theta = batch(args.samples)
    own = _own_tables(shared)
    same = np.array_equal(roll(shared, theta).decel, roll(own, theta).decel)
    t_shared, t_own = (_best(lambda p=p: roll(p, theta)) for p in (shared, own))
    scan = {n: _best(lambda b=batch(n): roll(*b)) for n in args.sizes}
    shifted = [{**theta, p.name: theta[p.name] * np.exp(effect_fit.FD_STEP)} for p in params]  # a Jacobian's
    followed = laws.simulate_shifted(shared, ROLLOUT_EFFECTS, theta, shifted, DT, case.n_steps)
    same_columns = all(np.array_equal(followed[:, c], roll(shared, t).decel) for c, t in enumerate(shifted))
    t_columns = _best(lambda: [roll(shared, t) for t in shifted])
    t_followed = _best(lambda: laws.simulate_shifted(shared, ROLLOUT_EFFECTS, theta, shifted, DT, case.n_steps))

    calls, columns = [], []
    counted = _counted("simulate", calls, lambda plant, *a: plant.row.size)
    counted_columns = _counted("simulate_shifted", columns, lambda plant, effects, theta, shifted, *a:
                               plant.row.size * len(shifted))
    t0, c0 = time.perf_counter(), time.process_time()
    with counted, counted_columns:
        fit = fit_physics(campaign, train, "auto", surrogate, candidates=tuple(args.candidates))
    t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0

    effects = "+".join(ROLLOUT_EFFECTS)
    print(f"CAE + {effects} rollout, {args.samples} samples x {case.n_steps + 1} steps (CPU, best of 3):")
    print(f"  tables shared by condition: {t_shared:.3f} s; each sample its own copy: {t_own:.3f} s "
          f"-> {t_own / t_shared:.2f}x; identical: {same}")
    per_sample, fixed = np.polyfit(list(scan), list(scan.values()), 1) if len(scan) > 1 else (np.nan, np.nan)
    print("  by batch size: " + ", ".join(f"{n} samples {t:.3f} s" for n, t in scan.items())
          + f" -> about {fixed:.3f} s per rollout + {1e3 * per_sample:.3f} ms per sample")
    print(f"  a Jacobian's {len(shifted)} finite-difference columns: a rollout each {t_columns:.3f} s; following "
          f"the unshifted rollout until their law acts {t_followed:.3f} s -> {t_columns / t_followed:.2f}x; "
          f"identical: {same_columns}")
    print(f"one fold's `auto` effect choice (without {args.holdout}, {len(train)} tests): {t_fit:.1f} s wall, "
          f"{c_fit:.1f} s CPU; chose {'+'.join(fit.effects) or 'none'}")
    print(f"  {len(calls)} batched rollouts, {np.mean(calls):.0f} samples each on average "
          f"({sum(calls) * (case.n_steps + 1) / 1e6:.0f} M sample-steps), and {len(columns)} Jacobians of "
          f"{np.mean(columns):.0f} samples x columns each on average")
    return 0


if __name__ == "__main__":
    sys.exit(main())
