"""Cost of a fit against the size of the test library: wall time per part, peak memory, log-log slopes.

For each size N in ``--sizes`` a campaign of the second world is made in memory (``wide`` matrix:
N tests evenly spaced over 10-37 mph, Table 1's three configurations in turn, ``--n-cae`` Latin-
hypercube CAE runs, nothing withheld, seed 0) and, in a fresh process (so its peak RSS is its own):

surrogate_s   the CAE surrogate fitted on the CAE runs
fit_s         ``fit_model`` of ``--k`` / ``--inputs`` (the surrogate given), every training test
predict_s     ``predict`` at the median test's condition with ``--samples`` draws

and, inside fit_s, the cumulative time (cProfile) of the parts that grow with N:

data_s        bias data (projection and thinning of every test)
search_s      likelihood search (theta-bound candidates x restarts, ``choose_theta_bound``)
scatter_s     the test-to-test scatter's refits, one per training test (``scatter_needs``)
condition_s   conditioning on the data (``condition``, outside the scatter refits)
onset_s       the onset correction's input: its base model's held-out residuals
onset_gp_s    the onset correction's 1-D GP over time (its fit on the early rows)

rows (bias rows, both branches) and peak_GB (the process's peak RSS) follow; the last lines give
the log-log slope of each column between the smallest and the largest size (time ~ N^slope).
``--exact`` fits as before the caps: every row conditioned on, one scatter refit per test on
every other row (``max_condition_points=None``, ``scatter_needs(max_folds=None, max_rows=None)``).
Every figure is measured in this run.

    .venv/bin/python benchmarks/bench_scaling.py [--sizes 11 22 44 88] [--n-cae 400] [--exact] [--json]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import resource
import subprocess
import sys
import time

import numpy as np

PARTS = {  # column -> (module file suffix, function name) whose cumulative time it reports
    "data_s": ("method/model.py", "training_data"),
    "search_s": ("gp/optimise.py", "choose_theta_bound"),
    "scatter_s": ("gp/grouped.py", "scatter_needs"),
    "condition_s": ("gp/kriging.py", "_condition"),
    "onset_s": ("method/mixture.py", "grouped_residuals"),  # the base model's held-out residuals it learns
}
COLUMNS = ["tests", "rows", "surrogate_s", "fit_s", "predict_s", "data_s", "search_s", "scatter_s",
           "condition_s", "onset_s", "onset_gp_s", "peak_GB"]


def campaign(n_tests: int, n_cae: int):
    from crashfuse.world.multibody.generate import build  # benchmarks may use the world; method code never does
    from crashfuse.world.multibody.presets import resolve
    return build(resolve("withheld", ["none"]), seed=0, n_cae=n_cae, matrix="wide", n_tests=n_tests)[0]


def measure(n_tests: int, n_cae: int, k: int, inputs: str, n_samples: int, exact: bool = False) -> dict:
    """One size, in this process: the figures of one row."""
    import functools

    import crashfuse.gp.kriging
    from crashfuse.gp.grouped import scatter_needs
    from crashfuse.method.config import MethodConfig
    from crashfuse.method.model import fit_model, training_data
    from crashfuse.method.rollout import predict
    from crashfuse.method.surrogate import CAESurrogate

    camp = campaign(n_tests, n_cae)
    t0 = time.perf_counter()
    surrogate = CAESurrogate(random_state=0).fit(camp)
    t1 = time.perf_counter()
    config = MethodConfig(k=k, inputs=inputs, **({"max_condition_points": None} if exact else {}))
    if exact:
        crashfuse.gp.kriging.scatter_needs = functools.partial(scatter_needs, max_folds=None, max_rows=None)
    onset_gp = _time_onset_gp()
    profile = cProfile.Profile()
    profile.enable()
    model = fit_model(camp, config, surrogate=surrogate)
    profile.disable()
    t2 = time.perf_counter()
    test = camp.pulses[camp.tests[len(camp.tests) // 2]]
    predict(model, test.v0, test.front_weight, test.rear_weight, test.meta.get("powertrain"), test.meta.get("drive"),
            n_samples=n_samples, random_state=0)
    t3 = time.perf_counter()
    data = training_data(camp, camp.tests, config, surrogate)
    row = dict(tests=n_tests, rows=int(data.loading.y.size + data.unloading.y.size), surrogate_s=t1 - t0,
               fit_s=t2 - t1, predict_s=t3 - t2, **_parts(profile), **onset_gp)
    row["peak_GB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return row


def _parts(profile) -> dict:
    stats = pstats.Stats(profile).stats
    out = dict.fromkeys(PARTS, 0.0)
    for (path, _, name), (_, _, _, cumulative, _) in stats.items():
        for column, (suffix, func) in PARTS.items():
            if name == func and path.endswith(suffix):
                out[column] += cumulative  # each function is entered from outside itself only once here
    return out


def _time_onset_gp() -> dict:
    """Make the onset correction's GP add its fit time to the returned dict's ``onset_gp_s``."""
    import crashfuse.method.onset as onset

    spent = {"onset_gp_s": 0.0}

    class TimedGP(onset.ReplicateMeanGP):
        def fit(self, x, y, groups):
            t = time.perf_counter()
            try:
                return super().fit(x, y, groups)
            finally:
                spent["onset_gp_s"] += time.perf_counter() - t

    onset.ReplicateMeanGP = TimedGP
    return spent


def slopes(rows: list) -> dict:
    """log(column) against log(tests) between the first and the last row."""
    a, b = rows[0], rows[-1]
    ratio = np.log(b["tests"] / a["tests"])
    return {c: float(np.log(b[c] / a[c]) / ratio) for c in COLUMNS[1:] if a[c] > 0 and b[c] > 0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[11, 22, 44, 88])
    ap.add_argument("--n-cae", type=int, default=400)
    ap.add_argument("--k", type=int, default=1)
    ap.add_argument("--inputs", default="state")
    ap.add_argument("--samples", type=int, default=200)
    ap.add_argument("--exact", action="store_true", help="no caps: the fit as before them")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # a worker: one size, JSON out
    args = ap.parse_args(argv)
    if args.one is not None:
        print(json.dumps(measure(args.one, args.n_cae, args.k, args.inputs, args.samples, args.exact)))
        return 0
    rows = []
    for n in args.sizes:
        cmd = [sys.executable, __file__, "--one", str(n), "--n-cae", str(args.n_cae), "--k", str(args.k),
               "--inputs", args.inputs, "--samples", str(args.samples), *(["--exact"] if args.exact else [])]
        rows.append(json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.splitlines()[-1]))
        if not args.json:
            print(" ".join(f"{c}={rows[-1][c]:.3g}" for c in COLUMNS), flush=True)
    result = {"rows": rows, "slopes": slopes(rows) if len(rows) > 1 else {}}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print("log-log slope (smallest to largest size): "
              + ", ".join(f"{c} {s:.2f}" for c, s in result["slopes"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
