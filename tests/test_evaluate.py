"""Leave-one-test-out evaluation: no leakage, the table contract, CAE rows, coverage, CLI."""

from __future__ import annotations

import functools
import pickle
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest

import crashfuse.evaluation.loto as ev
import crashfuse.method.model
from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.io.campaign_write import write_campaign
from crashfuse.signals.iso18571 import iso_score
from crashfuse.method.config import MethodConfig
from crashfuse.io.campaign import read_campaign
from crashfuse.method.model import fit_model, load_model, load_surrogate
from crashfuse.evaluation.fold import band_coverage
from crashfuse.evaluation.records import read_fold_json
from crashfuse.method.rollout import predict
from crashfuse.method.selection import choose
from crashfuse.method.mixture import GMMGPBias
from crashfuse.reporting.plots import plot_evaluation
from crashfuse.reporting.tracking import load_folds
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

pytestmark = pytest.mark.xdist_group("evaluate")  # one worker builds the module's campaign and evaluation

KEEP = ["T02", "T05", "T08"]
FAST = dict(n_grid=40, n_restarts=0)


@pytest.fixture(scope="module")
def campaign():
    full = build(resolve("paper"), seed=0, n_cae=16)[0]
    companions = [full.companion(t).run_id for t in KEEP]
    return full.subset(KEEP + companions + [r for r in full.cae if r.startswith("C0")])


@pytest.fixture(scope="module")
def surrogate(campaign):
    return CAESurrogate(random_state=0).fit(campaign)


@pytest.fixture(scope="module")
def result(campaign, surrogate, tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluation")
    return ev.evaluate(campaign, ks=[1, 2], inputs=["paper", "state"], out=out, n_samples=40, n_jobs=2,
                       surrogate=surrogate, progress=None, auto=True, **FAST), out


def test_no_fold_sees_its_held_out_test(campaign, surrogate, monkeypatch):
    seen = []

    def spy(*args, **kwargs):
        model = fit_model(*args, **kwargs)
        seen.append((kwargs["holdout"], model))
        return model

    monkeypatch.setattr(ev, "fit_model", spy)
    ev.evaluate(campaign, ks=[1], inputs=["paper"], n_samples=5, n_jobs=1, surrogate=surrogate, progress=None,
                **FAST)
    assert sorted(h for h, _ in seen) == KEEP
    for held, model in seen:
        assert held not in model.training_tests
        assert held not in model.groups["loading"] + model.groups["unloading"]
        assert set(model.groups["loading"]) == set(KEEP) - {held}
        assert model.surrogate is surrogate  # fitted once on CAE runs, shared


def test_fit_with_a_holdout_reproduces_the_evaluate_fold(campaign, monkeypatch):
    # One seeding rule: `fit --seed S --holdout T` (surrogate fitted inside) is evaluate's fold for T.
    # A random restart makes the surrogate depend on its seed (with none it is deterministic).
    restarting = functools.partial(CAESurrogate, n_restarts=1)
    monkeypatch.setattr(ev, "CAESurrogate", restarting)
    monkeypatch.setattr(crashfuse.method.model, "CAESurrogate", restarting)
    fold = ev.evaluate(campaign, ks=[1], inputs=["paper"], holdout="T05", n_samples=5, random_state=3, n_jobs=1,
                       progress=None, **FAST)
    model = fit_model(campaign, MethodConfig(k=1, inputs="paper", random_state=3, **FAST), holdout="T05")
    test = campaign.pulses["T05"].after_contact()
    pred = predict(model, test.v0, test.front_weight, test.rear_weight, test.meta["powertrain"],
                   test.meta["drive"], n_samples=5, random_state=3, duration=float(test.time[-1]), dt=test.dt)
    pd.testing.assert_frame_equal(fold.predictions[("paper", "K1", "T05")].drop(columns="test_decel_g"),
                                  pred.frame())


def test_iso_table_contract(result):
    res, out = result
    iso = pd.read_csv(out / "iso_table.csv", dtype={"window_ms": str})
    assert list(iso.columns) == ["test_id", "inputs", "model", "window_ms", "overall", "corridor", "phase",
                                 "magnitude", "slope"]
    assert set(iso["model"]) == {"CAE", "K1", "K2", "auto"} and set(iso["inputs"]) == {"paper", "state", "auto"}
    assert set(iso["window_ms"]) == {"0-20", "0-40", "0-60"}
    # one row per test x inputs x model x window; the auto model's inputs hold CAE and auto
    assert len(iso) == len(KEEP) * (2 * 3 + 2) * 3
    assert not iso.duplicated(["test_id", "inputs", "model", "window_ms"]).any()
    assert iso[["overall", "corridor", "phase", "magnitude", "slope"]].apply(lambda c: c.between(0, 1)).all().all()


def test_other_windows_rate_the_same_folds(campaign, surrogate, result):
    """``windows``: the folds, the auto model's choice among them and the CAE rows are the same; the rows are
    the windows asked for, the rebound's 0-100 ms among them."""
    fold = ev.evaluate(campaign, ks=[1, 2], inputs=["state"], holdout="T05", windows=("0-100", "0-60"),
                       n_samples=40, n_jobs=1, surrogate=surrogate, progress=None, auto=True, **FAST)
    iso = fold.iso_table
    assert list(dict.fromkeys(iso["window_ms"])) == ["0-100", "0-60"]
    assert set(iso["model"]) == {"CAE", "K1", "K2", "auto"} and iso["overall"].between(0, 1).all()
    default = result[0].iso_table
    default = default[(default.test_id == "T05") & (default.window_ms == "0-60") & (default.inputs != "paper")]
    keys = ["inputs", "model"]
    pd.testing.assert_frame_equal(iso[iso.window_ms == "0-60"].sort_values(keys).reset_index(drop=True),
                                  default.sort_values(keys).reset_index(drop=True))
    with pytest.raises(InputError, match="distinct ISO windows"):
        ev.evaluate(campaign, ks=[1], inputs=["state"], windows=(), surrogate=surrogate, progress=None)


def test_cae_rows_rate_the_companion_run(campaign, result):
    iso = result[0].iso_table
    test, cae = campaign.pulses["T05"], campaign.companion("T05")
    row = iso[(iso.test_id == "T05") & (iso.model == "CAE") & (iso.window_ms == "0-40") & (iso.inputs == "state")]
    expect = iso_score(test.time, test.decel, cae.time, cae.decel, 0.0, 0.04)["overall"]
    assert row["overall"].item() == pytest.approx(expect, abs=1e-12)


def test_fold_rows_rate_the_written_prediction(campaign, result):
    res, out = result
    frame = pd.read_csv(out / "state" / "K2" / "T05" / "T05_prediction.csv")
    test = campaign.pulses["T05"]
    expect = iso_score(test.time, test.decel, frame["time_s"], frame["decel_g"] * 9.80665, 0.0, 0.06)["overall"]
    iso = res.iso_table
    got = iso[(iso.test_id == "T05") & (iso.model == "K2") & (iso.window_ms == "0-60") & (iso.inputs == "state")]
    assert got["overall"].item() == pytest.approx(expect, abs=2e-3)  # the CSV carries 6 significant digits


def test_coverage_is_the_fraction_inside_the_band(campaign, result):
    res, out = result
    cov = pd.read_csv(out / "coverage.csv")
    assert len(cov) == len(KEEP) * (2 * 2 + 1) and cov["coverage"].between(0, 1).all()
    assert (cov.loc[cov.model == "K1", "cluster_switches"] == 0).all()  # one GP: nothing to switch
    frame = pd.read_csv(out / "paper" / "K1" / "T02" / "T02_prediction.csv")
    test = campaign.pulses["T02"]
    win = test.time <= 0.06 + 1e-12
    inside = ((test.decel[win] >= np.interp(test.time[win], frame.time_s, frame.decel_lo_g * 9.80665) - 1e-3)
              & (test.decel[win] <= np.interp(test.time[win], frame.time_s, frame.decel_hi_g * 9.80665) + 1e-3))
    row = cov[(cov.test_id == "T02") & (cov.model == "K1") & (cov.inputs == "paper")]
    assert row["coverage"].item() == pytest.approx(inside.mean(), abs=0.01)
    assert row["n_points"].item() == win.sum()
    latent = ((test.decel[win] >= np.interp(test.time[win], frame.time_s, frame.decel_latent_lo_g * 9.80665) - 1e-3)
              & (test.decel[win] <= np.interp(test.time[win], frame.time_s, frame.decel_latent_hi_g * 9.80665) + 1e-3))
    assert row["coverage_latent"].item() == pytest.approx(latent.mean(), abs=0.01)
    assert (cov["coverage"] >= cov["coverage_latent"]).all()  # the test band holds the latent one


def test_the_band_setting_never_moves_the_scores(campaign, surrogate):
    res, latent = (ev.evaluate(campaign, ks=[1], inputs=["state"], holdout="T05", n_samples=40, n_jobs=1,
                               surrogate=surrogate, progress=None, band=band, **FAST) for band in ("test", "latent"))
    key = ("state", "K1", "T05")
    pd.testing.assert_frame_equal(latent.predictions[key].drop(columns=["decel_lo_g", "decel_hi_g"]),
                                  res.predictions[key].drop(columns=["decel_lo_g", "decel_hi_g"]))
    iso = res.iso_table
    same = iso[(iso.test_id == "T05") & (iso.inputs == "state") & (iso.model == "K1")].reset_index(drop=True)
    pd.testing.assert_frame_equal(latent.iso_table[latent.iso_table.model == "K1"].reset_index(drop=True), same)
    row = latent.coverage.iloc[0]
    assert row["coverage"] == row["coverage_latent"] == res.coverage.iloc[0]["coverage_latent"]
    assert latent.records[key].settings["band"] == "latent" and res.records[key].settings["band"] == "test"


def test_band_coverage_closed_form():
    t = np.linspace(0, 0.1, 101)
    a = np.sin(40 * t)
    lo = np.where(t < 0.03, a - 1, a + 0.5)  # the first 30 samples of the 61 in 0-60 ms are inside
    cov, n = band_coverage(t, a, t, lo, lo + 2)
    assert n == 61 and cov == pytest.approx(30 / 61)


@pytest.mark.parametrize("kw, field", [(dict(ks=[0]), "k"), (dict(inputs=["both"]), "inputs"),
                                       (dict(trend="cubic"), "trend"), (dict(random_state=-1), "random_state"),
                                       (dict(inputs=["paper"], auto=True), "auto")])
def test_bad_settings(campaign, surrogate, kw, field):
    with pytest.raises(InputError) as err:
        ev.evaluate(campaign, surrogate=surrogate, progress=None, **kw)
    assert err.value.field == field


def test_fold_json_matches_the_table(result):
    res, out = result
    record = read_fold_json(out / "state" / "K1" / "T08" / "T08.fold.json")
    iso = res.iso_table
    rows = iso[(iso.test_id == "T08") & (iso.model == "K1") & (iso.inputs == "state")]
    for _, row in rows.iterrows():
        assert record.iso[row.window_ms]["overall"] == pytest.approx(row.overall, abs=1e-12)
    assert record.k == 1 and record.campaign["hash"] == res.records[("state", "K1", "T08")].campaign["hash"]
    assert (out / "state" / "K1" / "T08" / record.prediction).exists()
    start, end = record.run_time["start"], record.run_time["end"]  # the fold's run: its fit, then its rollout
    assert time.time() - 3600 < start and end - start >= record.metrics["fit_seconds"] + record.metrics["predict_seconds"]


def test_the_table_knows_every_input_mode():
    from crashfuse.evaluation.iso_table import AUTO, ROW_INPUTS
    from crashfuse.method.projection import INPUTS

    assert ROW_INPUTS == (*INPUTS, AUTO)


def test_auto_copies_the_candidate_with_the_smallest_inner_error(campaign, result):
    """Per held-out test, the auto rows, fold JSON and prediction are those of the state fold :func:`choose` picks
    (simplest first), named in the JSON."""
    res, out = result
    cov, iso = res.coverage, res.iso_table
    for test_id in KEEP:
        assert cov[(cov.test_id == test_id) & (cov.inputs == "paper")].inner_error.isna().all()  # not candidates
        candidates = cov[(cov.test_id == test_id) & (cov.inputs == "state")].sort_values("model")  # state K1, K2
        assert (candidates.inner_error > 0).all() and np.isfinite(candidates.inner_error).any()
        best = candidates.iloc[choose(candidates.inner_error.tolist()).index]
        record = read_fold_json(out / "auto" / "auto" / test_id / f"{test_id}.fold.json")
        assert record.model == "auto" and record.settings["chosen"] == f"{best.inputs} {best.model}"
        assert cov[(cov.test_id == test_id) & (cov.inputs == "auto")].chosen.tolist() == [record.settings["chosen"]]
        assert record.settings["candidates"].count(":") == len(candidates)
        chosen = iso[(iso.test_id == test_id) & (iso.inputs == best.inputs) & (iso.model == best.model)]
        auto = iso[(iso.test_id == test_id) & (iso.inputs == "auto") & (iso.model == "auto")]
        np.testing.assert_array_equal(auto.overall.to_numpy(), chosen.overall.to_numpy())
        pd.testing.assert_frame_equal(res.predictions["auto", "auto", test_id],
                                      res.predictions[best.inputs, best.model, test_id])
        assert record.metrics["inner_error_mps2_sq"] == pytest.approx(best.inner_error)
    plot_evaluation(res, out, campaign)
    _, folds = load_folds(out)  # tracking reads the auto folds: same keys within (auto, auto), CAE rows there
    assert sum(f.record.model == "auto" for f in folds) == len(KEEP)


def test_cli_prepare_then_one_fold(campaign, tmp_path):
    small = campaign.subset(["T05", "T08", campaign.companion("T05").run_id, campaign.companion("T08").run_id]
                            + campaign.cae[len(KEEP):])
    folder = write_campaign(small, tmp_path / "campaign")
    surrogate = tmp_path / "surrogate.cfmodel"
    assert main(["prepare", str(folder), "--out", str(surrogate)]) == 0
    out = tmp_path / "eval"
    assert main(["evaluate", str(folder), "--k", "1", "--inputs", "paper", "--holdout", "T08", "--surrogate",
                 str(surrogate), "--samples", "20", "--jobs", "1", "--n-grid", "40", "--out", str(out)]) == 0
    iso = pd.read_csv(out / "iso_table.csv")
    assert set(iso["test_id"]) == {"T08"} and set(iso["model"]) == {"CAE", "K1"}
    assert sorted(p.name for p in (out / "paper" / "K1" / "T08").iterdir()) == ["T08.fold.json", "T08.png",
                                                                               "T08_prediction.csv"]
    model = tmp_path / "model.cfmodel"
    assert main(["fit", str(folder), "--k", "2", "--inputs", "paper", "--pooled", "--n-grid", "40",
                 "--out", str(model)]) == 0
    assert load_model(model).config.pooled is True  # paper's default is False
    assert main(["fit", str(folder), "--k", "1", "--inputs", "state", "--onset", "--n-grid", "40",
                 "--out", str(model)]) == 0
    assert load_model(model).config.onset is True  # state's default is False
    assert main(["fit", str(folder), "--k", "1", "--inputs", "state", "--no-shrink", "--n-grid", "40",
                 "--out", str(model)]) == 0
    assert load_model(model).config.shrink is False and isinstance(load_model(model).bias_["loading"], GMMGPBias)
    assert main(["fit", str(folder), "--k", "1", "--inputs", "paper", "--onset", "--out", str(model)]) == 2
    assert main(["evaluate", str(folder), "--k", "0", "--out", str(tmp_path / "x")]) == 2
    assert main(["evaluate", str(folder), "--k", "1", "--holdout", "C0001", "--out", str(tmp_path / "x")]) == 2
    assert main(["evaluate", str(folder), "--k", "1", "--surrogate", str(folder / "conditions.csv"),
                 "--out", str(tmp_path / "x")]) == 2
    for windows in (["60-20"], ["0-60", "0-60"], ["0-60ms"]):
        assert main(["evaluate", str(folder), "--k", "1", "--windows", *windows, "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_the_cli_steps_of_a_fold_give_the_evaluate_fold(campaign, tmp_path, capsys):
    """fit -> rollout -> score (the workflow's jobs) score what evaluate does, to the CSV's 6 digits; auto
    picks among rollouts with their inner error; bad steps are named."""
    folder = write_campaign(campaign, tmp_path / "campaign")
    surrogate, fold = tmp_path / "surrogate.cfmodel", tmp_path / "fold"
    assert main(["prepare", str(folder), "--out", str(surrogate)]) == 0
    for k in (1, 2):  # K2 reuses K1's GP as its pooled GP, as the workflow's train jobs do
        model, out = tmp_path / f"K{k}.cfmodel", fold / f"K{k}"
        pooled = ["--pooled-from", str(tmp_path / "K1.cfmodel")] if k == 2 else []
        assert main(["fit", str(folder), "--k", str(k), "--inputs", "state", "--holdout", "T05", "--surrogate",
                     str(surrogate), "--n-grid", "40", *pooled, "--out", str(model)]) == 0
        assert main(["rollout", str(model), str(folder), "--test", "T05", "--samples", "40", "--inner",
                     "--out", str(out)]) == 0
        assert main(["score", str(folder), str(out), "--test", "T05", "--table-dir", str(out)]) == 0
    # fit --surrogate: the model refers to the surrogate's file (rollout above found it there) instead of a copy
    moved = tmp_path / "moved.cfmodel"
    surrogate.rename(moved)
    with pytest.raises(InputError, match="refers to its CAE surrogate"):
        load_model(tmp_path / "K1.cfmodel")
    assert load_model(tmp_path / "K1.cfmodel", load_surrogate(moved)).surrogate is not None
    moved.rename(surrogate)
    res = ev.evaluate(read_campaign(folder), ks=[2, 1], inputs=["state"], holdout="T05", n_samples=40, n_jobs=1,
                      surrogate=load_surrogate(surrogate), progress=None, n_grid=40)
    assert list(res.coverage.model) == ["K2", "K1"]  # the order asked for, though K1 is fitted first
    for k in ("K1", "K2"):
        steps = pd.read_csv(fold / k / "iso_table.csv", dtype={"window_ms": str})
        np.testing.assert_allclose(steps[steps.model == k].overall, res.iso_table[res.iso_table.model == k].overall,
                                   atol=1e-4)
    assert read_fold_json(fold / "K1" / "T05.fold.json").settings == res.records["state", "K1", "T05"].settings
    assert main(["auto", str(fold / "K1" / "T05.rollout.json"), str(fold / "K2" / "T05.rollout.json"),
                 "--inputs", "state", "--out", str(fold / "auto")]) == 0
    assert main(["score", str(folder), str(fold / "auto"), "--test", "T05", "--table-dir", str(fold / "auto")]) == 0
    assert set(pd.read_csv(fold / "auto" / "iso_table.csv").model) == {"CAE", "auto"}
    # The workflow's most numerous job starts without the estimator, tracking, plotting or filtering libraries
    probe = (f"import sys; from crashfuse.cli import main; main(['score', {str(folder)!r}, {str(fold / 'K1')!r}, "
             f"'--test', 'T05', '--table-dir', {str(tmp_path / 'probe')!r}]); "
             "print(sorted(m for m in ('sklearn', 'mlflow', 'matplotlib', 'scipy.signal') if m in sys.modules))")
    assert subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          check=True).stdout.splitlines()[-1] == "[]"
    capsys.readouterr()
    assert main(["fit", str(folder), "--k", "2", "--inputs", "state", "--holdout", "T02", "--surrogate",
                 str(surrogate), "--n-grid", "40", "--pooled-from", str(tmp_path / "K1.cfmodel"),
                 "--out", str(tmp_path / "other.cfmodel")]) == 2
    assert "K1.cfmodel: field 'pooled_from'" in capsys.readouterr().err and not (tmp_path / "other.cfmodel").exists()
    assert main(["score", str(folder), str(fold / "K1"), "--test", "T99", "--table-dir", str(fold)]) == 2
    assert "T99" in capsys.readouterr().err
    assert main(["score", str(folder), str(fold / "K1"), "--test", "T05", "--windows", "40-20",
                 "--table-dir", str(fold)]) == 2
    assert "--windows" in capsys.readouterr().err
    assert main(["score", str(folder), str(tmp_path), "--test", "T05", "--table-dir", str(fold)]) == 2
    assert "T05.rollout.json" in capsys.readouterr().err
    assert main(["rollout", str(tmp_path / "K1.cfmodel"), str(folder), "--test", "T08", "--out", str(fold)]) == 2
    assert "fitted without T08" in capsys.readouterr().err


def test_reading_one_run_and_its_companion(campaign, tmp_path):
    folder = write_campaign(campaign, tmp_path / "campaign")
    one = read_campaign(folder, runs=["T05"])
    assert one.tests == ["T05"] and set(one.pulses) == {"T05", campaign.companion("T05").run_id}
    np.testing.assert_array_equal(one.pulses["T05"].decel, read_campaign(folder).pulses["T05"].decel)
    with pytest.raises(InputError) as err:
        read_campaign(folder, runs=["T99"])
    assert err.value.field == "run_id"


def test_a_surrogate_of_the_unchanged_folder_spares_parsing_its_runs(campaign, tmp_path, monkeypatch):
    """``read_campaign(known=...)`` (what a fold job passes from its surrogate) parses a run only when it is used,
    with the same bits and content hash as a full read; a changed byte in a run it never uses reads all again."""
    import crashfuse.io.campaign as campaign_module

    folder = write_campaign(campaign, tmp_path / "campaign")
    whole = read_campaign(folder)
    known = (whole.source, whole.content_hash())
    loads = []
    monkeypatch.setattr(campaign_module, "_load_run", functools.partial(_counted, campaign_module._load_run, loads))
    lazy = read_campaign(folder, known=known)
    assert not loads and lazy.content_hash() == known[1] and list(lazy.pulses) == list(whole.pulses)
    np.testing.assert_array_equal(lazy.companion("T05").decel, whole.companion("T05").decel)
    assert len(loads) == 1
    copy = pickle.loads(pickle.dumps(lazy))  # as evaluate's worker processes receive it
    np.testing.assert_array_equal(copy.pulses["T02"].decel, whole.pulses["T02"].decel)
    assert copy.content_hash() == known[1] and len(loads) == 2
    last = folder / "pulses" / f"{whole.cae[-1]}.csv"
    text = last.read_bytes().rstrip(b"\n")
    last.write_bytes(text[:-1] + str((int(text[-1:]) + 1) % 10).encode() + b"\n")  # its last digit
    changed = read_campaign(folder, known=known)
    assert isinstance(changed.pulses, dict) and changed.source != known[0] and changed.content_hash() != known[1]


def _counted(load, calls, *args):
    calls.append(args)
    return load(*args)


def test_a_test_without_a_companion_is_scored_against_the_surrogate(campaign, tmp_path):
    """A campaign whose tests name no CAE run: the score job rates CAE by the surrogate fitted on the whole
    campaign (it once checked the surrogate against the one test it had read, and refused every fold)."""
    folder = write_campaign(campaign, tmp_path / "campaign")
    table = pd.read_csv(folder / "conditions.csv", dtype=str, keep_default_na=False)
    table.assign(cae_run_id="").to_csv(folder / "conditions.csv", index=False)
    surrogate, model, out = tmp_path / "surrogate.cfmodel", tmp_path / "K1.cfmodel", tmp_path / "fold"
    assert main(["prepare", str(folder), "--out", str(surrogate)]) == 0
    assert main(["fit", str(folder), "--k", "1", "--inputs", "paper", "--holdout", "T05", "--surrogate",
                 str(surrogate), "--n-grid", "40", "--out", str(model)]) == 0
    assert main(["rollout", str(model), str(folder), "--test", "T05", "--samples", "20", "--out", str(out)]) == 0
    assert main(["score", str(folder), str(out), "--test", "T05", "--surrogate", str(surrogate),
                 "--table-dir", str(out)]) == 0
    assert set(pd.read_csv(out / "iso_table.csv").model) == {"CAE", "K1"}


def test_workers_read_the_campaign_once_from_a_pickle_they_remove(campaign, surrogate, tmp_path, monkeypatch):
    """With workers the campaign and surrogate travel once, in a temporary pickle removed afterwards;
    the folds equal those of workers given them with every fold, bit for bit. (In-process folds,
    ``n_jobs=1``, differ from any worker's in the last bits: BLAS runs other thread counts there.)"""
    from joblib import Parallel, delayed

    monkeypatch.setattr(ev.tempfile, "tempdir", str(tmp_path))
    folds = [(MethodConfig(k=1, inputs="paper", **FAST), "T02", None),
             (MethodConfig(k=1, inputs="state", **FAST), "T08", None)]  # no physics: the plain model
    settings = (5, "test")
    chains = [([config], test, physics) for config, test, physics in folds]
    shared = [chain[0] for chain in ev._run_chains(campaign, surrogate, chains, 2, settings)]
    assert not list(tmp_path.iterdir())
    direct = Parallel(n_jobs=2)(delayed(ev._fold)(campaign, surrogate, *fold, *settings) for fold in folds)
    for got, want in zip(shared, direct):
        assert got["iso"] == want["iso"]
        assert {k: v for k, v in got["coverage"].items() if not k.endswith("_s")} == \
            {k: v for k, v in want["coverage"].items() if not k.endswith("_s")}
        pd.testing.assert_frame_equal(got["frame"], want["frame"], check_exact=True)
