"""One leave-one-test-out fold as the method's steps: train, rollout, score.

:func:`crashfuse.evaluation.loto.evaluate` runs the three in one process per fold; the workflow runs
each as its own job (``crashfuse fit`` -> ``crashfuse rollout`` -> ``crashfuse score``), so that a
change to the scoring windows reruns only the scores and a change to the Monte Carlo samples only
the rollouts. Between rollout and score travel the prediction CSV and the rollout's facts
(``<test>.rollout.json``: the model's settings and the fit's and rollout's diagnostics), so a
score needs neither the model file nor the GP libraries.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

from crashfuse.errors import InputError
from crashfuse.evaluation.iso_table import AUTO, BASELINE, SCORES, WINDOWS, effects_label, model_label, window_bounds
from crashfuse.evaluation.records import FoldRecord
from crashfuse.io.atomic import write_text
from crashfuse.io.tables import read_json
from crashfuse.signals.iso18571 import iso_score
from crashfuse.units import G0, MS

__all__ = ["ROLLOUT_SUFFIX", "rollout_fold", "write_rollout_facts", "read_rollout_facts", "auto_facts", "score_fold",
           "cae_rows", "band_coverage", "COVERAGE_WINDOW_MS", "COVERAGE_COLUMNS", "AUTO_INPUTS"]

ROLLOUT_SUFFIX = ".rollout.json"
COVERAGE_WINDOW_MS = (0, 60)
# The input modes the auto model chooses among by default: the paper mode's inner error looked as good
# where its held-out test then lost (docs/decisions.md, section 23).
AUTO_INPUTS = ("state",)
COVERAGE_COLUMNS = ["test_id", "inputs", "model", "coverage", "coverage_latent", "n_points", "extrapolation",
                    "n_gps_loading", "n_gps_unloading", "cluster_switches", "fit_s", "predict_s", "inner_error",
                    "effects_fitted", "chosen"]
_FACT_KEYS = ("test_id", "inputs", "k", "model", "seed", "campaign", "settings", "metrics")


def rollout_fold(model, campaign, test_id: str, n_samples: int, band: str = "test", inner: bool = False):
    """Predict the held-out test's condition with ``model`` (fitted without it) over its record.

    Parameters
    ----------
    model : FittedModel
    campaign : Campaign
    test_id : str
    n_samples : int
        Monte Carlo samples.
    band : {"test", "latent"}
    inner : bool
        Also the model's inner error on its training tests (:func:`crashfuse.method.selection.inner_error`),
        what the ``auto`` model chooses by.

    Returns
    -------
    prediction : Prediction
    facts : dict
        What the score needs besides the prediction table: ``test_id, inputs, k, model, seed,
        campaign, settings``, ``metrics`` (fit and predict seconds, cluster switches, GPs per
        branch, extrapolation flag, and ``inner_error`` with ``inner``) and ``run_time`` (``start``:
        the fit's start, ``end``: now, UNIX seconds; empty for a model that does not know its start);
        JSON-ready.
    """
    from crashfuse.method.rollout import predict  # the GP stack: not for a score job
    from crashfuse.method.selection import inner_error

    if test_id not in model.holdout:
        raise InputError(f"expected a model fitted without {test_id} (its holdout is {model.holdout})",
                         field="test")
    test = campaign.pulses[test_id].after_contact()
    t0 = time.perf_counter()
    pred = predict(model, test.v0, test.front_weight, test.rear_weight, test.meta.get("powertrain"),
                   test.meta.get("drive"), n_samples=n_samples, random_state=model.config.random_state,
                   duration=float(test.time[-1]), dt=test.dt, band=band)
    seconds = time.perf_counter() - t0
    config = model.config
    settings = {**fold_settings(config, n_samples), "band": band}
    if model.physics is not None:
        settings["effects_fitted"] = effects_label(model.physics.effects)
    if model.chain is not None:
        settings.update(chain_f_res_hz=model.chain.f_res_, chain_zeta=model.chain.zeta_res_)
    metrics = {"fit_seconds": float(model.fit_seconds), "predict_seconds": seconds,
               "cluster_switches": float(cluster_switches(model, pred)),
               "n_gps_loading": float(_n_gps(model, "loading")), "n_gps_unloading": float(_n_gps(model, "unloading")),
               "extrapolation": float(pred.extrapolation["any"])}
    if inner:
        metrics["inner_error"] = inner_error(model, campaign)
    facts = {"test_id": test_id, "inputs": config.inputs, "k": int(config.k),
             "model": model_label(config.k, effects_label(config.effects)), "seed": int(config.random_state),
             "campaign": {"name": campaign.root.name if campaign.root else "campaign", "hash": model.campaign_hash},
             "settings": settings, "metrics": metrics,
             "run_time": {"start": model.fit_started, "end": time.time()} if model.fit_started else {}}
    return pred, facts


def fold_settings(config, n_samples: int) -> dict:
    """A fold's settings as the fold JSON's scalars (docs/tracking.md).

    K, the input mode and the seed have their own fields there. The GMMGPBias settings appear
    only where they differ from the bias model's defaults, as ``bias_<name>`` (tuples as text).
    """
    from crashfuse.method.config import BIAS_SETTINGS  # the GP stack: not for a score job

    own = {"k", "inputs", "random_state", *BIAS_SETTINGS}
    flat = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name not in own}
    flat["effects"] = effects_label(config.effects)
    flat.update({f"bias_{k}": v if isinstance(v, (str, bool, int, float)) or v is None else str(v)
                 for k, v in config.changed_bias_settings().items()})
    return {**flat, "n_samples": int(n_samples)}


def _n_gps(model, branch) -> int:
    est = model.bias_.get(branch)
    return 0 if est is None else len(est.gps_)


def cluster_switches(model, pred) -> int:
    """How often the most responsible GP changes along the mean-function rollout (both branches).

    With ``assignment='select'`` each change is a switch of the bias function along the pulse.

    Parameters
    ----------
    model : FittedModel
    pred : Prediction

    Returns
    -------
    int
    """
    from crashfuse.method.projection import BRANCHES

    path = pred.mean_path
    cond = model.condition(**pred.condition)
    count = 0
    for branch in BRANCHES:
        est, (on, x, v) = model.bias_.get(branch), path.on_branch(branch)
        if est is None or on.sum() < 2:
            continue
        resp = est.predict_responsibilities(model.features(branch, x, v, cond))
        count += int(np.count_nonzero(np.diff(np.argmax(resp, axis=1))))
    return count


def write_rollout_facts(path: str | os.PathLike, facts: dict) -> Path:
    """Write a rollout's facts as JSON (name ending in ``.rollout.json``), atomically."""
    path = Path(path)
    if not path.name.endswith(ROLLOUT_SUFFIX):
        raise ValueError(f"a rollout facts file name ends in {ROLLOUT_SUFFIX!r}, got {path.name!r}")
    return write_text(path, json.dumps(facts, indent=2, sort_keys=True) + "\n")


def read_rollout_facts(path: str | os.PathLike) -> dict:
    """Read a rollout's facts; InputError names the file and the missing key."""
    path = Path(path)
    facts = read_json(path, "expected the facts of a rollout ('crashfuse rollout' writes them)")
    missing = [k for k in _FACT_KEYS if not isinstance(facts, dict) or k not in facts]
    if missing:
        raise InputError("expected the keys of a rollout's facts", path, missing[0])
    return facts


def auto_facts(candidates: list, inputs=AUTO_INPUTS) -> tuple[int, dict]:
    """The ``auto`` model's rollout facts for one held-out test: the candidate's that
    :func:`crashfuse.method.selection.choose` picks by inner error, relabelled.

    Parameters
    ----------
    candidates : list of dict
        The rollout facts (:func:`rollout_fold` with ``inner``) of every candidate of the test.
    inputs : sequence of str
        The order of the input modes among candidates of one K (simplest first: K ascending, then this).

    Returns
    -------
    index : int
        Position of the chosen candidate in ``candidates``.
    facts : dict
        Its facts with ``inputs`` and ``model`` = ``auto``, the settings ``chosen`` (``<inputs> <model>``)
        and ``candidates`` (every candidate's inner error as text) and the metric ``inner_error_mps2_sq``
        (the chosen one's; a candidate's may be infinite, which a metric cannot be).
    """
    from crashfuse.method.selection import choose

    tests = {c["test_id"] for c in candidates}
    missing = [c["inputs"] + " " + c["model"] for c in candidates if "inner_error" not in c["metrics"]]
    if len(tests) != 1 or missing:
        raise InputError(f"expected the rollouts of one test, each with its inner error (rollout --inner); got tests "
                         f"{sorted(tests)}, without it: {missing}", field="candidates")
    other = sorted({c["inputs"] for c in candidates} - set(inputs))
    if other:
        raise InputError(f"expected candidates of the input modes {list(inputs)}, got {other}", field="inputs")
    order = sorted(range(len(candidates)), key=lambda i: (candidates[i]["k"], list(inputs).index(candidates[i]["inputs"])))
    pick = choose([candidates[i]["metrics"]["inner_error"] for i in order])
    names = [f"{candidates[i]['inputs']} {candidates[i]['model']}" for i in order]
    won = candidates[order[pick.index]]
    facts = {**won, "inputs": AUTO, "model": AUTO,
             "settings": {**won["settings"], "chosen": names[pick.index],
                          "candidates": "; ".join(f"{n}: {e:.6g}" for n, e in zip(names, pick.scores))},
             "metrics": {**won["metrics"], "inner_error_mps2_sq": pick.scores[pick.index]}}
    return order[pick.index], facts


def score_fold(campaign, test_id: str, frame, facts: dict, windows=WINDOWS, cae=None) -> dict:
    """Rate a fold's prediction against its held-out test: ISO rows, band coverage, the fold record.

    Parameters
    ----------
    campaign : Campaign
    test_id : str
    frame : DataFrame
        The prediction table (:meth:`Prediction.frame` or :func:`crashfuse.io.prediction.read_prediction_csv`),
        deceleration in g.
    facts : dict
        :func:`rollout_fold`'s facts.
    windows : sequence of str
        ISO windows ``'<start>-<end>'`` in ms.
    cae : tuple (time, decel), optional
        The CAE pulse the ``CAE`` rows rate (SI); default the test's companion run, which must then exist.

    Returns
    -------
    dict
        ``iso`` (the model's rows), ``cae_iso`` (the CAE rows), ``coverage`` (one row of
        :data:`COVERAGE_COLUMNS`) and ``record`` (:class:`FoldRecord`).
    """
    if facts["test_id"] != test_id:
        raise InputError(f"expected the rollout of {test_id}, got that of {facts['test_id']}", field="test")
    windows = check_windows(windows)
    test = campaign.pulses[test_id].after_contact()
    mode, name, metrics = facts["inputs"], facts["model"], facts["metrics"]
    t = frame["time_s"].to_numpy(float)
    decel = {c: frame[c].to_numpy(float) * G0 for c in ("decel_g", "decel_lo_g", "decel_hi_g", "decel_latent_lo_g",
                                                          "decel_latent_hi_g")}
    iso = [_iso_row(test, t, decel["decel_g"], test_id, mode, name, w) for w in windows]
    cae_t, cae_a = cae if cae is not None else _companion(campaign, test_id)
    cae_iso = [_iso_row(test, cae_t, cae_a, test_id, mode, BASELINE, w) for w in windows]
    cov, n = band_coverage(test.time, test.decel, t, decel["decel_lo_g"], decel["decel_hi_g"])
    cov_latent, _ = band_coverage(test.time, test.decel, t, decel["decel_latent_lo_g"], decel["decel_latent_hi_g"])
    coverage = dict(test_id=test_id, inputs=mode, model=name, coverage=cov, coverage_latent=cov_latent, n_points=n,
                    extrapolation=bool(metrics["extrapolation"]), n_gps_loading=int(metrics["n_gps_loading"]),
                    n_gps_unloading=int(metrics["n_gps_unloading"]),
                    cluster_switches=int(metrics["cluster_switches"]), fit_s=metrics["fit_seconds"],
                    predict_s=metrics["predict_seconds"], inner_error=metrics.get("inner_error"),
                    effects_fitted=facts["settings"].get("effects_fitted"), chosen=facts["settings"].get("chosen"))
    record = FoldRecord(
        test_id=test_id, inputs=mode, k=facts["k"], seed=facts["seed"], campaign=facts["campaign"],
        conditions={"v0_mps": test.v0, "front_weight_kg": test.front_weight, "rear_weight_kg": test.rear_weight,
                    "powertrain": str(test.meta.get("powertrain")), "drive": str(test.meta.get("drive"))},
        settings=dict(facts["settings"]),
        iso={row["window_ms"]: {s: row[s] for s in SCORES} for row in iso},
        metrics={"coverage_95_0_60": cov, "coverage_latent_95_0_60": cov_latent,
                 **{k: float(v) for k, v in metrics.items() if k != "inner_error"}},
        figures=[f"{test_id}.png"], prediction=f"{test_id}_prediction.csv", run_time=dict(facts.get("run_time", {})),
    )
    return {"iso": iso, "cae_iso": cae_iso, "coverage": coverage, "record": record}


def check_windows(windows) -> tuple[str, ...]:
    """``windows`` (labels ``'<start>-<end>'`` in ms) as a tuple; InputError (field ``windows``) on none, a bad
    label or one given twice."""
    windows = (windows,) if isinstance(windows, str) else tuple(windows)
    if not windows or len(set(windows)) < len(windows):
        raise InputError(f"expected one or more distinct ISO windows '<start>-<end>' in ms, got {list(windows)}",
                         field="windows")
    for w in windows:
        try:
            window_bounds(w)
        except ValueError as err:
            raise InputError(str(err), field="windows") from None
    return windows


def _companion(campaign, test_id):
    cae = campaign.companion(test_id)
    if cae is None:
        raise InputError(f"test {test_id} names no companion CAE run: the CAE rows need the surrogate's pulse",
                         campaign.root, "cae_run_id")
    cae = cae.after_contact()
    return cae.time, cae.decel


def cae_rows(campaign, surrogate, test_id, mode, windows=WINDOWS) -> list[dict]:
    """The CAE rows of one test: its companion run, or the surrogate's zero-bias pulse where it has none."""
    test = campaign.pulses[test_id].after_contact()
    t, a = cae_pulse(campaign, surrogate, test_id)
    return [_iso_row(test, t, a, test_id, mode, BASELINE, w) for w in windows]


def cae_pulse(campaign, surrogate, test_id):
    """(time, decel) in SI of the CAE pulse a test's CAE rows rate: its companion, else the surrogate's."""
    if campaign.companion(test_id) is not None or surrogate is None:
        return _companion(campaign, test_id)
    test = campaign.pulses[test_id].after_contact()
    curve = surrogate.curve(test.v0, test.front_weight, test.rear_weight, test.meta.get("powertrain"),
                            test.meta.get("drive"))
    traj = curve.rollout(test.dt, test.time.size - 1)
    return traj.time, traj.decel[0]


def band_coverage(t_test, a_test, t_pred, lo, hi, window_ms=COVERAGE_WINDOW_MS) -> tuple[float, int]:
    """Fraction of test samples in the window inside the band ``[lo, hi]`` (interpolated to their times).

    Parameters
    ----------
    t_test, a_test : ndarray, shape (n,)
        Held-out test time (s) and deceleration (m/s^2).
    t_pred, lo, hi : ndarray, shape (m,)
        Prediction time (s) and the band's lower and upper deceleration (m/s^2).
    window_ms : (float, float)

    Returns
    -------
    coverage : float
    n_points : int
    """
    inside = (t_test >= window_ms[0] * MS - 1e-12) & (t_test <= window_ms[1] * MS + 1e-12)
    t, a = t_test[inside], a_test[inside]
    ok = (a >= np.interp(t, t_pred, lo)) & (a <= np.interp(t, t_pred, hi))
    return float(ok.mean()), int(ok.size)


def _iso_row(test, t_cmp, cmp, test_id, mode, name, window: str) -> dict:
    start, end = window_bounds(window)
    s = iso_score(test.time, test.decel, t_cmp, cmp, start * MS, end * MS)
    return dict(test_id=test_id, inputs=mode, model=name, window_ms=window, **s)
