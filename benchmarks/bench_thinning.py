"""Training cost of the bias model vs number of bias points, and the held-out ISO cost of thinning.

Everything runs on real leave-one-test-out folds of a campaign (default: the `paper` campaign,
seed 0, generated in memory), with the CAE surrogate fitted once and shared, as in
:func:`crashfuse.evaluation.loto.evaluate`. A fold's bias models are both branches' GMM-GP models as
:func:`crashfuse.method.model.fit_model` fits them: hyperparameters by maximum likelihood on a seeded random
subset of each cluster (``max_fit_points``, 300 by default), then conditioned on every point of it.

Part 1 - fit cost. One fold (``--holdout``), K in ``--ks``: ``n_grid`` is chosen so that the fold
has about ``--targets`` bias points in all (loading + unloading), plus the full 12.5 kHz
projection (``n_grid=None``). Conditioning exactly on the full set needs, for the largest cluster
of n points, the n x n correlation matrix and its Cholesky copy (``exact_GiB = 2 * 8 n^2``): a
17k-point loading branch at K = 1 needs 4.1 GiB and ~1.5e12 flops. The ``full`` rows therefore use
a subset-of-data (SoD) approximation: the same subset hyperparameter fit, then conditioning on
a seeded random ``--full-cap`` points per cluster (``max_condition_points``). Where the largest
cluster needs at most ``--exact-limit-gib`` (K = 3 splits the loading branch), a ``full-exact``
row follows: the same hyperparameters, conditioned on every point - the SoD's cost, isolated.

Part 2 - ISO cost of thinning. Folds ``--folds``, ``n_grid`` in ``--grids`` (``full`` = the SoD
fit above, and ``full-exact`` where it fits): held-out ISO/TS 18571 ISO(0-60 ms) of the Monte
Carlo mean (``--samples`` draws), and three RMS differences d from the full projection b (the
bias as the model learns it: in m/s^2, or relative to the CAE deceleration with the relative
target), each divided by RMS(b) over the fold's training tests:

rel_data   the thinned training data, linearly interpolated back onto the full projection's
           points (what thinning alone loses; 0 unthinned)
rel_fit    the fitted bias model's mean at the training tests' full projection
rel_held   the fitted bias model's mean at the held-out test's full projection (its true bias;
           not divided by its own RMS, which is near zero for a low-speed test)

Columns of part 1: points (bias points fitted, both branches), fit_s (wall time of the fold fit,
projection included), peak_MiB (peak traced allocation, tracemalloc), n_max (largest cluster),
cond_max (most points one GP conditions on), exact_GiB (see above). Part 1 runs alone; part 2
runs its (fold, K) jobs in ``--jobs`` processes, so its fit_s include that contention. Every
figure is measured in this run; ``--json`` prints them as JSON instead of the tables.

    .venv/bin/python benchmarks/bench_thinning.py [CAMPAIGN] [--quick] [--jobs 2] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import resource
import sys
import time
import tracemalloc

import numpy as np
from joblib import Parallel, delayed

from crashfuse.method.mixture import GMMGPBias
from crashfuse.io.campaign import read_campaign
from crashfuse.signals.iso18571 import iso_score
from crashfuse.method.config import MethodConfig
from crashfuse.method.model import fit_model, training_data
from crashfuse.method.projection import BRANCHES, bias_data
from crashfuse.method.rollout import predict
from crashfuse.method.surrogate import CAESurrogate

FULL, EXACT = "full", "full-exact"  # n_grid labels of the unthinned rows: SoD, and exact where it fits
WINDOW_S = (0.0, 0.060)
SETTINGS = {  # full run (about 10 min on 2 busy cores) and --quick
    "full": dict(holdout="T06", folds=["T02", "T09"], ks=[1, 3], targets=[500, 1000, 2000, 4000, 8000],
                 grids=["50", "100", "200", "400", FULL], samples=100, full_cap=4000),
    "quick": dict(holdout="T06", folds=["T06"], ks=[1], targets=[500, 2000],
                  grids=["50", "200", FULL], samples=30, full_cap=2000),
}


def _campaign(folder):
    if folder:
        return read_campaign(folder)
    from crashfuse.world.generate import build  # benchmarks may use the world; method code never does
    from crashfuse.world.presets import resolve
    return build(resolve("paper"), seed=0)[0]


def _training(campaign, holdout: str) -> list[str]:
    return [t for t in campaign.tests if t != holdout]


def _traced(fn):
    """``fn()``, its wall time (s) and its peak traced allocation (MiB)."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        out = fn()
        wall = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()
    return out, wall, peak


def grid_for(counts, target: int) -> int:
    """The ``n_grid`` whose thinned total ``sum(min(n_grid, counts))`` is nearest ``target``.

    Parameters
    ----------
    counts : ndarray of int, shape (n_branch_tests,)
        Full-projection rows of each (branch, test); thinning keeps ``min(n_grid, count)``.
    target : int
        Wanted bias points in all.
    """
    grids = np.arange(2, counts.max() + 1)
    totals = np.minimum(grids[:, None], counts).sum(axis=1)
    return int(grids[np.argmin(np.abs(totals - target))])


def exact_gib(n: int) -> float:
    """GiB of the n x n correlation matrix and its Cholesky copy that exact conditioning on n points needs."""
    return 2 * 8 * n**2 / 2**30


def fold_fits(campaign, surrogate, k, holdout, n_grid, inputs="state", full_cap=4000, exact_limit_gib=1.5, seed=0,
              **bias_params):
    """The fold's model(s) at one ``n_grid``, each fit timed and traced.

    ``n_grid=None`` gives the SoD fit (label ``full``: conditioned on ``full_cap`` random points per
    cluster) and then, if its largest cluster needs at most ``exact_limit_gib`` (:func:`exact_gib`),
    the exact solve on every point with the same seeds, hence the same hyperparameters (``full-exact``).

    Yields
    ------
    label : int or str
        ``n_grid``, ``full`` or ``full-exact``.
    model : FittedModel
    fit_s : float
        Wall time of the fit, projection included (s).
    peak_mib : float
        Peak traced allocation of the fit (MiB).
    """
    def fit(n, **extra):
        config = MethodConfig(k=k, inputs=inputs, n_grid=n, random_state=seed, **{**bias_params, **extra})
        return _traced(functools.partial(fit_model, campaign, config, holdout=holdout, surrogate=surrogate))

    if n_grid is not None:
        yield (n_grid, *fit(n_grid))
        return
    sod = fit(None, max_condition_points=full_cap)
    yield (FULL, *sod)
    if exact_gib(_sizes(sod[0])[1]) <= exact_limit_gib:
        yield (EXACT, *fit(None, max_condition_points=None))


def _sizes(model) -> tuple[int, int, int]:
    """Bias points fitted, largest cluster and most points conditioned on, over both branches."""
    fitted = [getattr(est, "base_", est) for est in model.bias_.values() if est is not None]  # past the onset correction
    clusters = np.concatenate([est.n_points_per_cluster_ for est in fitted])
    cond = max(gp.n_condition_ for est in fitted for gp in est.gps_)
    return int(clusters.sum()), int(clusters.max()), int(cond)


def cost_rows(campaign, surrogate, holdout, ks, targets, inputs="state", full_cap=4000, exact_limit_gib=1.5, seed=0,
              **bias_params):
    """Part 1: fit time and peak memory of one fold vs bias points, and of the full set (:func:`fold_fits`).

    Returns
    -------
    list of dict
        Keys ``k, n_grid, points, fit_s, peak_mib, n_max, cond_max, exact_gib``.
    """
    full = bias_data(campaign, _training(campaign, holdout), inputs, n_grid=None, surrogate=surrogate)
    counts = np.concatenate([np.unique(full.branch(b).groups, return_counts=True)[1] for b in BRANCHES])
    grids = sorted({grid_for(counts, n) for n in targets}) + [None]
    rows = []
    for k in ks:
        for g in grids:
            for label, model, wall, peak in fold_fits(campaign, surrogate, k, holdout, g, inputs, full_cap,
                                                      exact_limit_gib, seed, **bias_params):
                points, n_max, cond = _sizes(model)
                rows.append(dict(k=k, n_grid=label, points=points, fit_s=wall, peak_mib=peak, n_max=n_max,
                                 cond_max=cond, exact_gib=exact_gib(n_max)))
                _say(f"cost K={k} n_grid={label}: {points} points, {wall:.1f} s")
    return rows


def _rms(a) -> float:
    return float(np.sqrt(np.mean(a**2)))


def _projection(campaign, surrogate, tests, model, n_grid):
    """Bias data of ``tests`` as ``model`` learnt them (inputs, target, weights), thinned to ``n_grid``."""
    return training_data(campaign, tests, dataclasses.replace(model.config, n_grid=n_grid), surrogate)


def fold_errors(campaign, surrogate, test_id, model, n_grid) -> dict:
    """``rel_data``, ``rel_fit`` and ``rel_held`` of a fold's model (see the module docstring)."""
    train = _training(campaign, test_id)
    full = _projection(campaign, surrogate, train, model, None)
    rel_data = 0.0 if n_grid is None else thinning_error(full, _projection(campaign, surrogate, train, model, n_grid))
    d_fit, b_fit = residuals(model, full)
    d_held = residuals(model, _projection(campaign, surrogate, [test_id], model, None))[0]
    return dict(rel_data=rel_data, rel_fit=_rms(d_fit) / _rms(b_fit), rel_held=_rms(d_held) / _rms(b_fit))


def thinning_error(full, thinned) -> float:
    """Relative RMS of the thinned data, interpolated per test and branch, against the full data."""
    diffs, refs = [], []
    for b in BRANCHES:
        f, t = full.branch(b), thinned.branch(b)
        for test in np.unique(f.groups):
            fi, ti = f.groups == test, t.groups == test
            diffs.append(np.interp(f.X[fi, 0], t.X[ti, 0], t.y[ti]) - f.y[fi])
            refs.append(f.y[fi])
    return _rms(np.concatenate(diffs)) / _rms(np.concatenate(refs))


def residuals(model, full) -> tuple[np.ndarray, np.ndarray]:
    """The model's bias mean minus full-projection bias data, and those data, both branches.

    Returns
    -------
    diff, bias : ndarray, shape (n_full,)
        Zero bias is predicted on a branch the model has no GP for.
    """
    diffs, refs = [], []
    for b in BRANCHES:
        est, d = model.bias_[b], full.branch(b)
        diffs.append((est.predict(d.X) if est is not None and d.y.size else 0.0) - d.y)
        refs.append(d.y)
    return np.concatenate(diffs), np.concatenate(refs)


def held_out_iso(model, pulse, n_samples, seed) -> float:
    """ISO(0-60 ms) of the Monte Carlo mean prediction against the held-out test (after contact)."""
    test = pulse.after_contact()
    pred = predict(model, test.v0, test.front_weight, test.rear_weight, test.meta.get("powertrain"),
                   test.meta.get("drive"), n_samples=n_samples, random_state=seed,
                   duration=float(test.time[-1]), dt=test.dt)
    return iso_score(test.time, test.decel, pred.time, pred.decel, *WINDOW_S)["overall"]


def cae_iso(campaign, test_id) -> float | None:
    """ISO(0-60 ms) of the test's companion CAE run (None without one)."""
    cae = campaign.companion(test_id)
    if cae is None:
        return None
    test, cae = campaign.pulses[test_id].after_contact(), cae.after_contact()
    return iso_score(test.time, test.decel, cae.time, cae.decel, *WINDOW_S)["overall"]


def thinning_rows(campaign, surrogate, folds, ks, grids, n_samples, inputs="state", full_cap=4000,
                  exact_limit_gib=1.5, seed=0, n_jobs=1, **bias_params):
    """Part 2: per fold, K and n_grid (None: :func:`fold_fits`), held-out ISO(0-60 ms) and relative RMS.

    Each (fold, K) is one job; ``n_jobs`` processes run them side by side (so ``fit_s`` here is
    measured under that contention; part 1 is the sequential cost).

    Returns
    -------
    list of dict
        Keys ``test_id, k, n_grid, points, fit_s, rel_data, rel_fit, rel_held, iso``, by fold, K, n_grid.
    """
    jobs = (delayed(_thinning_job)(campaign, surrogate, test_id, k, grids, n_samples, inputs, full_cap,
                                   exact_limit_gib, seed, bias_params) for test_id in folds for k in ks)
    return [row for rows in Parallel(n_jobs=n_jobs)(jobs) for row in rows]


def _thinning_job(campaign, surrogate, test_id, k, grids, n_samples, inputs, full_cap, exact_limit_gib, seed,
                  bias_params) -> list[dict]:
    rows = []
    for g in grids:
        for label, model, fit_s, _ in fold_fits(campaign, surrogate, k, test_id, g, inputs, full_cap,
                                                exact_limit_gib, seed, **bias_params):
            iso = held_out_iso(model, campaign.pulses[test_id], n_samples, seed)
            rows.append(dict(test_id=test_id, k=k, n_grid=label, points=_sizes(model)[0], fit_s=fit_s,
                             **fold_errors(campaign, surrogate, test_id, model, g), iso=iso))
            _say(f"thinning {test_id} K={k} n_grid={label}: ISO(0-60) {iso:.3f}")
    return rows


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _print_tables(result: dict) -> None:
    s = result["settings"]
    print(f"Part 1 - fit cost of one fold (hold out {s['holdout']}, {s['inputs']} inputs); 'full' = SoD, "
          f"hyperparameters on {s['max_fit_points']}/cluster, conditioned on {s['full_cap']} random "
          "points/cluster")
    print(f"{'K':>2} {'n_grid':>10} {'points':>7} {'fit_s':>7} {'peak_MiB':>9} {'n_max':>6} {'cond_max':>8} "
          f"{'exact_GiB':>9}")
    for r in result["cost"]:
        print(f"{r['k']:>2} {r['n_grid']:>10} {r['points']:>7} {r['fit_s']:7.2f} {r['peak_mib']:9.0f} "
              f"{r['n_max']:>6} {r['cond_max']:>8} {r['exact_gib']:9.2f}")
    print(f"\nPart 2 - ISO cost of thinning ({s['samples']} Monte Carlo samples); CAE ISO(0-60): "
          + ", ".join(f"{t} {v:.3f}" for t, v in result["cae_iso"].items() if v is not None))
    print(f"{'test':>5} {'K':>2} {'n_grid':>10} {'points':>7} {'fit_s':>6} {'rel_data':>8} {'rel_fit':>7} "
          f"{'rel_held':>8} {'ISO0-60':>7}")
    for r in result["thinning"]:
        print(f"{r['test_id']:>5} {r['k']:>2} {r['n_grid']:>10} {r['points']:>7} {r['fit_s']:6.2f} "
              f"{r['rel_data']:8.3f} {r['rel_fit']:7.3f} {r['rel_held']:8.3f} {r['iso']:7.3f}")
    print("\nmean over folds")
    print(f"{'K':>2} {'n_grid':>10} {'fit_s':>6} {'rel_data':>8} {'rel_fit':>7} {'rel_held':>8} {'ISO0-60':>7} "
          f"{'min ISO':>7}")
    for (k, g), rows in _by_setting(result["thinning"]).items():
        mean = {c: np.mean([r[c] for r in rows]) for c in ("fit_s", "rel_data", "rel_fit", "rel_held", "iso")}
        print(f"{k:>2} {g:>10} {mean['fit_s']:6.2f} {mean['rel_data']:8.3f} {mean['rel_fit']:7.3f} "
              f"{mean['rel_held']:8.3f} {mean['iso']:7.3f} {min(r['iso'] for r in rows):7.3f}")
    print(f"\ntotal {result['wall_s']:.0f} s; peak RSS {result['peak_rss_mib']:.0f} MiB")


def _by_setting(rows) -> dict:
    """Rows grouped by (K, n_grid), in first-seen order."""
    out = {}
    for r in rows:
        out.setdefault((r["k"], r["n_grid"]), []).append(r)
    return dict(sorted(out.items(), key=lambda kv: kv[0][0]))


def _grid(text: str):
    return None if text == FULL else int(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("campaign", nargs="?")
    ap.add_argument("--quick", action="store_true", help="one fold, K=1, three grids")
    ap.add_argument("--holdout", help="the fold of part 1")
    ap.add_argument("--folds", nargs="+", help="held-out tests of part 2")
    ap.add_argument("--ks", type=int, nargs="+")
    ap.add_argument("--targets", type=int, nargs="+", help="bias points in all, part 1")
    ap.add_argument("--grids", nargs="+", help=f"n_grid values of part 2 ('{FULL}': no thinning, SoD)")
    ap.add_argument("--samples", type=int)
    ap.add_argument("--full-cap", type=int, help="points per cluster the full-set fit conditions on")
    ap.add_argument("--exact-limit-gib", type=float, default=1.5,
                    help="also solve the full set exactly when its largest cluster needs at most this")
    ap.add_argument("--inputs", default="state", choices=("paper", "state"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2, help="processes for part 2 (part 1 runs alone)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON instead of tables")
    args = ap.parse_args(argv)
    s = {key: getattr(args, key) if getattr(args, key) is not None else val
         for key, val in SETTINGS["quick" if args.quick else "full"].items()}
    s.update(inputs=args.inputs, seed=args.seed, exact_limit_gib=args.exact_limit_gib, jobs=args.jobs,
             max_fit_points=GMMGPBias().max_fit_points)
    t0 = time.perf_counter()
    campaign = _campaign(args.campaign)
    surrogate = CAESurrogate(random_state=args.seed).fit(campaign)
    common = dict(inputs=args.inputs, full_cap=s["full_cap"], exact_limit_gib=args.exact_limit_gib,
                  seed=args.seed)
    cost = cost_rows(campaign, surrogate, s["holdout"], s["ks"], s["targets"], **common)
    thinning = thinning_rows(campaign, surrogate, s["folds"], s["ks"], [_grid(g) for g in s["grids"]],
                             s["samples"], n_jobs=args.jobs, **common)
    result = dict(settings=s, cost=cost, thinning=thinning, cae_iso={t: cae_iso(campaign, t) for t in s["folds"]},
                  wall_s=time.perf_counter() - t0,
                  peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        _print_tables(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
