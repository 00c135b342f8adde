"""Fit cost of the bias model vs number of bias points, and the accuracy cost of its approximations.

Synthetic bias data shaped like the real thing: ``n_tests`` tests, each a displacement grid
``s`` with constant ``v0, w_f, w_r`` (4-D inputs), bias a smooth function of ``(s, v0)``
plus noise. Prints one table; every row is measured in this run.

Columns
-------
fit_s        wall time of one ``fit``
peak_MiB     peak traced allocation during that fit (tracemalloc)
rmse         RMSE (m/s^2) against the true bias function on two held-out tests
d_ref        RMSE (m/s^2) of the prediction difference to the first row of that n (the exact
             fit up to 2000 points, hyperparameters on a subset but conditioned on all above)

Usage::

    .venv/bin/python benchmarks/bench_bias.py                  # 500 ... 8000
    .venv/bin/python benchmarks/bench_bias.py --sizes 25000    # full 12.5 kHz scale, approximations only
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from crashfuse.gp.kriging import KrigingGP
from crashfuse.method.mixture import GMMGPBias

EXACT_MAX = 2000  # full-data MLE beyond this takes minutes per fit


def true_bias(s, v0):
    """Bias (m/s^2) vs displacement s (m) and impact speed v0 (m/s)."""
    return 40 * np.sin(6 * s) * (v0 / 12) ** 2 - 25 * s * (v0 > 12)


def make_tests(n_points, n_tests=10, seed=0):
    """Bias data from ``n_tests`` tests, ``n_points`` in all, and two held-out tests.

    Returns
    -------
    X : ndarray, shape (n_points, 4)   [s m, v0 m/s, w_f kg, w_r kg]
    y : ndarray, shape (n_points,)     bias m/s^2
    X_test : ndarray, shape (400, 4)
    y_test : ndarray, shape (400,)     noise-free truth
    """
    rng = np.random.default_rng(seed)

    def one(v0, m):
        s = np.linspace(0, 0.04 * v0, m)
        w = rng.uniform([900, 700], [1300, 1000])
        return np.column_stack([s, np.full(m, v0), np.full(m, w[0]), np.full(m, w[1])])

    speeds = np.linspace(7, 17, n_tests)
    X = np.vstack([one(v, n_points // n_tests) for v in speeds])
    y = true_bias(X[:, 0], X[:, 1]) + 1.0 * rng.standard_normal(len(X))
    X_test = np.vstack([one(v, 200) for v in (9.3, 14.6)])
    return X, y, X_test, true_bias(X_test[:, 0], X_test[:, 1])


def measure(model, X, y, X_test):
    """Fit time (s), peak traced memory (MiB) and test predictions of ``model``."""
    tracemalloc.start()
    t0 = time.perf_counter()
    model.fit(X, y)
    fit_s = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return fit_s, peak, model.predict(X_test)


def configurations(n):
    """(name, estimator) pairs measured at ``n`` points."""
    rows = []
    if n <= EXACT_MAX:
        rows.append(("exact (MLE on all, condition on all)", KrigingGP(max_fit_points=None, random_state=0)))
    if n <= 8000:
        rows += [("default (MLE on 300, condition on all)", KrigingGP(random_state=0)),
                 ("GMMGPBias K=3 on v0 (default GPs)", GMMGPBias(n_clusters=3, cluster_inputs=[1], random_state=0))]
    if n > 2000:
        rows.append(("SoD (MLE on 300, condition on 2000)", KrigingGP(max_condition_points=2000, random_state=0)))
    if n > 4000:
        rows += [("SoD (MLE on 300, condition on 4000)", KrigingGP(max_condition_points=4000, random_state=0)),
                 ("GMMGPBias K=3 on v0, condition <= 2000/cluster",
                  GMMGPBias(n_clusters=3, cluster_inputs=[1], max_condition_points=2000, random_state=0))]
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[500, 1000, 2000, 4000, 8000])
    args = parser.parse_args(argv)
    print(f"{'n':>6}  {'configuration':<47} {'fit_s':>7} {'peak_MiB':>9} {'rmse':>7} {'d_ref':>7}")
    for n in args.sizes:
        X, y, X_test, y_test = make_tests(n)
        reference = None
        for name, model in configurations(n):
            fit_s, peak, pred = measure(model, X, y, X_test)
            reference = pred if reference is None else reference
            rmse = np.sqrt(np.mean((pred - y_test) ** 2))
            d_ref = np.sqrt(np.mean((pred - reference) ** 2))
            print(f"{n:>6}  {name:<47} {fit_s:7.2f} {peak:9.0f} {rmse:7.3f} {d_ref:7.3f}", flush=True)


if __name__ == "__main__":
    main()
