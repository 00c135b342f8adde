"""A team MLflow server: PostgreSQL as the backend store, artifacts served (proxied) by the server,
fed by the workflow with parallel jobs.

PostgreSQL and ``mlflow server`` run on loopback ports with all their state in temp folders. The
workflow's small config logs to the server through ``tracking.uri``, then logs again: nothing may
be duplicated. The setup is documented in docs/tracking.md, "A team server on PostgreSQL".
"""

from __future__ import annotations

import contextlib
import json
import os
import pwd
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

psycopg2 = pytest.importorskip("psycopg2", reason="no PostgreSQL driver for MLflow: pip install -e '.[team]'")
os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
from mlflow.entities import ViewType  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from snakemake.utils import validate  # noqa: E402

from servers import free_port, mlflow_server, serving  # noqa: E402
from test_workflow import SCHEMA, TEST_CONFIG, job_counts, snakemake  # noqa: E402

SUPERUSER = "postgres"  # the throwaway cluster's superuser, who plays the team's DBA
DB = "mlflow"  # the role the server logs in as and the database it owns
PREDICTION_SUFFIXES = (".csv", ".json", ".png")  # per final model and condition (workflow/rules/final.smk)


# --- PostgreSQL ---------------------------------------------------------------------------------


def _postgres_bin() -> Path:
    """The folder holding initdb and postgres; installed with apt-get when missing and we are root."""
    found = _find_postgres_bin()
    if found is None:
        _install_postgres()
        found = _find_postgres_bin()
    if found is None:
        pytest.skip("apt-get installed postgresql, yet no folder holds both initdb and postgres")
    return found


def _install_postgres() -> None:
    # Debian's package also creates a cluster `main` (started where services may start); unused here.
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        pytest.skip("PostgreSQL's server binaries (initdb, postgres) are not installed, and installing them takes "
                    "root and apt-get: apt-get install postgresql")
    done = subprocess.run(["apt-get", "install", "-y", "postgresql"], capture_output=True, text=True, timeout=900,
                          env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    if done.returncode:
        pytest.skip(f"PostgreSQL is not installed and apt-get install postgresql failed: {done.stderr[-500:]}")


def _find_postgres_bin() -> Path | None:
    # Debian keeps the server binaries off PATH, in /usr/lib/postgresql/<major>/bin; prefer the newest.
    on_path = [Path(p).resolve().parent for p in [shutil.which("postgres")] if p]
    debian = sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True,
                    key=lambda p: [int(x) for x in p.parent.name.split(".") if x.isdigit()])
    return next((d for d in on_path + debian if (d / "initdb").exists() and (d / "postgres").exists()), None)


def _cluster_user() -> dict:
    """subprocess options that run PostgreSQL as the `postgres` system user when we are root
    (PostgreSQL refuses to run as root), and as ourselves otherwise."""
    if os.geteuid() != 0:
        return {}
    try:
        user = pwd.getpwnam("postgres")
    except KeyError:
        pytest.skip("running as root without a `postgres` system user to run PostgreSQL as (it refuses root)")
    return {"user": user.pw_uid, "group": user.pw_gid, "extra_groups": []}


@pytest.fixture()
def postgres():
    """A throwaway cluster on a loopback port with a database `mlflow` owned by the role `mlflow`;
    yields the server's backend store URI."""
    bindir, as_user = _postgres_bin(), _cluster_user()
    # Not under pytest's tmp_path: root's is 0700, and the postgres user must enter this folder.
    base = Path(tempfile.mkdtemp(prefix="crashfuse-pg-"))
    try:
        base.chmod(0o755)
        if as_user:
            os.chown(base, as_user["user"], as_user["group"])
        as_user["cwd"] = base
        # trust: any local connection is let in; acceptable for a loopback cluster deleted after the test.
        _run([bindir / "initdb", "-D", base / "data", "-U", SUPERUSER, "--auth=trust", "-E", "UTF8", "--no-locale",
              "--no-sync"], **as_user)
        port = free_port()
        with _running_postgres(bindir, base, port, as_user):
            _create_database(port)
            yield f"postgresql://{DB}@127.0.0.1:{port}/{DB}"
    finally:
        shutil.rmtree(base, ignore_errors=True)


def _run(command: list, **options) -> None:
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=120, **options)
    assert done.returncode == 0, f"{command[0]} failed:\n{done.stdout}\n{done.stderr}"


@contextlib.contextmanager
def _running_postgres(bindir: Path, base: Path, port: int, as_user: dict):
    """The postmaster in the foreground as its own process (so its PID is ours to stop), its socket in
    `base`; on exit a fast shutdown (SIGINT: sessions ended, checkpoint), SIGKILL after 30 s."""
    log = base / "postgres.log"
    command = [bindir / "postgres", "-D", base / "data", "-p", port, "-k", base,
               "-c", "listen_addresses=127.0.0.1", "-c", "fsync=off"]  # fsync off: nothing here must survive a crash
    with log.open("w") as out:
        server = subprocess.Popen([str(c) for c in command], stdout=out, stderr=subprocess.STDOUT,
                                  start_new_session=True, **as_user)
    try:
        _wait_for_postgres(port, server, log)
        yield server
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(timeout=10)


def _connect(port: int, user: str = SUPERUSER, dbname: str = "postgres"):
    return psycopg2.connect(host="127.0.0.1", port=port, user=user, dbname=dbname, connect_timeout=5)


def _wait_for_postgres(port: int, server: subprocess.Popen, log: Path, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while True:
        if server.poll() is not None:
            raise AssertionError(f"postgres exited with code {server.returncode}: {log.read_text()[-2000:]}")
        try:
            _connect(port).close()
            return
        except psycopg2.OperationalError:
            assert time.monotonic() < deadline, f"postgres did not accept connections within {timeout} s"
            time.sleep(0.2)


def _create_database(port: int) -> None:
    """What the team's DBA does once: a login role for the MLflow server and a database it owns (in
    PostgreSQL 15 only the owner may create tables in its public schema: MLflow's migrations do)."""
    conn = _connect(port)
    conn.autocommit = True  # CREATE DATABASE refuses to run inside a transaction
    try:
        with conn.cursor() as cur:
            cur.execute(f"CREATE ROLE {DB} LOGIN")
            cur.execute(f"CREATE DATABASE {DB} OWNER {DB}")
    finally:
        conn.close()


# --- the MLflow server --------------------------------------------------------------------------


@pytest.fixture()
def team_server(postgres, tmp_path):
    """`mlflow server` on the PostgreSQL store, serving artifacts from tmp_path/artifacts; yields its URL."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    # Two workers, as a team server has: PostgreSQL takes their concurrent writes (a SQLite file would lock).
    # --serve-artifacts: clients upload and download through the server, no shared disk needed.
    command = mlflow_server(port, postgres, tmp_path / "artifacts", 2, "--serve-artifacts")
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env.update(MLFLOW_DISABLE_TELEMETRY="true", MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false")  # as test_tracking.py
    # The first start creates MLflow's tables (its migrations): allow for that.
    with serving(command, tmp_path / "mlflow-server.log", env, url + "/health", timeout=180):
        yield url


# --- the test -----------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_workflow_logs_to_a_team_server_once(postgres, team_server, tmp_path, monkeypatch):
    """config/test.yaml with `tracking.uri` naming the server, 4 parallel jobs and a registered final
    model per state K and auto: every fold, parent and final run, artifact and model version once;
    after `--forcerun track` (track and every register job again) the very same ones."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)  # only the config names the server
    config = yaml.safe_load(TEST_CONFIG.read_text())
    validate(config, str(SCHEMA))  # fills in the defaults the counts depend on (auto, ...)
    config["diagnosis"]["enabled"] = False  # logs nothing to MLflow; keeps the test short
    config["tests"], config["ks"] = config["tests"][:2], [1]  # 4 fold jobs (K1 and auto per test) run side by side
    config["tracking"] = {"enabled": True, "uri": team_server}
    config["predictions"]["models"] = ["auto", *(f"state/K{k}" for k in config["ks"])]  # all fitted for auto anyway
    configfile = tmp_path / "team.yaml"
    configfile.write_text(yaml.safe_dump(config))
    workdir, client = tmp_path / "work", MlflowClient(tracking_uri=team_server)
    results, artifacts = workdir / config["results"], tmp_path / "artifacts"

    snakemake(workdir, "--cores", "4", configfile=configfile, warm=True)
    first = _snapshot(client, results, artifacts, postgres)
    _check_runs(first, config, results)
    _check_artifacts(first, config, results)

    again = snakemake(workdir, "--cores", "4", "--forcerun", "track", configfile=configfile, warm=True)
    n_models = len(config["predictions"]["models"])
    assert job_counts(again.stdout + again.stderr) == {"track": 1, "register": n_models, "all": 1}
    assert _snapshot(client, results, artifacts, postgres) == first


def _snapshot(client: MlflowClient, results: Path, artifacts: Path, store: str) -> dict:
    """What the workflow wrote and what the server holds: every run (deleted ones too) with its role,
    parent, artifacts and number of metrics, the model versions, the stored files, the tables' rows."""
    experiments = [e for e in client.search_experiments(ViewType.ALL) if e.name.startswith("crashfuse/")]
    runs = client.search_runs([e.experiment_id for e in experiments], run_view_type=ViewType.ALL, max_results=1000)
    models = [m.name for m in client.search_registered_models("name LIKE 'crashfuse-%'")]
    return {
        "tracking": json.loads((results / "tracking.json").read_text()),
        "registered": {str(p.relative_to(results)): json.loads(p.read_text())
                       for p in (results / "registered").glob("*/*.json")},
        "experiments": {e.experiment_id: (e.name, e.artifact_location) for e in experiments},
        "runs": {r.info.run_id: {"role": r.data.tags.get("crashfuse.role"), "stage": r.info.lifecycle_stage,
                                 "parent": r.data.tags.get("mlflow.parentRunId"),
                                 "artifacts": sorted(_artifacts(client, r.info.run_id)),
                                 "metrics": len(r.data.metrics)}
                 for r in runs},
        "versions": {name: sorted((v.version, v.run_id, v.source)
                                  for v in client.search_model_versions(f"name = '{name}'")) for name in models},
        "stored": sorted(str(p.relative_to(artifacts)) for p in artifacts.rglob("*") if p.is_file()),
        "rows": _rows(store),
    }


def _artifacts(client: MlflowClient, run_id: str, path: str | None = None) -> list[str]:
    out = []
    for item in client.list_artifacts(run_id, path):
        out += _artifacts(client, run_id, item.path) if item.is_dir else [item.path]
    return out


def _rows(store: str) -> dict[str, int]:
    """Row counts of MLflow's tables, read from PostgreSQL itself."""
    conn = psycopg2.connect(store)
    try:
        with conn.cursor() as cur:
            counts = {}
            for table in ("experiments", "runs", "params", "metrics", "registered_models", "model_versions"):
                cur.execute(f"SELECT count(*) FROM {table}")
                counts[table] = cur.fetchone()[0]
            return counts
    finally:
        conn.close()


def _fold_files(config: dict, results: Path) -> list[Path]:
    """The workflow's fold JSONs, <results>/folds/<inputs>/<model>/<test>/<test>.fold.json, as many as the config
    implies: tests x K x input modes, and one auto fold per test."""
    found = sorted((results / "folds").rglob("*.fold.json"))
    assert len(found) == len(config["tests"]) * (len(config["ks"]) * len(config["inputs"]) + int(config["auto"]))
    return found


def _check_runs(seen: dict, config: dict, results: Path) -> None:
    """One experiment; a fold run per fold JSON under the parent of its (inputs, model); a final run per
    registered model with one version; nothing else, nothing deleted; PostgreSQL holds them all."""
    folds = _fold_files(config, results)
    groups = {f.relative_to(results / "folds").parts[:2] for f in folds}
    models = config["predictions"]["models"]
    logged, registered, runs = seen["tracking"], seen["registered"], seen["runs"]
    assert list(seen["experiments"]) == [logged["experiment_id"]]
    assert len(logged["folds"]) == len(folds) and len(logged["parents"]) == len(groups)
    assert len(registered) == len(seen["versions"]) == len(models)

    by_role = {role: {i for i, r in runs.items() if r["role"] == role} for role in ("fold", "parent", "final")}
    assert by_role["fold"] == set(logged["folds"].values())
    assert by_role["parent"] == set(logged["parents"].values())
    assert by_role["final"] == {r["run_id"] for r in registered.values()}
    assert len(runs) == len(folds) + len(groups) + len(models)
    assert {r["stage"] for r in runs.values()} == {"active"}
    for key, run_id in logged["folds"].items():  # key: <inputs>/<model>/<test>
        assert runs[run_id]["parent"] == logged["parents"][key.rsplit("/", 1)[0]]
    for entry in registered.values():
        assert [v[:2] for v in seen["versions"][entry["name"]]] == [("1", entry["run_id"])]
        assert entry["model_uri"] == f"models:/{entry['name']}/1"
    rows = seen["rows"]
    assert rows["runs"] == len(runs) and rows["model_versions"] == rows["registered_models"] == len(models)
    assert rows["metrics"] == sum(r["metrics"] for r in runs.values())  # a history of one point per metric


def _check_artifacts(seen: dict, config: dict, results: Path) -> None:
    """A fold run's figures, prediction and fold JSON; a parent's iso_table.csv; a final run's
    predictions; and on the server's disk exactly those files and the registered models' files."""
    logged, runs = seen["tracking"], seen["runs"]
    assert [loc for _, loc in seen["experiments"].values()] == [f"mlflow-artifacts:/{logged['experiment_id']}"]
    for key, run_id in logged["folds"].items():
        test = key.rsplit("/", 1)[1]
        record = json.loads((results / "folds" / key / f"{test}.fold.json").read_text())
        assert runs[run_id]["artifacts"] == sorted([*(f"figures/{Path(f).name}" for f in record["figures"]),
                                                    f"prediction/{Path(record['prediction']).name}",
                                                    f"fold/{test}.fold.json"])
    for run_id in logged["parents"].values():
        assert runs[run_id]["artifacts"] == ["iso_table.csv"]
    conditions = [c["name"] for c in config["predictions"]["conditions"]]
    for entry in seen["registered"].values():
        assert runs[entry["run_id"]]["artifacts"] == sorted(f"predictions/{c}{s}" for c in conditions
                                                            for s in PREDICTION_SUFFIXES)
    # <experiment>/<run id>/artifacts/<path> per run artifact, and (MLflow 3 keeps a logged model apart
    # from its run) <experiment>/models/<model id>/artifacts/... per registered version (source models:/<id>).
    stored = [Path(p).parts for p in seen["stored"]]
    assert {"/".join(p) for p in stored if p[1] != "models"} == {
        f"{logged['experiment_id']}/{i}/artifacts/{a}" for i, r in runs.items() for a in r["artifacts"]}
    model_ids = {source.rsplit("/", 1)[1] for versions in seen["versions"].values() for _, _, source in versions}
    assert {p[2] for p in stored if p[1] == "models"} == {p[2] for p in stored if p[-1] == "MLmodel"} == model_ids
