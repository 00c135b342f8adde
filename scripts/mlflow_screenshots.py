"""Screenshots of the MLflow UI on a workflow's runs, taken with headless Chromium.

Run from the project folder after ``make reproduce`` (Chromium from the OS packages, e.g.
``apt-get install chromium``)::

    .venv/bin/python scripts/mlflow_screenshots.py [--db mlflow.db] [--out docs/img]

It starts ``mlflow server`` on loopback over the SQLite store, opens the campaign's experiment
(which must open on its runs, not on the GenAI overview) and the compare view of the parent runs
(one per input mode and K, and ``auto``), and writes ``mlflow_runs.png`` and ``mlflow_compare.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

from mlflow.tracking import MlflowClient

BIN = Path(sys.executable).parent
# The UI's mode (GenAI or model training) is the browser's, not the experiment's: a fresh profile opens
# in GenAI mode on an empty traces overview unless the URL asks for model training.
MODEL_TRAINING = "workflowType=machine_learning"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--db", default="mlflow.db", help="the SQLite tracking store (default mlflow.db)")
    p.add_argument("--out", default="docs/img", help="folder for the PNG files (default docs/img)")
    p.add_argument("--wait-ms", type=int, default=20000, help="how long the page may render (virtual time)")
    args = p.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        sys.exit("no Chromium on PATH (apt-get install chromium)")
    uri = f"sqlite:///{Path(args.db).resolve()}"
    exp, parents = _parent_runs(MlflowClient(tracking_uri=uri))
    port = _free_port()
    server = subprocess.Popen([str(BIN / "mlflow"), "server", "--host", "127.0.0.1", "--port", str(port),
                               "--workers", "1", "--backend-store-uri", uri],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                              env={**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true",
                                   "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"})
    try:
        base = f"http://127.0.0.1:{port}"
        _wait_up(base)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        runs = urllib.parse.quote(json.dumps(parents))
        pages = {"mlflow_runs.png": f"{base}/#/experiments/{exp}?{MODEL_TRAINING}",
                 "mlflow_compare.png": f"{base}/#/compare-runs?runs={runs}&experiments="
                                       f"{urllib.parse.quote(json.dumps([exp]))}&{MODEL_TRAINING}"}
        for name, url in pages.items():
            _screenshot(browser, url, out / name, args.wait_ms)
            print(f"wrote {out / name}: {url}")
    finally:
        os.killpg(server.pid, 15)
        server.wait(timeout=30)
    return 0


def _parent_runs(client: MlflowClient) -> tuple[str, list[str]]:
    """The crashfuse experiment with the most recent runs and its parent runs' ids."""
    exps = [e for e in client.search_experiments() if e.name.startswith("crashfuse/")]
    if not exps:
        sys.exit("no crashfuse experiment in the store: run the workflow first")
    exp = max(exps, key=lambda e: e.last_update_time or 0)
    parents = client.search_runs([exp.experiment_id], "tags.`crashfuse.role` = 'parent'", max_results=50)
    return exp.experiment_id, [r.info.run_id for r in parents]


def _screenshot(browser: str, url: str, png: Path, wait_ms: int) -> None:
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                        f"--user-data-dir={profile}", "--window-size=1600,1000",
                        f"--virtual-time-budget={wait_ms}", f"--screenshot={png.resolve()}", url],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=180)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_up(base: str, timeout: float = 90) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(base + "/health", timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    sys.exit(f"mlflow server not up at {base} within {timeout} s")


if __name__ == "__main__":
    raise SystemExit(main())
