"""MLflow tracking: runs, params, metrics, artifacts and idempotence, on a temp SQLite store and a
real ``mlflow server`` on loopback."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
from mlflow.entities import ViewType  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from crashfuse.reporting import tracking  # noqa: E402
from crashfuse.errors import InputError  # noqa: E402
from crashfuse.gp.threads import cpu_kernels  # noqa: E402
from crashfuse.evaluation.records import FoldRecord, write_fold_json  # noqa: E402
from servers import free_port, mlflow_server, serving  # noqa: E402

SCORES = ["overall", "corridor", "phase", "magnitude", "slope"]
WINDOWS = ["0-20", "0-40", "0-60"]
TESTS = ["T01", "T02", "T10"]
KS = [1, 2]
# A 1x1 PNG (signature, IHDR, IDAT, IEND), so the artifacts are real image files.
PNG = bytes.fromhex("89504e470d0a1a0a0000000d4948445200000001000000010806000000"
                    "1f15c4890000000d49444154789c63f8ffff3f0005fe02fea7d6a4880000000049454e44ae426082")


T0 = 1.7e9  # the folds' run times: fold (k, i) from T0 + 100 k + 10 i for 5 + i s


def make_evaluation(root: Path, seed: int = 0, settings: dict | None = None, t0: float = T0) -> pd.DataFrame:
    """A small evaluation directory: iso_table.csv, one fold JSON + PNG + prediction CSV per fold."""
    rng = np.random.default_rng(seed)
    rows = [dict(test_id=t, inputs="paper", model=m, window_ms=w, **dict(zip(SCORES, rng.uniform(0.3, 0.95, 5))))
            for t in TESTS for m in ["CAE", *(f"K{k}" for k in KS)] for w in WINDOWS]
    table = pd.DataFrame(rows)
    root.mkdir(parents=True, exist_ok=True)
    table.to_csv(root / "iso_table.csv", index=False, float_format="%.17g")
    for k in KS:
        for i, test in enumerate(TESTS):
            fold_dir = root / "paper" / f"K{k}" / test
            fold_dir.mkdir(parents=True, exist_ok=True)
            (fold_dir / "prediction.png").write_bytes(PNG)
            (fold_dir / "prediction.csv").write_text("time_s,decel_g,decel_lo_g,decel_hi_g,cae_decel_g\n0,0,0,0,0\n")
            mine = table[(table.test_id == test) & (table.model == f"K{k}")].set_index("window_ms")
            record = FoldRecord(
                test_id=test, inputs="paper", k=k, seed=7,
                campaign={"name": "tiny", "hash": "ab" * 32},
                conditions={"v0_mps": 10.0 + i, "front_weight_kg": 1000.0, "rear_weight_kg": 800.0,
                            "powertrain": "Type I", "drive": "FWD"},
                settings=settings or {"trend": "constant", "nugget": 1e-6, "n_restarts": 3},
                iso={w: {s: float(mine.at[w, s]) for s in SCORES} for w in WINDOWS},
                metrics={"coverage_95_0_60": float(rng.uniform()), "log_marginal_likelihood": float(rng.normal())},
                figures=["prediction.png"], prediction="prediction.csv",
                run_time={"start": t0 + 100 * k + 10 * i, "end": t0 + 100 * k + 11 * i + 5})
            write_fold_json(fold_dir / f"{test}.fold.json", record)
    return table


@pytest.fixture()
def store(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    return f"sqlite:///{tmp_path / 'store' / 'mlflow.db'}"


def _runs(client: MlflowClient, exp_id: str, view=ViewType.ACTIVE_ONLY):
    return client.search_runs([exp_id], run_view_type=view, max_results=1000)


def check_logged(client: MlflowClient, out: dict, table: pd.DataFrame, results: Path, t0: float = T0) -> None:
    """Runs, params, metrics, tags, run times and artifacts as the evaluation directory says."""
    assert client.get_experiment(out["experiment_id"]).tags["mlflow.experimentKind"] == "custom_model_development"
    runs = _runs(client, out["experiment_id"])
    children = [r for r in runs if r.data.tags["crashfuse.role"] == "fold"]
    parents = {r.info.run_id: r for r in runs if r.data.tags["crashfuse.role"] == "parent"}
    assert len(parents) == len(KS) and len(children) == len(KS) * len(TESTS)
    assert len({frozenset(r.data.params) for r in children}) == 1
    assert len({frozenset(r.data.metrics) for r in children}) == 1
    for run in children:
        tags, metrics = run.data.tags, run.data.metrics
        test, k = tags["crashfuse.test_id"], int(tags["crashfuse.k"])
        parent = parents[tags["mlflow.parentRunId"]]
        assert parent.data.tags["crashfuse.k"] == str(k)
        assert run.data.params["test_id"] == test and run.data.params["k"] == str(k)
        i = TESTS.index(test)
        assert (run.info.start_time, run.info.end_time) == (int((t0 + 100 * k + 10 * i) * 1000),
                                                            int((t0 + 100 * k + 11 * i + 5) * 1000))
        for model, prefix in ((f"K{k}", "iso"), ("CAE", "cae_iso")):
            row = table[(table.test_id == test) & (table.model == model)]
            for w, s in [(w, s) for w in WINDOWS for s in SCORES]:
                want = row.loc[row.window_ms == w, s].item()
                assert metrics[f"{prefix}_{s}_{w.replace('-', '_')}"] == pytest.approx(want, abs=1e-12)
        assert tags["crashfuse.campaign_hash"] == "ab" * 32 and tags["crashfuse.inputs"] == "paper"
        assert tags["crashfuse.kernels"] == cpu_kernels()
        paths = {a.path for folder in ("figures", "fold") for a in client.list_artifacts(run.info.run_id, folder)}
        assert paths == {"figures/prediction.png", f"fold/{test}.fold.json"}
        local = client.download_artifacts(run.info.run_id, "figures/prediction.png", str(results.parent / "downloads" / run.info.run_id))
        assert Path(local).read_bytes() == PNG
    for parent in parents.values():
        k = int(parent.data.tags["crashfuse.k"])
        want = table[table.model == f"K{k}"].groupby("window_ms")["overall"].mean()["0-60"]
        assert parent.data.metrics["iso_overall_0_60"] == pytest.approx(want, abs=1e-12)
        assert parent.data.metrics["n_folds"] == len(TESTS)
        assert [a.path for a in client.list_artifacts(parent.info.run_id)] == ["iso_table.csv"]
        assert parent.data.params["k"] == str(k) and "test_id" not in parent.data.params
        n = len(TESTS) - 1  # the parent spans its first fold's start to its last fold's end
        assert (parent.info.start_time, parent.info.end_time) == (int((t0 + 100 * k) * 1000),
                                                                  int((t0 + 100 * k + 11 * n + 5) * 1000))


def test_log_creates_runs_and_a_rerun_updates_them(tmp_path, store):
    results = tmp_path / "results"
    table = make_evaluation(results)
    client = MlflowClient(tracking_uri=store)
    out = tracking.log_evaluation(results, tracking_uri=store, config={"k": [1, 2]}, project_dir=tmp_path)
    assert out["experiment_name"] == "crashfuse/tiny-" + "ab" * 6
    assert client.get_experiment(out["experiment_id"]).artifact_location.startswith((tmp_path / "store").as_uri())
    check_logged(client, out, table, results)

    again = tracking.log_evaluation(results, tracking_uri=store, config={"k": [1, 2]}, project_dir=tmp_path)
    assert again == out
    assert len(_runs(client, out["experiment_id"], ViewType.ALL)) == len(KS) * (len(TESTS) + 1)
    some = next(iter(out["folds"].values()))
    assert len(client.get_metric_history(some, "iso_overall_0_60")) == 1  # unchanged values are not re-logged

    # New scores (same params): the same runs carry the new values.
    table = make_evaluation(results, seed=1)
    third = tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert third["folds"] == out["folds"]
    check_logged(client, third, table, results)


def test_changed_params_replace_the_run_without_orphans(tmp_path, store):
    results = tmp_path / "results"
    make_evaluation(results)
    client = MlflowClient(tracking_uri=store)
    first = tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    table = make_evaluation(results, settings={"trend": "linear", "nugget": 1e-6, "n_restarts": 3})
    second = tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert set(second["folds"].values()).isdisjoint(first["folds"].values())
    active = _runs(client, second["experiment_id"])
    assert {r.info.run_id for r in active} == {*second["folds"].values(), *second["parents"].values()}
    assert all(r.data.params["trend"] == "linear" for r in active)
    check_logged(client, second, table, results)


def test_folds_run_again_replace_their_runs_with_the_new_times(tmp_path, store):
    results = tmp_path / "results"
    make_evaluation(results)
    client = MlflowClient(tracking_uri=store)
    first = tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    table = make_evaluation(results, t0=T0 + 3600)
    second = tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert set(second["folds"].values()).isdisjoint(first["folds"].values())
    check_logged(client, second, table, results, t0=T0 + 3600)


def test_inconsistent_evaluations_are_refused_before_logging(tmp_path, store):
    results = tmp_path / "results"
    make_evaluation(results)
    fold = results / "paper" / "K2" / "T02" / "T02.fold.json"
    doc = json.loads(fold.read_text())
    doc["metrics"]["extra_metric"] = 1.0
    fold.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert err.value.field == "metrics" and err.value.file.endswith("T02.fold.json")
    assert "extra_metric" in str(err.value)

    doc["metrics"].pop("extra_metric")
    doc["iso"]["0-60"]["overall"] += 0.01  # disagrees with iso_table.csv
    fold.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert err.value.field == "iso.0-60.overall"

    doc["iso"]["0-60"]["overall"] -= 0.01
    doc["run_time"] = {"start": doc["run_time"]["end"] + 1, "end": doc["run_time"]["end"]}
    fold.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert err.value.field == "run_time" and "start <= end" in str(err.value)

    fold.unlink()
    with pytest.raises(InputError) as err:
        tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert err.value.file.endswith("iso_table.csv") and "T02" in str(err.value)
    assert not (tmp_path / "store").exists()  # nothing was written


def test_an_explicit_fold_list_ignores_stale_folds(tmp_path, store):
    results = tmp_path / "results"
    table = make_evaluation(results)
    listed = sorted(results.rglob("*.fold.json"))
    stale = results / "paper" / "K3" / "T01" / "T01.fold.json"  # left by an earlier config with K = 3
    stale.parent.mkdir(parents=True)
    doc = json.loads(listed[0].read_text())
    stale.write_text(json.dumps({**doc, "k": 3}))
    with pytest.raises(InputError) as err:  # the folder form reads it, and iso_table.csv has no K3 rows
        tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path)
    assert err.value.file.endswith("iso_table.csv") and "K3" in str(err.value)
    out = tracking.log_evaluation(results, tracking_uri=store, project_dir=tmp_path, fold_files=listed)
    check_logged(MlflowClient(tracking_uri=store), out, table, results)
    with pytest.raises(InputError) as err:
        tracking.load_folds(results, fold_files=[])
    assert err.value.field == "fold_files"


def test_cli_track_takes_the_fold_list(tmp_path, store, capsys):
    from crashfuse.cli import main

    results = tmp_path / "results"
    make_evaluation(results)
    listed = [str(f) for f in sorted(results.rglob("*.fold.json"))]
    (results / "paper" / "K3").mkdir()
    (results / "paper" / "K3" / "junk.fold.json").write_text("{}")  # stale and broken: never read
    argv = ["track", str(results), "--tracking-uri", store, "--out", str(tmp_path / "tracking.json")]
    assert main([*argv, "--folds", *listed]) == 0
    assert len(json.loads((tmp_path / "tracking.json").read_text())["folds"]) == len(KS) * len(TESTS)
    assert main(argv) == 2
    assert "junk.fold.json" in capsys.readouterr().err


def test_tracking_uri_precedence(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert tracking.resolve_tracking_uri(None, tmp_path) == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:1")
    assert tracking.resolve_tracking_uri(None, tmp_path) == "http://127.0.0.1:1"
    assert tracking.resolve_tracking_uri("sqlite:////x/y.db", tmp_path) == "sqlite:////x/y.db"


@pytest.mark.slow
def test_logging_to_a_real_tracking_server(tmp_path, monkeypatch):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    command = mlflow_server(port, f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "server-artifacts", 1)
    # No telemetry, and no background job runner (a second process this test does not need).
    env = {**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true", "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    with serving(command, tmp_path / "server.log", env, url + "/health", timeout=90):
        results = tmp_path / "results"
        table = make_evaluation(results)
        monkeypatch.setenv("MLFLOW_TRACKING_URI", url)  # the environment names the server
        out = tracking.log_evaluation(results, project_dir=tmp_path)
        assert out["tracking_uri"] == url and not (tmp_path / "mlflow.db").exists()
        check_logged(MlflowClient(tracking_uri=url), out, table, results)
        assert any((tmp_path / "server-artifacts").rglob("prediction.png"))  # stored by the server
        assert tracking.log_evaluation(results, project_dir=tmp_path) == out
