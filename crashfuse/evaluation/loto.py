"""Leave-one-test-out evaluation: ISO/TS 18571 table, per-fold predictions, band coverage.

For every input mode, every K and every test of the campaign, one fold: the bias models are fitted
on the other tests only (the CAE surrogate is fitted ONCE on the CAE runs, which contain no test
data, and shared by every fold), the held-out test's condition is predicted
(:func:`crashfuse.method.rollout.predict`) and the Monte Carlo mean is rated against the held-out (CFC 60)
test over 0-20, 0-40 and 0-60 ms (or the windows asked for). The ``CAE`` rows rate the test's companion
CAE run (the surrogate's zero-bias pulse where a test has none). Folds run in parallel processes (joblib/loky).

Band coverage: the fraction of held-out test samples in 0-60 ms inside the reported 95 % band
(``band='test'`` by default: where a new test is expected, :func:`crashfuse.method.rollout.predict`), and
inside the latent band (the bias function's uncertainty alone) beside it.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import os
import pickle
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
from joblib import Parallel, delayed, effective_n_jobs

from crashfuse.errors import InputError
from crashfuse.evaluation.iso_table import AUTO, COLUMNS, WINDOWS, effects_label
from crashfuse.evaluation.fold import (AUTO_INPUTS, COVERAGE_COLUMNS, auto_facts, cae_pulse, cae_rows, check_windows,
                                       rollout_fold, score_fold)
from crashfuse.evaluation.records import fold_folder, write_fold_json
from crashfuse.io.atomic import atomic_path
from crashfuse.io.campaign import Campaign
from crashfuse.method.config import MethodConfig
from crashfuse.method.hybrid import fit_physics
from crashfuse.method.model import fit_model
from crashfuse.method.projection import INPUTS
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.units import G0



@dataclasses.dataclass(frozen=True)
class Evaluation:
    """Result of :func:`evaluate`.

    Attributes
    ----------
    iso_table : DataFrame
        Columns :data:`crashfuse.evaluation.iso_table.COLUMNS`; one row per test, input mode, model (CAE, K1, ...) and window.
    coverage : DataFrame
        Columns ``COVERAGE_COLUMNS``: per fold, the fraction of held-out test points in 0-60 ms inside
        the reported 95 % band (``coverage``) and inside the latent band (``coverage_latent``), the
        extrapolation flag, the GPs per branch, how often the selected GP changes
        along the mean-function rollout, the fold's fit and predict times (s), ``auto``'s inner error and
        the hybrid's effects fitted (``+``-joined, ``none``; empty without the hybrid).
    predictions : dict of (str, str, str) to DataFrame
        Per fold ``(inputs, model, test_id)``: the prediction table (:meth:`Prediction.frame`) with
        the held-out test's deceleration (``test_decel_g``) beside it.
    records : dict of (str, str, str) to FoldRecord
        Per fold, its tracking record (:mod:`crashfuse.evaluation.records`, docs/tracking.md).
    wall_time : float
        Seconds for the whole evaluation.
    """

    iso_table: pd.DataFrame
    coverage: pd.DataFrame
    predictions: dict
    records: dict
    wall_time: float


def evaluate(campaign: Campaign, ks=(1, 2, 3), inputs=INPUTS, out: str | os.PathLike | None = None,
             n_samples: int = 1000, random_state: int = 0, n_jobs: int = 2, surrogate: CAESurrogate | None = None,
             holdout=None, progress: Callable[[str], None] | None = print, band: str = "test",
             auto=False, windows=WINDOWS, **settings) -> Evaluation:
    """Every leave-one-test-out fold for each K in ``ks`` and each input mode.

    Parameters
    ----------
    campaign : Campaign
        Tests (CFC 60 as read) and CAE runs.
    ks : sequence of int
        Mixture sizes K.
    inputs : sequence of {"paper", "state"}
    out : path, optional
        Folder for ``iso_table.csv``, ``coverage.csv`` and, per fold, ``<inputs>/K<k>/<test>/`` with
        ``<test>_prediction.csv`` and ``<test>.fold.json`` (docs/tracking.md); each file atomic. The
        fold figures the fold JSON names are drawn by :func:`crashfuse.reporting.plots.plot_evaluation`.
    n_samples : int
        Monte Carlo samples per prediction.
    random_state : int
        Seeds the surrogate, every fold's bias models and draws.
    n_jobs : int
        Worker processes for the folds.
    surrogate : CAESurrogate, optional
        Already fitted on this campaign's CAE runs; fitted here otherwise.
    holdout : str or sequence of str, optional
        Run only the folds holding out these tests (default: every test), e.g. one fold per job.
    progress : callable, optional
        Receives one line per finished fold.
    band : {"test", "latent"}
        The reported band (:func:`crashfuse.method.rollout.predict`) that ``coverage`` measures; the latent
        band's coverage is recorded either way.
    auto : bool or sequence of {"paper", "state"}
        Also the ``auto`` model: per held-out test, among the folds of these input modes (True: ``state``,
        :data:`AUTO_INPUTS`) and every K, the one whose bias model predicts its training tests best
        (:func:`crashfuse.method.selection.inner_error`, the simplest unless a more complex candidate
        removes 10 % of the error: :func:`crashfuse.method.selection.choose`); its rows are labelled
        ``auto`` for both ``inputs`` and ``model``, its fold JSON names the choice.
    windows : sequence of str
        ISO/TS 18571 windows ``'<start>-<end>'`` in ms (default the paper's 0-20, 0-40 and 0-60); the
        progress lines name the last.
    **settings
        Further :class:`crashfuse.method.config.MethodConfig` settings of every fold (``assignment``,
        ``extra_inputs``, ``n_grid``, ``use_companion``, ``target``, ``weights``, ``velocity``, ``trend``,
        ``pooled``, ``onset`` and ``shrink`` - the state folds' only: the paper inputs carry no time - and the
        GMMGPBias settings such as ``theta_max_candidates`` or ``calibrate_variance``); None for
        ``target``, ``trend``, ``pooled``, ``onset``, ``shrink`` or ``use_companion`` keeps each input mode's default.

    Returns
    -------
    Evaluation
    """
    t0 = time.perf_counter()
    ks, inputs = _check_grid(ks, inputs)
    windows = check_windows(windows)
    configs = fold_configs(ks, inputs, random_state, settings)
    tests = _held_out(campaign, holdout)
    surrogate = surrogate or CAESurrogate(random_state=random_state).fit(campaign)
    say = progress or (lambda line: None)
    physics = _physics(campaign, surrogate, tests, next(iter(configs.values())).effects, n_jobs, say)
    auto_modes = _auto_modes(auto, inputs)
    ascending = sorted(ks)
    keys = list(itertools.product(inputs, tests))
    chains = [([configs[mode, k] for k in ascending], t, physics[t]) for mode, t in keys]
    n_folds = len(ks) * len(chains)
    say(f"evaluate: {n_folds} folds ({len(tests)} tests x K {list(ks)} x {list(inputs)}), {n_jobs} jobs")
    done, n = {}, 0
    for key, chain in zip(keys, _run_chains(campaign, surrogate, chains, n_jobs,
                                                       (n_samples, band, windows, auto_modes))):
        done[key] = chain
        for res in chain:
            n, cov = n + 1, res["coverage"]
            say(f"[{n}/{n_folds}] {cov['inputs']} {cov['model']} {cov['test_id']}: "
                f"ISO({windows[-1]}) {res['iso'][-1]['overall']:.3f}, coverage {cov['coverage']:.2f}, "
                f"fit {cov['fit_s']:.1f} s")
    results = [done[mode, t][ascending.index(k)] for mode in inputs for k in ks for t in tests]
    if auto_modes:
        chosen = [_auto_fold(campaign, surrogate, [r for r in results if r["coverage"]["test_id"] == t
                                                   and r["coverage"]["inputs"] in auto_modes], auto_modes, windows)
                  for t in tests]
        say("auto: " + ", ".join(f"{r['coverage']['test_id']} {r['record'].settings['chosen']}" for r in chosen))
        results += chosen
    modes = [*inputs, AUTO] if auto_modes else inputs
    baseline = [row for t in tests for mode in modes for row in cae_rows(campaign, surrogate, t, mode, windows)]
    iso = pd.DataFrame(baseline + [r for res in results for r in res["iso"]], columns=list(COLUMNS))
    coverage = pd.DataFrame([res["coverage"] for res in results], columns=COVERAGE_COLUMNS)
    keys = [(r["coverage"]["inputs"], r["coverage"]["model"], r["coverage"]["test_id"]) for r in results]
    predictions = {key: r["frame"] for key, r in zip(keys, results)}
    records = {key: r["record"] for key, r in zip(keys, results)}
    result = Evaluation(iso, coverage, predictions, records, time.perf_counter() - t0)
    if out is not None:
        write_evaluation(result, out)
    say(f"evaluate: done in {result.wall_time:.1f} s")
    return result


def _auto_modes(auto, inputs) -> tuple:
    """The input modes the auto model chooses among (empty without it); InputError if one is not evaluated."""
    if auto is False or auto is None:
        return ()
    modes = AUTO_INPUTS if auto is True else ((auto,) if isinstance(auto, str) else tuple(auto))
    missing = [m for m in modes if m not in inputs]
    if not modes or missing:
        raise InputError(f"the auto model chooses among evaluated input modes {list(inputs)}, got {list(modes)}",
                         field="auto")
    return modes


def _held_out(campaign: Campaign, holdout) -> list[str]:
    """The tests to hold out one at a time, in table order."""
    tests = campaign.tests
    if len(tests) < 2:
        raise InputError(f"leave-one-test-out needs at least 2 tests, got {len(tests)}", campaign.root, "source")
    if holdout is None:
        return tests
    wanted = {holdout} if isinstance(holdout, str) else set(holdout)
    unknown = sorted(wanted - set(tests))
    if unknown or not wanted:
        raise InputError(f"expected test run_ids among {tests}, got {sorted(wanted)}", campaign.root, "holdout")
    return [t for t in tests if t in wanted]


def _check_grid(ks, inputs):
    ks = list(ks)
    if not ks or any(isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1 for k in ks):
        raise InputError(f"expected integers K >= 1, got {ks}", field="k")
    inputs = [inputs] if isinstance(inputs, str) else list(inputs)
    bad = [m for m in inputs if m not in INPUTS]
    if not inputs or bad:
        raise InputError(f"expected input modes among {INPUTS}, got {inputs}", field="inputs")
    return ks, inputs


STATE_ONLY = ("onset", "shrink")  # settings over the time since contact, which the paper inputs lack


def fold_configs(ks, inputs, random_state: int, settings: dict) -> dict:
    """The :class:`MethodConfig` of every (input mode, K); ``onset`` and ``shrink`` apply to the state folds only.

    Raises
    ------
    InputError
        A bad setting (naming it), before any fold runs.
    """
    out = {}
    for mode in inputs:
        given = {name: value for name, value in settings.items() if mode == "state" or name not in STATE_ONLY}
        for k in ks:
            out[mode, k] = MethodConfig(k=k, inputs=mode, random_state=random_state, **given)
    return out


def _physics(campaign, surrogate, tests, effects, n_jobs, say) -> dict:
    """Per held-out test, the hybrid's effect laws fitted on the other tests (None without effects): one
    fit shared by that test's folds of every K and input mode."""
    if not effects:
        return dict.fromkeys(tests)
    say(f"evaluate: effect laws ({effects_label(effects)}) fitted per held-out test, {n_jobs} jobs")
    trains = [[r for r in campaign.tests if r != t] for t in tests]
    fits = Parallel(n_jobs=n_jobs)(delayed(fit_physics)(campaign, train, effects, surrogate) for train in trains)
    for t, fit in zip(tests, fits):
        say(f"  without {t}: {effects_label(fit.effects)}")
    return dict(zip(tests, fits))


def _run_chains(campaign, surrogate, chains, n_jobs, settings):
    """``_chain`` of every ``(configs, test_id, physics)`` in ``chains``, in order, on ``n_jobs`` processes.

    The campaign and the surrogate (120 MB pickled for the 1031-run ``paper`` campaign) reach each
    worker process once, through a temporary pickle: passed with every fold, pickling and unpickling
    them cost about 0.13 s CPU a fold.
    """
    if effective_n_jobs(n_jobs) == 1:
        yield from (_chain(campaign, surrogate, *chain, *settings) for chain in chains)
        return
    with tempfile.TemporaryDirectory(prefix="crashfuse-evaluate-") as tmp:
        shared = os.path.join(tmp, "campaign-surrogate.pkl")
        with open(shared, "wb") as fh:
            pickle.dump((campaign, surrogate), fh, protocol=pickle.HIGHEST_PROTOCOL)
        yield from Parallel(n_jobs=n_jobs, return_as="generator")(
            delayed(_shared_chain)(shared, *chain, *settings) for chain in chains)


def _shared_chain(shared, *chain_and_settings) -> list:
    """``_chain`` with the campaign and surrogate from the pickle ``shared`` (loaded once per process)."""
    return _chain(*_load_shared(shared), *chain_and_settings)


@functools.lru_cache(maxsize=1)
def _load_shared(path):
    with open(path, "rb") as fh:
        return pickle.load(fh)


def _chain(campaign, surrogate, configs, test_id, physics, *settings) -> list:
    """The folds of one input mode and held-out test, K ascending: a K > 1 model takes the pooled GP and
    the measurement chain of the K before it (:meth:`FittedModel.all_rows_gps`, :attr:`FittedModel.chain`:
    the same fits), so each is fitted once per fold."""
    out, pooled, mount = [], None, None
    for config in configs:
        res = _fold(campaign, surrogate, config, test_id, physics, *settings, pooled=pooled, chain=mount)
        model = res.pop("model")
        pooled, mount = model.all_rows_gps(), model.chain
        out.append(res)
    return out


def _fold(campaign, surrogate, config: MethodConfig, test_id, physics, n_samples, band, windows=WINDOWS,
          auto_modes=(), pooled=None, chain=None) -> dict:
    """Fit ``config`` without ``test_id`` (with the hybrid's ``physics`` fitted without it, if any, and
    the ``pooled`` GPs and measurement ``chain`` of another K's fit), roll out its condition and score it
    (:mod:`crashfuse.evaluation.fold`, the workflow's three steps in one process); the fit's inner
    error too where its input mode is among ``auto_modes``."""
    model = fit_model(campaign, config, holdout=test_id, surrogate=surrogate, physics=physics, pooled=pooled,
                      chain=chain)
    return {**scored_fold(model, campaign, surrogate, test_id, n_samples, band, config.inputs in auto_modes, windows),
            "model": model}


def scored_fold(model, campaign, surrogate, test_id, n_samples, band="test", inner=False, windows=WINDOWS) -> dict:
    """A fitted fold model's rollout of its held-out test, scored over ``windows``: ``iso``, ``coverage``,
    ``record`` (as :func:`crashfuse.evaluation.fold.score_fold`), ``facts`` and ``frame`` (the prediction table
    with the test's deceleration)."""
    pred, facts = rollout_fold(model, campaign, test_id, n_samples, band, inner)
    frame = pred.frame()
    scored = score_fold(campaign, test_id, frame, facts, windows, cae=cae_pulse(campaign, surrogate, test_id))
    frame["test_decel_g"] = np.interp(pred.time, *_test_decel(campaign, test_id)) / G0
    return {"iso": scored["iso"], "coverage": scored["coverage"], "frame": frame, "record": scored["record"],
            "facts": facts}


def _test_decel(campaign, test_id):
    test = campaign.pulses[test_id].after_contact()
    return test.time, test.decel


def _auto_fold(campaign, surrogate, candidates: list, inputs: list, windows) -> dict:
    """The ``auto`` fold of one held-out test: the candidate fold :func:`auto_facts` picks, scored under its label."""
    index, facts = auto_facts([c["facts"] for c in candidates], inputs)
    test_id, frame = facts["test_id"], candidates[index]["frame"]
    scored = score_fold(campaign, test_id, frame, facts, windows, cae=cae_pulse(campaign, surrogate, test_id))
    return {"iso": scored["iso"], "coverage": scored["coverage"], "frame": frame, "record": scored["record"],
            "facts": facts}


def write_evaluation(result: Evaluation, out: str | os.PathLike) -> Path:
    """Write the evaluation's tables and fold files into ``out``, each file atomically.

    ``iso_table.csv``, ``coverage.csv``, and per fold ``<inputs>/K<k>/<test>/`` with
    ``<test>_prediction.csv`` and ``<test>.fold.json``. Fold files come first, the tables last:
    a complete ``iso_table.csv`` means complete data. The fold figures (``<test>.png``) are the
    reporting layer's: :func:`crashfuse.reporting.plots.plot_evaluation`.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("expected a folder for the evaluation outputs, found a file", out, "out")
    for key, frame in result.predictions.items():
        folder = fold_folder(out, *key)
        _write_csv(frame, folder / f"{key[2]}_prediction.csv")
        write_fold_json(folder / f"{key[2]}.fold.json", result.records[key])
    _write_csv(result.coverage, out / "coverage.csv")
    _write_csv(result.iso_table, out / "iso_table.csv")
    return out


def _write_csv(frame: pd.DataFrame, path: Path) -> None:
    with atomic_path(path) as tmp:
        frame.to_csv(tmp, index=False, float_format="%.6g")
