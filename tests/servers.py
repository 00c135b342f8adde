"""Test-only handling of a server started on loopback: a free port, waiting for it, stopping it."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def serving(command: list[str], log: Path, env: dict, ready_url: str, timeout: float = 120):
    """Run ``command`` in its own process group (output to ``log``) until ``ready_url`` answers; on
    exit stop the group (SIGTERM, then SIGKILL after 20 s). A server that exits first fails the test
    with the end of its log."""
    with log.open("w") as out:
        server = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, env=env)
        try:
            _wait_up(ready_url, server, log, timeout)
            yield server
        finally:
            stop_group(server)


def stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM to the process group ``proc`` leads, SIGKILL after 20 s."""
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def mlflow_server(port: int, backend: str, artifacts: Path, workers: int, *extra: str) -> list[str]:
    """The `mlflow server` command beside this Python on 127.0.0.1 (skips the test if it is missing)."""
    mlflow_bin = Path(sys.executable).with_name("mlflow")
    if not mlflow_bin.exists():
        pytest.skip("the mlflow command is not installed beside this Python")
    return [str(mlflow_bin), "server", "--host", "127.0.0.1", "--port", str(port), "--workers", str(workers),
            "--backend-store-uri", backend, *extra, "--artifacts-destination", str(artifacts)]


def _wait_up(url: str, server: subprocess.Popen, log: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise AssertionError(f"the server exited with code {server.returncode}: {log.read_text()[-2000:]}")
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"the server did not answer {url} within {timeout} s")
