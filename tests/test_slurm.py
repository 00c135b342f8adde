"""The SLURM profile on a real SLURM cluster: one node on this machine (munged, slurmctld, slurmd
as root, all their state in a temp folder) runs a small config through workflow/profiles/slurm.
The fold jobs must be SLURM jobs of the cluster, and the results those of a local run.

Needs root and Debian's slurm-wlm and munge (installed with apt-get when missing). The setup is
documented in docs/workflow.md, "On a SLURM cluster".
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import re
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import yaml

pytest.importorskip("snakemake_executor_plugin_slurm", reason="no SLURM executor plugin: pip install -e '.[slurm]'")

from servers import free_port, stop_group  # noqa: E402
from test_workflow import ROOT, SNAKEFILE, TEST_CONFIG, snakemake  # noqa: E402

PROFILE = ROOT / "workflow" / "profiles" / "slurm" / "config.yaml"
PARTITION = "crashfuse"  # the test cluster's one partition, in place of the site's
SBIN = "/usr/sbin:/sbin"  # the daemons and mungekey live here, which may not be on a user's PATH
DAEMONS = ("munged", "slurmctld", "slurmd")


# --- the cluster ------------------------------------------------------------------------------------


def _binary(name: str) -> str | None:
    return shutil.which(name) or shutil.which(name, path=SBIN)


def _require_slurm() -> None:
    """Skip unless we are root with SLURM and MUNGE installed, installing them with apt-get if missing."""
    if os.geteuid() != 0:
        pytest.skip("the one-node SLURM cluster runs its daemons as root; run as root")
    needed = [*DAEMONS, "mungekey", "sbatch", "srun", "squeue", "sinfo", "scancel"]
    if any(_binary(b) is None for b in needed) and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        install = ["apt-get", "install", "-y", "-q", "slurm-wlm", "munge"]
        if subprocess.run(install, capture_output=True, timeout=900, env=env).returncode:
            subprocess.run(["apt-get", "update", "-q"], capture_output=True, timeout=600, env=env)
            subprocess.run(install, capture_output=True, timeout=900, env=env)
    missing = [b for b in needed if _binary(b) is None]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed, and apt-get install slurm-wlm munge did not install them")


def _write_slurm_conf(base: Path) -> Path:
    """A one-node cluster of this machine: its CPUs and memory as slurmd itself reads them (`slurmd -C`);
    no cgroups, no accounting; every file in `base`, free loopback ports."""
    node = subprocess.run([_binary("slurmd"), "-C"], capture_output=True, text=True, check=True).stdout.splitlines()[0]
    name = re.match(r"NodeName=(\S+)", node)[1]
    conf = base / "slurm.conf"
    conf.write_text("\n".join([
        "ClusterName=crashfuse-test",
        f"SlurmctldHost={name}(127.0.0.1)",
        f"SlurmctldPort={free_port()}",
        f"SlurmdPort={free_port()}",
        "SlurmUser=root",
        "SlurmdUser=root",
        "AuthType=auth/munge",
        "CredType=cred/munge",
        f"AuthInfo=socket={base / 'munge' / 'munge.socket'}",
        f"StateSaveLocation={base / 'state'}",
        f"SlurmdSpoolDir={base / 'spool'}",
        f"SlurmctldPidFile={base / 'slurmctld.pid'}",
        f"SlurmdPidFile={base / 'slurmd.pid'}",
        "ProctrackType=proctrack/linuxproc",
        "TaskPlugin=task/none",
        "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_Core_Memory",
        "MpiDefault=none",
        "ReturnToService=2",
        "AccountingStorageType=accounting_storage/none",
        "JobAcctGatherType=jobacct_gather/none",
        "JobCompType=jobcomp/none",
        f"{node} NodeAddr=127.0.0.1 State=UNKNOWN",
        f"PartitionName={PARTITION} Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
    ]) + "\n")
    return conf


def _srun_keeping_conf(base: Path, conf: Path) -> Path:
    """A folder holding an `srun` that sets SLURM_CONF: the jobstep plugin strips every SLURM_* variable,
    SLURM_CONF too, before its srun inside the job, and our slurm.conf is not at the default path."""
    folder = base / "bin"
    folder.mkdir()
    wrapper = folder / "srun"
    wrapper.write_text(f'#!/bin/sh\nexport SLURM_CONF={conf}\nexec {_binary("srun")} "$@"\n')
    wrapper.chmod(0o755)
    return folder


@contextlib.contextmanager
def _daemon(command: list, log: Path, env: dict):
    """Run ``command`` in the foreground as its own process group, output to ``log``; on exit SIGTERM
    to the group, SIGKILL after 20 s."""
    with log.open("w") as out:
        proc = subprocess.Popen([str(c) for c in command], stdout=out, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)
    try:
        yield proc
    finally:
        stop_group(proc)


def _log_tails(base: Path) -> str:
    return "".join(f"\n--- {name}.log ---\n{(base / f'{name}.log').read_text()[-1500:]}" for name in DAEMONS)


def _wait_until(ready, what: str, daemons: dict, base: Path, timeout: float = 60) -> None:
    """Poll ``ready()`` until true; fail with the daemons' logs when one exits or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    while not ready():
        for name, proc in daemons.items():
            if proc.poll() is not None:
                pytest.fail(f"{name} exited with code {proc.returncode} while waiting for {what}{_log_tails(base)}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} within {timeout} s{_log_tails(base)}")
        time.sleep(0.5)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A running one-node cluster; yields the environment of its clients (SLURM_CONF, the srun wrapper
    first on PATH, then this venv)."""
    _require_slurm()
    base = tmp_path_factory.mktemp("slurm")
    for folder in ("state", "spool", "munge"):
        (base / folder).mkdir()
    (base / "munge").chmod(0o755)  # munged's socket folder: every user may enter it
    conf = _write_slurm_conf(base)
    path = [_srun_keeping_conf(base, conf), Path(sys.executable).parent, os.environ.get("PATH", "")]
    # Nothing of an outer SLURM job (this suite may itself run in one) may leak into this cluster's jobs.
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "SBATCH_", "SRUN_"))}
    env.update(SLURM_CONF=str(conf), PATH=os.pathsep.join(map(str, path)))
    key = base / "munge.key"
    subprocess.run([_binary("mungekey"), "--create", f"--keyfile={key}"], check=True, capture_output=True)
    socket = base / "munge" / "munge.socket"
    # --force: munged wants every folder above its socket enterable by all; pytest's temp root is 0700.
    munged = [_binary("munged"), "--foreground", "--force", f"--socket={socket}", f"--key-file={key}",
              f"--pid-file={base / 'munged.pid'}", f"--seed-file={base / 'munged.seed'}"]
    with contextlib.ExitStack() as stack:
        daemons = {"munged": stack.enter_context(_daemon(munged, base / "munged.log", env))}
        _wait_until(socket.exists, "munge socket", daemons, base)
        daemons["slurmctld"] = stack.enter_context(_daemon([_binary("slurmctld"), "-D"], base / "slurmctld.log", env))
        daemons["slurmd"] = stack.enter_context(_daemon([_binary("slurmd"), "-D"], base / "slurmd.log", env))
        stack.callback(subprocess.run, ["scancel", "--partition", PARTITION], env=env, capture_output=True)
        _wait_until(lambda: _sinfo(env) == "idle", "idle node in sinfo", daemons, base)
        yield env


def _sinfo(env: dict) -> str:
    return subprocess.run(["sinfo", "--noheader", "--Node", "--format=%T"], env=env, capture_output=True,
                          text=True).stdout.strip()


# --- the workflow on it -----------------------------------------------------------------------------


def _small_config(path: Path) -> dict:
    """config/test.yaml cut to two folds (state K1 of two tests): no auto model, predictions, tracking
    or diagnosis."""
    config = yaml.safe_load(TEST_CONFIG.read_text())
    config.update(tests=config["tests"][:2], ks=config["ks"][:1], inputs=["state"], auto=False,
                  predictions={"conditions": []}, tracking={"enabled": False}, diagnosis={"enabled": False})
    path.write_text(yaml.safe_dump(config))
    return config


def _profile_for_the_test_cluster(folder: Path) -> Path:
    """workflow/profiles/slurm with this cluster's partition in place of the site's. An account, if the
    profile sets one, stays: a cluster without accounting takes any."""
    settings = yaml.safe_load(PROFILE.read_text())
    settings["default-resources"]["slurm_partition"] = PARTITION
    folder.mkdir()
    (folder / "config.yaml").write_text(yaml.safe_dump(settings))
    return folder


def _submitted(output: str) -> dict[str, str]:
    """{SLURM job id: what Snakemake submitted (`rule_<name>` or `group_fold_...`)} from its log."""
    return {jobid: next(p for p in Path(log).parts if p.startswith(("rule_", "group_")))
            for jobid, log in re.findall(r"has been submitted with SLURM jobid (\d+) \(log: (\S+)\)", output)}


def _job_states(env: dict) -> dict[str, tuple[str, str]]:
    """{job id: (state, partition)} of every job slurmctld still knows (finished ones for MinJobAge)."""
    out = subprocess.run(["squeue", "--states=all", "--noheader", "--format=%i|%T|%P"], env=env,
                         capture_output=True, text=True, check=True).stdout
    return {i: (state, partition) for i, state, partition in (line.split("|") for line in out.splitlines())}


@pytest.mark.slow
def test_slurm_profile_runs_the_folds_as_slurm_jobs(cluster, tmp_path):
    config_file = tmp_path / "config.yaml"
    config = _small_config(config_file)
    profile = _profile_for_the_test_cluster(tmp_path / "profile")
    on_slurm = tmp_path / "slurm"
    on_slurm.mkdir()
    # Status checks from 1 s on instead of 40 s: the jobs here take seconds.
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), "--directory", str(on_slurm),
               "--configfile", str(config_file), "--profile", str(profile),
               "--slurm-init-seconds-before-status-checks", "1", "--seconds-between-status-checks", "1"]
    local = tmp_path / "local"
    with concurrent.futures.ThreadPoolExecutor(1) as pool:  # the local run's jobs fill the SLURM run's waits
        reference = pool.submit(snakemake, local, "--cores", "2", configfile=config_file, warm=True)
        done = subprocess.run(command, cwd=on_slurm, env=cluster, capture_output=True, text=True, timeout=600)
        reference.result()
    output = done.stdout + done.stderr
    assert done.returncode == 0, output

    submitted, states = _submitted(output), _job_states(cluster)
    # A warning, so that the ids reach the summary of `make test` (pytest -q under xdist shows no prints);
    # a builtin category: xdist's controller cannot import a class defined in a test module.
    warnings.warn("SLURM jobs seen: " + "; ".join(f"{j} {what} {'/'.join(states.get(j, ('?',)))}"
                                                  for j, what in submitted.items()))
    folds = [j for j, what in submitted.items() if what.startswith("group_fold")]
    assert len(folds) == len(config["tests"]) * len(config["ks"]) * len(config["inputs"])
    assert "rule_prepare" in submitted.values()
    assert {states[j] for j in submitted} == {("COMPLETED", PARTITION)}

    results = Path(config["results"])
    for table in ("iso_table.csv", "tables/summary.csv"):
        assert (on_slurm / results / table).read_text() == (local / results / table).read_text()
