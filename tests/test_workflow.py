"""The Snakemake workflow: config schema, DAG shape, lint, profiles and a small end-to-end run.

Every Snakemake call runs in a temporary working directory (``--directory``), so nothing is written
into the repository's ``results/``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml
from mlflow.tracking import MlflowClient
from snakemake.cli import get_argument_parser
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from crashfuse import reproduce
from crashfuse.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
SNAKEFILE = ROOT / "Snakefile"
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
DEFAULT_CONFIG = ROOT / "config" / "config.yaml"
TEST_CONFIG = ROOT / "config" / "test.yaml"
CONDA_LINT = "Specify a conda environment or container for each rule."


def snakemake(workdir: Path, *args: str, configfile: Path = DEFAULT_CONFIG, check: bool = True, warm: bool = False):
    """Run this repository's workflow in ``workdir``; returns the CompletedProcess (stdout + stderr).
    ``warm``: its jobs are children of one :mod:`crashfuse.forkserver`, as `crashfuse.reproduce` runs them;
    a small run's jobs otherwise spend most of their CPU time importing the package."""
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), "--directory", str(workdir),
           "--configfile", str(configfile), *args]
    with contextlib.ExitStack() as stack:
        env = stack.enter_context(reproduce.forkserver_running(workdir / "forkserver.log")) if warm else None
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    if check and done.returncode:
        raise AssertionError(f"snakemake {' '.join(args)} failed:\n{done.stdout}\n{done.stderr}")
    return done


def job_counts(output: str) -> dict[str, int]:
    """The 'Job stats' table of a Snakemake run or dry run as {rule: count} (without the total)."""
    block = output.split("Job stats:", 1)[1].split("total", 1)[0]
    return {m[1]: int(m[2]) for m in re.finditer(r"^(\w+)\s+(\d+)\s*$", block, re.M)}


def write_config(path: Path, **changes) -> Path:
    """The default config with top-level ``changes``, written to ``path``."""
    config = yaml.safe_load(DEFAULT_CONFIG.read_text())
    config.update(changes)
    path.write_text(yaml.safe_dump(config))
    return path


# --- config schema ------------------------------------------------------------------------------


def test_default_config_is_the_schema_defaults():
    """config/config.yaml spells out exactly what an empty config gets from the schema."""
    empty, default = {}, yaml.safe_load(DEFAULT_CONFIG.read_text())
    validate(empty, str(SCHEMA))
    validate(default, str(SCHEMA))
    assert empty == default


def test_test_config_is_valid_and_small():
    config = yaml.safe_load(TEST_CONFIG.read_text())
    validate(config, str(SCHEMA))
    assert config["method"]["seed"] == 0  # filled in by the schema
    assert len(config["tests"]) * len(config["ks"]) * len(config["inputs"]) <= 6


@pytest.mark.parametrize("bad, named", [
    ({"ks": [0]}, "ks"),
    ({"ks": []}, "ks"),
    ({"ks": [1, 1]}, "ks"),
    ({"inputs": ["paper", "velocity"]}, "velocity"),
    ({"method": {"samples": 0}}, "samples"),
    ({"method": {"assignment": "vote"}}, "assignment"),
    ({"method": {"sample": 10}}, "sample"),
    ({"campaign": {"path": ""}}, "path"),
    ({"campaign": {"n_cae": 5}}, "n_cae"),
    ({"tracking": {"uri": 3}}, "uri"),
    ({"kss": [1]}, "kss"),
])
def test_bad_config_is_refused_naming_the_key(bad, named):
    with pytest.raises(WorkflowError, match=re.escape(named)):
        validate(bad, str(SCHEMA))


def test_the_workflows_copies_of_package_defaults_match_the_package():
    """common.smk names the auto model's and the pooling input modes without importing the package (1.5 s
    on every Snakemake start); they must stay the package's."""
    import ast

    from crashfuse.evaluation.fold import AUTO_INPUTS
    from crashfuse.method.config import MethodConfig
    from crashfuse.method.projection import INPUTS

    text = (ROOT / "workflow" / "rules" / "common.smk").read_text()
    copied = {name: ast.literal_eval(re.search(rf"^{name} = (\[.*\])$", text, re.M).group(1))
              for name in ("AUTO_INPUTS", "POOLED_INPUTS")}
    assert copied["AUTO_INPUTS"] == list(AUTO_INPUTS)
    assert copied["POOLED_INPUTS"] == [m for m in INPUTS if MethodConfig(inputs=m).bias_params()["pooled"]]


def test_snakemake_refuses_a_bad_config_before_running(tmp_path):
    done = snakemake(tmp_path, "-n", configfile=write_config(tmp_path / "c.yaml", ks=[0]), check=False)
    assert done.returncode != 0
    assert "0 is less than the minimum of 1" in done.stdout + done.stderr
    assert "instance['ks'][0]" in done.stdout + done.stderr
    assert not (tmp_path / "results").exists()


def test_reproduce_reports_an_unreadable_config(tmp_path):
    bad = tmp_path / "config.yaml"
    bad.write_text("results: [unclosed\n")
    with pytest.raises(InputError, match="YAML"):
        reproduce.results_dir(bad, tmp_path)
    assert reproduce.main(["--configfile", str(bad), "--workdir", str(tmp_path)]) == 2


def test_reproduce_removes_a_lock_only_no_snakemake_holds(tmp_path):
    locks = tmp_path / ".snakemake" / "locks"
    locks.mkdir(parents=True)
    (locks / "0.input.lock").write_text(str(tmp_path))
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "snakemake", str(tmp_path)])
    try:
        _wait_for_exec(holder.pid, b"snakemake")  # until exec, /proc shows the forking pytest worker's command
        assert reproduce.snakemake_running_in(tmp_path)
        assert not reproduce.release_stale_lock(TEST_CONFIG, tmp_path) and any(locks.iterdir())
    finally:
        holder.kill()
        holder.wait()
    assert not reproduce.snakemake_running_in(tmp_path)
    assert reproduce.release_stale_lock(TEST_CONFIG, tmp_path) and not any(locks.glob("*"))
    assert not reproduce.release_stale_lock(TEST_CONFIG, tmp_path)  # nothing left to remove


def _wait_for_exec(pid: int, word: bytes, timeout: float = 10.0) -> None:
    cmdline = Path(f"/proc/{pid}/cmdline")
    deadline = time.monotonic() + timeout
    while word not in cmdline.read_bytes():
        assert time.monotonic() < deadline, f"process {pid} never showed {word!r} in its command line"
        time.sleep(0.02)


# --- DAG ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A working directory where the workflow has generated the default (paper) campaign."""
    workdir = tmp_path_factory.mktemp("workflow")
    before = job_counts(snakemake(workdir, "-n").stdout)
    assert before["campaign"] == 1 and "train" not in before  # the checkpoint decides the folds
    snakemake(workdir, "--cores", "1", "--until", "campaign")
    return workdir


@pytest.mark.xdist_group("generated")  # one worker generates the campaign for all three
def test_default_dag_has_the_method_steps_per_test_k_and_input_mode(generated):
    """Each fold is four jobs: train -> rollout -> score, and its figure; each test's auto model one more
    (its choice), then score and figure."""
    counts = job_counts(snakemake(generated, "-n").stdout)
    conditions = pd.read_csv(generated / "results" / "paper" / "conditions.csv")
    n_tests = int((conditions["source"] == "test").sum())
    assert n_tests == 11
    assert counts["train"] == counts["rollout"] == n_tests * 3 * 2 and counts["auto"] == n_tests
    assert counts["score"] == counts["figure"] == n_tests * (3 * 2 + 1)
    assert counts["final_model"] == 3 and counts["final_auto"] == 1  # the state K the auto model chooses among
    assert counts["predict"] == counts["prediction_figure"] == 3  # the default config's conditions
    assert {counts[r] for r in ("prepare", "aggregate", "tables", "summary_figure", "track", "all")} == {1}
    assert "campaign" not in counts


@pytest.mark.xdist_group("generated")
def test_selected_tests_and_no_tracking(generated, tmp_path):
    config = write_config(tmp_path / "c.yaml", tests=["T03", "T10"], ks=[2],
                          tracking={"enabled": False})
    counts = job_counts(snakemake(generated, "-n", configfile=config).stdout)
    assert counts["train"] == 2 * 1 * 2
    assert "track" not in counts


@pytest.mark.xdist_group("generated")
def test_config_naming_an_unknown_test_is_refused(generated, tmp_path):
    config = write_config(tmp_path / "c.yaml", tests=["T03", "T99"])
    done = snakemake(generated, "-n", configfile=config, check=False)
    assert done.returncode != 0
    assert "['T99'] are not tests of" in done.stdout + done.stderr


def _conditions(folder: Path, tests: list[str]) -> Path:
    rows = [dict(run_id=t, source="test", v0_mph=35, front_weight_lb=2000, rear_weight_lb=1500, powertrain="ICE",
                 drive="FWD", cae_run_id=f"C{t}") for t in tests]
    rows += [dict(run_id=f"C{t}", source="cae", v0_mph=35, front_weight_lb=2000, rear_weight_lb=1500,
                  powertrain="ICE", drive="FWD", cae_run_id="") for t in tests]
    folder.mkdir()
    pd.DataFrame(rows).to_csv(folder / "conditions.csv", index=False)
    return folder


def test_user_campaign_folds_come_from_its_conditions(tmp_path):
    """A campaign named in config: no generation, one fold per test x K x input mode, read at DAG build."""
    campaign = _conditions(tmp_path / "lab", ["A1", "A2", "A3", "A4"])
    config = write_config(tmp_path / "c.yaml", campaign={"path": str(campaign)}, ks=[1, 2])
    counts = job_counts(snakemake(tmp_path, "-n", configfile=config).stdout)
    assert counts["train"] == 4 * 2 * 2
    assert "campaign" not in counts


def test_larger_k_reads_the_smallest_ks_pooled_gp_in_folds_and_final_models(tmp_path):
    """State K2 (pooling) trains and final model read the K1 model of the same test / of every test;
    paper K2 (no pooled GP) and every K1 fit from scratch."""
    campaign = _conditions(tmp_path / "lab", ["A1", "A2"])
    config = write_config(tmp_path / "c.yaml", campaign={"path": str(campaign)}, ks=[1, 2])
    commands = [line for line in snakemake(tmp_path, "-n", "-p", configfile=config).stdout.splitlines()
                if "crashfuse fit " in line]
    pooled = {re.search(r"--out (\S+)", c).group(1): re.search(r"--pooled-from (\S+)|$", c).group(1) for c in commands}
    assert len(pooled) == 2 * 2 * 2 + 2 and all(p is None for out, p in pooled.items() if "/K1/" in out)
    assert pooled["results/folds/state/K2/A1/model.cfmodel"] == "results/folds/state/K1/A1/model.cfmodel"
    assert pooled["results/folds/paper/K2/A1/model.cfmodel"] is None
    assert pooled["results/final/state/K2/model.cfmodel"] == "results/final/state/K1/model.cfmodel"


@pytest.mark.parametrize("value, flag", [(None, None), (True, "--use-companion"), (False, "--no-use-companion")])
def test_a_mode_default_is_passed_on_only_when_the_config_sets_it(tmp_path, value, flag):
    """``method.use_companion: null`` leaves each input mode its own default (no flag); a value reaches every fit."""
    campaign = _conditions(tmp_path / "lab", ["A1", "A2"])
    method = {**yaml.safe_load(DEFAULT_CONFIG.read_text())["method"], "use_companion": value}
    config = write_config(tmp_path / "c.yaml", campaign={"path": str(campaign)}, ks=[1], method=method)
    commands = [line for line in snakemake(tmp_path, "-n", "-p", configfile=config).stdout.splitlines()
                if "crashfuse fit " in line]
    flags = {re.search(r"--(?:no-)?use-companion\b|$", c).group(0) or None for c in commands}
    assert len(commands) > 2 * 2 and flags == {flag}  # the folds and the final model(s)


@pytest.mark.parametrize("tests, reused", [([], True), (["A1", "A2"], False)])
def test_the_diagnosis_rolls_out_the_state_folds_when_they_cover_every_test(tmp_path, tests, reused):
    """With every test held out in turn the diagnose job takes the state K1 fold models (`--fold-models`,
    waiting for them) instead of refitting its GMM-GPR rows; with a chosen list of tests it fits its own."""
    campaign = _conditions(tmp_path / "lab", ["A1", "A2"])
    config = write_config(tmp_path / "c.yaml", campaign={"path": str(campaign)}, tests=tests, ks=[1, 2])
    out = snakemake(tmp_path, "-n", "-p", configfile=config).stdout
    command = next(line for line in out.splitlines() if "crashfuse diagnose " in line)
    models = [f"results/folds/state/K1/{t}/model.cfmodel" for t in ("A1", "A2")]
    assert (f"--fold-models {' '.join(models)} " in command) is reused and ("--fold-models" in command) is reused


def test_user_campaign_with_one_test_is_refused(tmp_path):
    campaign = _conditions(tmp_path / "lab", ["A1"])
    config = write_config(tmp_path / "c.yaml", campaign={"path": str(campaign)})
    done = snakemake(tmp_path, "-n", configfile=config, check=False)
    assert done.returncode != 0
    assert "needs at least 2 tests, found 1" in done.stdout + done.stderr


def test_method_matrix_is_its_own_target_with_the_config_spread(tmp_path):
    config = write_config(tmp_path / "c.yaml", validation={"method": {"worlds": ["multibody"], "seeds": [4],
                                                                       "windows": ["0-60", "0-100"]}})
    assert "validate_method" not in job_counts(snakemake(tmp_path, "-n", configfile=config).stdout)
    done = snakemake(tmp_path, "-n", "-p", "results/validation/method_matrix.csv", configfile=config)
    assert job_counts(done.stdout) == {"validate_method": 1}
    assert "world validate-method --worlds multibody --withheld single pairs paper none noise" in done.stdout
    assert "--seeds 4 " in done.stdout and "--n-cae 150 1000" in done.stdout
    assert "--k 1 2 3 --auto --effects none --windows 0-60 0-100 " in done.stdout


def test_diagnosis_validation_is_its_own_target_with_the_config_spread(tmp_path):
    config = write_config(tmp_path / "c.yaml", validation={"worlds": ["multibody"], "seeds": [3], "n_cae": 40})
    assert "validate_diagnosis" not in job_counts(snakemake(tmp_path, "-n", configfile=config).stdout)
    done = snakemake(tmp_path, "-n", "-p", "results/diagnosis/validation.csv", configfile=config)
    assert job_counts(done.stdout) == {"validate_diagnosis": 1}
    assert ("world validate --worlds multibody --strengths realistic subtle --seeds 3 --pairs --n-cae 40 --jobs "
            in done.stdout)


def test_lint_is_clean_except_the_conda_advice(tmp_path):
    """The only lint is the conda/container advice: this workflow installs with pip (docs/workflow.md)."""
    done = snakemake(tmp_path, "--lint", check=False)
    lints = re.findall(r"^\s+\* (.+?):?$", done.stdout + done.stderr, re.M)
    assert lints, "expected the conda advice at least (did --lint run?)"
    assert set(lints) == {CONDA_LINT}


# --- profiles -------------------------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["local", "slurm"])
def test_profile_keys_are_snakemake_options(profile):
    if profile == "slurm":  # slurm-status-command is the executor plugin's option
        pytest.importorskip("snakemake_executor_plugin_slurm", reason="pip install -e '.[slurm]'")
    settings = yaml.safe_load((ROOT / "workflow" / "profiles" / profile / "config.yaml").read_text())
    options = {o for a in get_argument_parser()._actions for o in a.option_strings}
    assert [k for k in settings if f"--{k}" not in options] == []


def test_slurm_profile_targets_rules_of_this_workflow(tmp_path):
    settings = yaml.safe_load((ROOT / "workflow" / "profiles" / "slurm" / "config.yaml").read_text())
    assert settings["executor"] == "slurm"
    rules = set(snakemake(tmp_path, "--list-rules").stdout.split())
    assert set(settings["set-resources"]) <= rules


# --- end to end -------------------------------------------------------------------------------------


def _finished_models(log: str) -> list[str]:
    """The model files of the train jobs Snakemake's log reports finished."""
    outputs = dict((jobid, out) for out, jobid in
                   re.findall(r"rule train:\n(?:    .*\n)*?    output: (\S+)\n(?:    .*\n)*?    jobid: (\d+)", log))
    return [outputs[j] for j in re.findall(r"Finished jobid: (\d+) \(Rule: train\)", log)]


def _stop_group(pgid: int, grace: float = 30) -> None:
    """What a supervisor does after SIGTERM: a grace period, then SIGKILL. Snakemake 9.27 sometimes
    lingers after SIGTERM, holding its lock (seen in the suite); the resume must cope with either end."""
    for sig in (None, signal.SIGKILL):
        if sig is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pgid, sig)
        deadline = time.monotonic() + grace
        while _live_in_group(pgid):
            if time.monotonic() > deadline:
                break
            time.sleep(0.1)
        else:
            return
    raise AssertionError("the killed run's processes survived SIGKILL")


def _live_in_group(pgid: int) -> bool:
    """Whether a process of the group is alive (zombies are not: orphans may never be reaped where PID 1
    does not reap, as in some containers)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, _, group = stat.read_text().rsplit(")", 1)[1].split()[:3]
        except (OSError, IndexError):
            continue
        if int(group) == pgid and state != "Z":
            return True
    return False


def _killed_among_the_folds(command, env, workdir: Path, n_models: int) -> dict:
    """Start ``command``, kill it (SIGTERM to its process group) once its first train job has finished;
    return the fold models Snakemake reported finished, with their modification times."""
    log = workdir / "killed.log"
    with log.open("w") as out:
        run = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + 300
        while not _finished_models(log.read_text()):
            assert run.poll() is None and time.monotonic() < deadline, "no train job finished before the run ended"
            time.sleep(0.1)
        os.killpg(run.pid, signal.SIGTERM)
        assert run.wait(timeout=120) != 0
        _stop_group(run.pid)  # Snakemake outlives the wrapper while it shuts down, its lock still held
    left = {workdir / p: (workdir / p).stat().st_mtime_ns for p in _finished_models(log.read_text())}
    assert 0 < len(left) < n_models  # killed in the middle of the folds
    return left


@pytest.mark.slow
def test_end_to_end_on_the_test_config(tmp_path):
    """`python -m crashfuse.reproduce` on config/test.yaml, killed among the folds and started again
    (it finishes only what is missing), then: nothing to redo; a changed setting reruns only what
    depends on it."""
    config = yaml.safe_load(TEST_CONFIG.read_text())
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}  # the embedded store
    # 4 parallel jobs: folds run concurrently, the MLflow logging step must still lose nothing.
    command = [sys.executable, "-m", "crashfuse.reproduce", "--configfile", str(TEST_CONFIG),
               "--workdir", str(tmp_path), "--cores", "4"]
    results = tmp_path / config["results"]
    n_tests = len(config["tests"])
    left = _killed_among_the_folds(command, env, tmp_path, n_tests * len(config["ks"]) * len(config["inputs"]))
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert {p: p.stat().st_mtime_ns for p in left} == left  # the folds fitted before the kill were not redone
    for model in left:
        assert f"--out {model.relative_to(tmp_path)}" not in done.stdout + done.stderr
    iso = pd.read_csv(results / "iso_table.csv", dtype={"test_id": str})
    assert sorted(iso["test_id"].unique()) == sorted(config["tests"])
    assert sorted(iso["model"].unique()) == ["CAE"] + [f"K{k}" for k in config["ks"]] + ["auto"]
    assert len(iso) == n_tests * (len(config["inputs"]) * (1 + len(config["ks"])) + 2) * 3  # auto: CAE and auto
    assert iso["overall"].between(0, 1).all()
    for test in config["tests"]:  # the auto rows are the rows of the candidate its auto job chose
        facts = json.loads((results / "folds" / "auto" / "auto" / test / f"{test}.rollout.json").read_text())
        inputs, model = facts["settings"]["chosen"].split()
        rows = [iso[(iso.test_id == test) & (iso.inputs == i) & (iso.model == m)].overall.tolist()
                for i, m in (("auto", "auto"), (inputs, model))]
        assert rows[0] == rows[1]
    for condition in config["predictions"]["conditions"]:  # the deliverable: a condition nobody tested
        stem = results / "predictions" / "auto" / "auto" / condition["name"]
        predicted = json.loads(stem.with_suffix(".json").read_text())
        assert predicted["metrics"]["peak_decel_g"]["lo"] <= predicted["metrics"]["peak_decel_g"]["hi"]
        assert len(pd.read_csv(stem.with_suffix(".csv"))) > 100 and stem.with_suffix(".png").stat().st_size > 0
    assert "auto chose" in (results / "logs" / "final" / "auto.log").read_text()
    assert (results / "report.html").stat().st_size > 0
    assert str(results / "report.html") in done.stdout
    logged = json.loads((results / "tracking.json").read_text())
    assert len(logged["folds"]) == n_tests * (len(config["ks"]) * len(config["inputs"]) + 1)
    assert logged["tracking_uri"] == f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(logged["tracking_uri"])
    runs = client.search_runs([logged["experiment_id"]])
    n_parents = len(config["ks"]) * len(config["inputs"]) + 1
    assert len(runs) == n_parents + len(logged["folds"]) + 1  # and the final auto model's run
    assert sum(r.data.tags.get("crashfuse.role") == "fold" for r in runs) == len(logged["folds"])
    folds = [r for r in runs if r.data.tags.get("crashfuse.role") == "fold"]
    assert all(r.info.end_time - r.info.start_time >= 1000 * r.data.metrics["fit_seconds"] for r in folds)  # real times
    registered = json.loads((results / "registered" / "auto" / "auto.json").read_text())
    assert registered["model_uri"] == "models:/crashfuse-paper/1"  # the generated campaign's folder: paper
    assert client.get_run(registered["run_id"]).info.experiment_id == logged["experiment_id"]

    diagnosis = json.loads((results / "diagnosis" / "diagnosis.json").read_text())
    assert {"verdict", "effects", "regions", "shrink"} <= set(diagnosis)
    assert {e["effect"] for e in diagnosis["effects"]} == set(config["diagnosis"]["effects"])

    again = snakemake(tmp_path, "-n", configfile=TEST_CONFIG)
    assert "Nothing to be done" in again.stdout + again.stderr

    n_folds = n_tests * (len(config["ks"]) * len(config["inputs"]) + 1)  # scored and drawn; auto included
    changed = dict(config, method={**config["method"], "samples": config["method"]["samples"] + 1})
    (tmp_path / "changed.yaml").write_text(yaml.safe_dump(changed))
    counts = job_counts(snakemake(tmp_path, "-n", configfile=tmp_path / "changed.yaml").stdout)
    assert counts["rollout"] == n_folds - n_tests and counts["score"] == counts["figure"] == n_folds
    assert not {"train", "final_model", "prepare", "campaign", "diagnose"} & set(counts)  # samples: no refit
    assert counts["predict"] == len(config["predictions"]["conditions"])
    windows = dict(config, scoring={"windows": ["0-30", "0-60"]})
    (tmp_path / "windows.yaml").write_text(yaml.safe_dump(windows))
    counts = job_counts(snakemake(tmp_path, "-n", configfile=tmp_path / "windows.yaml").stdout)
    assert counts["score"] == n_folds
    assert not {"train", "rollout", "figure", "prepare", "campaign", "predict"} & set(counts)  # only the scores

    uri = dict(config, tracking={"enabled": True, "uri": f"sqlite:///{tmp_path / 'other.db'}"})
    (tmp_path / "uri.yaml").write_text(yaml.safe_dump(uri))
    counts = job_counts(snakemake(tmp_path, "-n", configfile=tmp_path / "uri.yaml").stdout)
    assert set(counts) == {"track", "register", "all"}
