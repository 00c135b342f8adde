"""CAE surrogate accuracy and cost on the ``paper`` campaign, and the cost of thinning projected bias.

Every figure is measured in this run, on the world's ``paper`` campaign built in memory
(11 tests, their companions CT01..CT11 and 1009 Latin-hypercube CAE runs).

Sections
--------
1. Held-out CAE runs: a seeded 10 % of the 1020 CAE runs is held out, the surrogate is fitted on
   the rest; each held-out condition is rolled out with zero bias and rated against the run by
   ISO/TS 18571 over 0-60 ms (and 0-100 ms). Columns: fit_s, mean, min, p05 (5th percentile),
   curve_ms (one ``curve()`` call), rollout_ms (one 1250-step rollout), for a few settings.
2. The 11 test conditions: the surrogate fitted on C0001..C1009 only (companions excluded)
   against the companions CT01..CT11 it has never seen, ISO 0-60 ms; the fit's wall and CPU
   time (wall times swing with other jobs on a shared machine; CPU time less so).
3. Projection thinning: relative RMS error of the bias recovered from ``n_grid`` thinned points vs
   the full projected union, over the 11 test/companion pairs, and the time of ``bias_data``.

Usage::

    .venv/bin/python benchmarks/bench_surrogate.py            # all sections
    .venv/bin/python benchmarks/bench_surrogate.py --quick    # default settings only
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from sklearn.base import clone

from crashfuse.signals.domain import displacement_branches
from crashfuse.signals.iso18571 import iso_score, iso_score_many
from crashfuse.method.projection import bias_data, project_branch, thin
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

SETTINGS = {
    "default": {},
    "no one-hot": {"categorical": False},
    "6 components": {"n_components": 6},
    "14 components": {"n_components": 14},
    "grid 100": {"n_grid": 100},
}


def holdout_accuracy(campaign, surrogate: CAESurrogate, fraction: float = 0.1, random_state=0,
                     window: tuple[float, float] = (0.0, 0.06)) -> dict:
    """ISO/TS 18571 of surrogate pulses vs held-out CAE runs.

    A seeded ``fraction`` of the campaign's CAE runs is held out, a clone of ``surrogate`` (its
    settings) is fitted on the rest, and each held-out condition is rolled out with zero bias
    (``CAECurve.rollout``) on the run's own time grid and rated against the run over ``window`` (s).

    Returns
    -------
    dict
        ``run_ids`` (list of h), ``overall`` (ndarray, shape (h,)), ``fit_time_s`` and
        ``surrogate`` (the fitted clone).
    """
    ids = campaign.cae
    rng = np.random.default_rng(random_state)
    held_ids = [ids[i] for i in sorted(rng.choice(len(ids), size=round(fraction * len(ids)), replace=False))]
    train = [campaign.pulses[r] for r in ids if r not in set(held_ids)]
    surrogate = clone(surrogate).fit(train)
    scores = []
    for run_id in held_ids:
        p = campaign.pulses[run_id]
        c = surrogate.curve(p.v0, p.front_weight, p.rear_weight, p.meta.get("powertrain"), p.meta.get("drive"))
        traj = c.rollout(p.dt, p.time.size - 1)
        scores.append(iso_score_many(p.time, p.decel, traj.time, traj.decel, *window)["overall"][0])
    return {"run_ids": held_ids, "overall": np.array(scores), "fit_time_s": surrogate.fit_time_,
            "surrogate": surrogate}


def held_out(campaign, quick: bool) -> None:
    print("1. held-out CAE runs (10 %, seed 0), ISO/TS 18571 overall of surrogate vs run")
    print(f"{'setting':>14} {'fit_s':>6} {'mean60':>7} {'min60':>6} {'p05_60':>6} {'mean100':>7} "
          f"{'curve_ms':>8} {'rollout_ms':>10}")
    for name, kw in SETTINGS.items():
        if quick and name != "default":
            continue
        res = holdout_accuracy(campaign, CAESurrogate(random_state=0, **kw), 0.1, 0, (0.0, 0.06))
        sur = res["surrogate"]
        full, t_curve, t_roll = [], 0.0, 0.0
        for run_id in res["run_ids"]:
            p = campaign.pulses[run_id]
            t0 = time.perf_counter()
            c = sur.curve(p.v0, p.front_weight, p.rear_weight, p.meta["powertrain"], p.meta["drive"])
            t1 = time.perf_counter()
            traj = c.rollout(p.dt, p.time.size - 1)
            t_curve, t_roll = t_curve + t1 - t0, t_roll + time.perf_counter() - t1
            full.append(iso_score(p.time, p.decel, traj.time, traj.decel[0], 0.0, 0.1)["overall"])
        o, n = res["overall"], len(res["run_ids"])
        print(f"{name:>14} {res['fit_time_s']:6.1f} {o.mean():7.3f} {o.min():6.3f} {np.percentile(o, 5):6.3f} "
              f"{np.mean(full):7.3f} {1e3 * t_curve / n:8.1f} {1e3 * t_roll / n:10.1f}")
        if name == "default":
            worst = np.argsort(o)[:3]
            print("   worst:", ", ".join(f"{res['run_ids'][i]} (v0 {campaign.pulses[res['run_ids'][i]].v0:.1f} m/s) "
                                       f"{o[i]:.3f}" for i in worst))


def at_test_conditions(campaign) -> None:
    print("2. surrogate fitted on C0001..C1009 vs the unseen companions, ISO 0-60 ms")
    lhs = [campaign.pulses[r] for r in campaign.cae if not r.startswith("CT")]
    cpu = time.process_time()
    sur = CAESurrogate(random_state=0).fit(lhs)
    cpu = time.process_time() - cpu
    scores = []
    for test_id in campaign.tests:
        t, cae = campaign.pulses[test_id], campaign.companion(test_id)
        c = sur.curve(t.v0, t.front_weight, t.rear_weight, t.meta["powertrain"], t.meta["drive"])
        traj = c.rollout(cae.dt, cae.time.size - 1)
        scores.append(iso_score(cae.time, cae.decel, traj.time, traj.decel[0])["overall"])
        print(f"   {test_id} v0 {t.v0:5.2f} m/s  ISO {scores[-1]:.3f}  s_max surrogate {c.s_max:.3f} m, "
              f"companion {displacement_branches(cae).s_max:.3f} m")
    print(f"   mean {np.mean(scores):.3f}  min {np.min(scores):.3f}  (fit of 1009 runs: {sur.fit_time_:.1f} s wall, "
          f"{cpu:.1f} s CPU)")


def thinning(campaign) -> None:
    print("3. thinning: relative RMS of the bias rebuilt from n_grid points vs the full union (11 pairs)")
    pairs = [(displacement_branches(campaign.pulses[t]), displacement_branches(campaign.companion(t)))
             for t in campaign.tests]
    print(f"{'n_grid':>7} {'load_mean':>9} {'load_max':>8} {'unl_mean':>8} {'unl_max':>7}")
    for n_grid in (25, 50, 100, 200, 400, 800):
        row = []
        for name in ("loading", "unloading"):
            err = []
            for tb, cb in pairs:
                if getattr(cb, name) is None:
                    continue
                x, v, b = project_branch(getattr(tb, name), getattr(cb, name))
                xt, _, bt = thin(x, v, b, n_grid)
                err.append(np.sqrt(np.mean((np.interp(x, xt, bt) - b) ** 2) / np.mean(b**2)))
            row += [np.mean(err), np.max(err)]
        print(f"{n_grid:7d} {row[0]:9.4f} {row[1]:8.4f} {row[2]:8.4f} {row[3]:7.4f}")
    for n_grid in (200, None):
        t0 = time.perf_counter()
        data = bias_data(campaign, campaign.tests, inputs="state", n_grid=n_grid)
        print(f"   bias_data(11 tests, n_grid={n_grid}): {data.loading.y.size} loading + "
              f"{data.unloading.y.size} unloading rows in {1e3 * (time.perf_counter() - t0):.0f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="default surrogate settings only")
    args = parser.parse_args()
    t0 = time.perf_counter()
    campaign = build(resolve("paper"), seed=0)[0]
    print(f"paper campaign: {len(campaign.tests)} tests, {len(campaign.cae)} CAE runs "
          f"(built in {time.perf_counter() - t0:.1f} s)")
    held_out(campaign, args.quick)
    at_test_conditions(campaign)
    thinning(campaign)


if __name__ == "__main__":
    main()
