"""The workflow's warm start: a command run by a forked child of `crashfuse forkserver` is the command, as its
own process would run it - output, files, exit code - and a killed command takes its child with it."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crashfuse import forkserver

CRASHFUSE = [sys.executable, "-m", "crashfuse"]


@pytest.fixture
def server(tmp_path):
    """A server on a pipe (as `make reproduce` starts it); yields (its process, its address)."""
    address = str(tmp_path / "forkserver.sock")
    env = {**os.environ, **dict.fromkeys(forkserver.THREAD_VARIABLES, "1")}
    proc = subprocess.Popen([*CRASHFUSE, "forkserver", address, "--while-stdin-open"], stdin=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 60
    while not os.path.exists(address):
        assert proc.poll() is None and time.monotonic() < deadline, "the server did not start listening"
        time.sleep(0.05)
    yield proc, address
    proc.stdin.close()
    proc.wait(timeout=30)
    assert not os.path.exists(address)  # it cleans up after itself


def run(args, cwd, address=None, **kwargs):
    env = {**os.environ, **dict.fromkeys(forkserver.THREAD_VARIABLES, "1")}
    env.pop(forkserver.ADDRESS, None)
    if address:
        env[forkserver.ADDRESS] = address
    return subprocess.Popen([*CRASHFUSE, *args], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, **kwargs)


def files(folder: Path) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError):
            state, ppid = stat.read_text().rsplit(")", 1)[1].split()[:2]
            if int(ppid) == pid and state != "Z":
                found.append(int(stat.parent.name))
    return found


def test_a_forked_command_writes_what_its_own_process_writes(server, tmp_path):
    _, address = server
    args = ["world", "generate", "--out", "campaign", "--world", "multibody", "--n-cae", "20"]
    for name, via in (("plain", None), ("forked", address)):
        (tmp_path / name).mkdir()
        done = run(args, tmp_path / name, via)  # a relative path: the child works in the command's directory
        out, err = done.communicate(timeout=120)
        assert done.returncode == 0, err
        assert "campaign" in out
    assert files(tmp_path / "forked" / "campaign") == files(tmp_path / "plain" / "campaign")


def test_exit_code_and_error_come_back_and_no_server_means_its_own_process(server, tmp_path):
    _, address = server
    for via in (address, str(tmp_path / "nobody.sock")):
        done = run(["fit", "no-such-campaign", "--k", "1", "--out", "m.cfmodel"], tmp_path, via)
        out, err = done.communicate(timeout=60)
        assert done.returncode == 2 and "no-such-campaign: campaign folder does not exist" in err and not out
        done = run(["fit", "--k", "x"], tmp_path, via)  # argparse exits by SystemExit
        assert done.wait(timeout=60) == 2 and "invalid" in done.stderr.read()


def test_a_killed_command_ends_its_child_and_the_server_ends_with_its_input(server, tmp_path):
    proc, address = server
    command = run(["world", "generate", "--out", "campaign"], tmp_path, address)  # ~3 s: the paper preset
    deadline = time.monotonic() + 30
    while not children(proc.pid):
        assert command.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    command.send_signal(signal.SIGKILL)
    command.wait(timeout=10)
    deadline = time.monotonic() + 1  # well before the generation would have ended by itself
    while children(proc.pid):
        assert time.monotonic() < deadline, "the killed command's child lives on"
        time.sleep(0.01)
    assert not (tmp_path / "campaign" / "conditions.csv").exists()  # no campaign written


def test_a_command_handed_to_the_server_does_not_import_numpy():
    """The client's own start-up is what every job still pays: the CLI module without numpy and the rest."""
    done = subprocess.run([sys.executable, "-c", "import sys, crashfuse.cli; print(sorted(m for m in sys.modules "
                           "if m.split('.')[0] in {'numpy', 'scipy', 'sklearn', 'pandas', 'matplotlib'}))"],
                          capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def test_only_a_named_server_outside_slurm_jobs_is_used(monkeypatch):
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    monkeypatch.delenv(forkserver.ADDRESS, raising=False)
    assert not forkserver.wanted(["fit"])
    monkeypatch.setenv(forkserver.ADDRESS, "/tmp/some.sock")
    assert forkserver.wanted(["fit"]) and not forkserver.wanted(["forkserver", "/tmp/other.sock"])
    monkeypatch.setenv("SLURM_JOB_ID", "42")  # a SLURM job's work stays in its allocation
    assert not forkserver.wanted(["fit"])
