"""`make reproduce`: run the whole workflow, build its HTML report, print the table and where things are.

``python -m crashfuse.reproduce`` runs Snakemake on the repository's ``Snakefile`` with the local
profile (2 cores) and ``config/config.yaml`` (the embedded default: the world's ``paper``
campaign, 11 tests x K = 1, 2, 3 x both input modes), then ``snakemake --report``, then prints the
paper's Table 2 for each input mode and the paths of the figures, the report and the MLflow store.
A finished run does nothing the second time; a killed run resumes where it stopped. The jobs run as
children of a :mod:`crashfuse.forkserver` started for the run, which imports the package once for all.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from crashfuse import forkserver
from crashfuse.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
SNAKEFILE = ROOT / "Snakefile"
PROFILE = ROOT / "workflow" / "profiles" / "local"
DEFAULT_CONFIG = ROOT / "config" / "config.yaml"


def snakemake_command(configfile: Path, workdir: Path, cores: int, *extra: str) -> list[str]:
    """The Snakemake invocation of this repository's workflow.

    Parameters
    ----------
    configfile : Path
        Workflow config (YAML).
    workdir : Path
        Working directory: relative paths in the config (``results``) and the embedded MLflow
        store (``mlflow.db``) live here.
    cores : int
        Cores Snakemake may use.
    *extra : str
        Further Snakemake arguments.

    Returns
    -------
    list of str
        argv, starting with this interpreter (so the jobs use this environment's ``crashfuse``).
    """
    return [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), "--profile", str(PROFILE),
            "--directory", str(workdir), "--configfile", str(configfile), "--cores", str(cores), *extra]


def results_dir(configfile: Path, workdir: Path) -> Path:
    """The config's ``results`` folder (schema default ``results``), resolved against ``workdir``."""
    try:
        config = yaml.safe_load(configfile.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise InputError(f"expected a readable YAML workflow config: {err}", configfile) from None
    if not isinstance(config, dict):
        raise InputError("expected a YAML mapping of settings", configfile)
    return workdir / config.get("results", "results")


def release_stale_lock(configfile: Path, workdir: Path) -> bool:
    """Remove the lock a killed run left in ``workdir`` (Snakemake keeps it after some kill signals), so
    that starting again resumes, as it is meant to; never while a Snakemake process works there.

    Returns
    -------
    bool
        True if a stale lock was removed.
    """
    if not any((workdir / ".snakemake" / "locks").glob("*")) or snakemake_running_in(workdir):
        return False
    subprocess.run(snakemake_command(configfile, workdir, 1, "--unlock"), check=True, capture_output=True)
    return True


def snakemake_running_in(workdir: Path) -> bool:
    """Whether a process whose command line names Snakemake works in ``workdir`` (its working directory or
    an argument). Without /proc (not Linux) nothing can be told apart: True, the safe answer."""
    procs = Path("/proc")
    if not (procs / "self" / "cmdline").is_file():
        return True
    for proc in procs.glob("[0-9]*"):
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
            cwd = os.readlink(proc / "cwd")
        except OSError:  # gone meanwhile, or not ours to read
            continue
        if any(b"snakemake" in a for a in argv) and (os.fsencode(workdir) in argv or cwd == os.fspath(workdir)):
            return True
    return False


@contextlib.contextmanager
def forkserver_running(log: Path):
    """A :mod:`crashfuse.forkserver` for the workflow's jobs while the block runs; yields their environment.

    The server starts with one BLAS thread, as Snakemake starts a one-thread job; its jobs find it through
    ``CRASHFUSE_FORKSERVER`` (until it listens, and if it fails, they run as plain processes).
    """
    log.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="crashfuse-") as folder, log.open("w") as log_file:
        address = os.path.join(folder, "forkserver.sock")
        one_thread = {**os.environ, **dict.fromkeys(forkserver.THREAD_VARIABLES, "1")}
        server = subprocess.Popen([sys.executable, "-m", "crashfuse", "forkserver", address, "--while-stdin-open"],
                                  env=one_thread, stdin=subprocess.PIPE, stdout=log_file, stderr=subprocess.STDOUT)
        try:
            yield {**os.environ, forkserver.ADDRESS: address}
        finally:
            server.stdin.close()  # the server stops at the end of its input
            try:
                server.wait(timeout=30)
            except subprocess.TimeoutExpired:
                server.kill()


def summary(results: Path) -> str:
    """The Table 2 of each input mode and the paths of the figures, report and MLflow store.

    Parameters
    ----------
    results : Path
        The workflow's results folder after a complete run.

    Returns
    -------
    str
        The Table 2 of each input mode and the mean scores over the held-out tests (Markdown),
        then one ``name: path`` line per output.
    """
    tables = [*sorted((results / "tables").glob("table2_*.md")), results / "tables" / "summary.md"]
    lines = [t.read_text() for t in tables if t.is_file()]
    lines += [f"ISO table:        {results / 'iso_table.csv'}",
              f"Tables (md, tex): {results / 'tables'}",
              f"Summary figure:   {results / 'figures' / 'iso_summary.png'}",
              f"Fold figures:     {results / 'folds'}/<inputs>/K<k>/<test>/<test>.png",
              f"HTML report:      {results / 'report.html'}"]
    tracking = results / "tracking.json"
    if tracking.is_file():
        logged = json.loads(tracking.read_text())
        lines += [f"MLflow store:     {logged['tracking_uri']} (experiment {logged['experiment_name']})",
                  f"MLflow UI:        mlflow ui --backend-store-uri {logged['tracking_uri']}, then "
                  f"http://127.0.0.1:5000/#/experiments/{logged['experiment_id']}?workflowType=machine_learning"]
    lines += [f"Registered model: {json.loads(p.read_text())['model_uri']} ({p})"
              for p in sorted((results / "registered").glob("*/*.json"))]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the workflow and its report; print the summary. Returns Snakemake's exit code on failure."""
    p = argparse.ArgumentParser(prog="python -m crashfuse.reproduce", description=__doc__.splitlines()[0])
    p.add_argument("--configfile", type=Path, default=DEFAULT_CONFIG, help="workflow config (default config/config.yaml)")
    p.add_argument("--workdir", type=Path, default=ROOT, help="working directory (default the repository)")
    p.add_argument("--cores", type=int, default=2, help="cores for Snakemake (default 2)")
    args = p.parse_args(argv)
    configfile, workdir = args.configfile.resolve(), args.workdir.resolve()
    try:
        results = results_dir(configfile, workdir)
    except InputError as err:
        print(f"crashfuse reproduce: error: {err}", file=sys.stderr)
        return 2
    if release_stale_lock(configfile, workdir):
        print("crashfuse reproduce: removed the lock a killed run left (no Snakemake process works here)")
    t0 = time.perf_counter()
    with forkserver_running(results / "logs" / "forkserver.log") as env:
        for extra in ((), ("--report", str(results / "report.html"))):
            done = subprocess.run(snakemake_command(configfile, workdir, args.cores, *extra), env=env, check=False)
            if done.returncode:
                return done.returncode
    print(f"\ncrashfuse reproduce: workflow complete in {time.perf_counter() - t0:.0f} s\n")
    print(summary(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
