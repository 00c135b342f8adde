# Paths, config checks and the fold list. Folds come from the campaign's tests: read from
# conditions.csv when the DAG is built (a user campaign), or after the `campaign` checkpoint
# has generated the campaign (the default).

import csv
import json
import shlex
import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError

# Jobs run the `crashfuse` of the environment running Snakemake, whether or not it is on PATH.
shell.prefix(f'set -euo pipefail; export PATH={shlex.quote(str(Path(sys.executable).parent))}:"$PATH"; ')

RESULTS = config["results"]
GENERATED = config["campaign"]["path"] is None
CAMPAIGN = f"{RESULTS}/paper" if GENERATED else config["campaign"]["path"]
METHOD = config["method"]
DIAG = config["diagnosis"]
# The auto model chooses among the state folds (crashfuse.evaluation.fold.AUTO_INPUTS; docs/decisions.md 23).
AUTO_INPUTS = ["state"]
if config["auto"] and not set(AUTO_INPUTS) <= set(config["inputs"]):
    raise WorkflowError(f"config auto: the auto model chooses among the {AUTO_INPUTS} folds; add them to inputs "
                        f"(got {config['inputs']}) or set auto: false")


def method_args():
    """The fits' method options; a param of the train jobs, so that changing one reruns the fits
    (the Monte Carlo samples are the rollouts' param)."""
    flags = [
        f"--seed {METHOD['seed']}",
        f"--n-grid {METHOD['n_grid']}",
        f"--assignment {METHOD['assignment']}",
    ]
    for key in ("trend", "cae_decel"):  # None: each input mode's default
        flags += [f"--{key.replace('_', '-')} {METHOD[key]}"] if METHOD[key] else []
    for key in ("use_companion", "extra_inputs", "pooled", "onset", "shrink", "chain"):  # None: the mode's default
        name = key.replace("_", "-")
        flags += [] if METHOD[key] is None else [f"--{name}" if METHOD[key] else f"--no-{name}"]
    return " ".join(flags)


# The input modes whose K > 1 models pool by default (crashfuse.method.config; method.pooled overrides;
# tests/test_workflow.py holds this copy to the package).
POOLED_INPUTS = ["state"]


def _pooled_from(wildcards):
    """The smallest K's label (`K<k>`) whose pooled GP a larger K of a pooling input mode reuses
    (`crashfuse fit --pooled-from`: the same fit, made once); None for the smallest K or a mode that
    does not pool."""
    k_min = f"K{min(config['ks'])}"
    pools = wildcards.inputs in POOLED_INPUTS if METHOD["pooled"] is None else METHOD["pooled"]
    return None if not pools or wildcards.model == k_min else k_min


def pooled_model(wildcards):
    """The fold's model of the smallest K, for a larger K's `train` (nothing when it does not pool)."""
    k_min = _pooled_from(wildcards)
    return [] if k_min is None else fold_path("model.cfmodel").format(inputs=wildcards.inputs, model=k_min,
                                                                      test=wildcards.test)


def final_path(inputs="{inputs}", model="{model}"):
    """`<results>/final/{inputs}/{model}/model.cfmodel`: a model fitted on every test."""
    return f"{RESULTS}/final/{inputs}/{model}/model.cfmodel"


def pooled_final_model(wildcards):
    """The final model of the smallest K, for a larger K's `final_model` (nothing when it does not pool)."""
    k_min = _pooled_from(wildcards)
    return [] if k_min is None else final_path(wildcards.inputs, k_min)


def pooled_flag(wildcards, input):
    """`--pooled-from MODEL` when the job reads a smaller K's model."""
    return f"--pooled-from {shlex.quote(input.pooled)}" if input.pooled else ""


def fold_path(name):
    """`<results>/folds/{inputs}/{model}/{test}/<name>`: a file of one fold (model, prediction, rollout facts,
    ISO rows, coverage, fold JSON, figure), wildcards kept; `model` is `K<k>`, or `auto` (inputs `auto`)."""
    return f"{RESULTS}/folds/{{inputs}}/{{model}}/{{test}}/{name}"


def table_inputs():
    """The `inputs` labels of the ISO table: the config's input modes, and `auto` with the auto model."""
    return [*config["inputs"], "auto"] if config["auto"] else config["inputs"]


def fold_title(wildcards):
    """A fold figure's title."""
    if wildcards.model == "auto":
        return f"{wildcards.test}: auto"
    return f"{wildcards.test}: {wildcards.inputs} inputs, K = {wildcards.model[1:]}"


def candidate_files(pattern, test):
    """`pattern` of the auto model's candidates of one test: every K of its input modes (AUTO_INPUTS)."""
    return expand(fold_path(pattern), inputs=AUTO_INPUTS, model=[f"K{k}" for k in config["ks"]], test=test)


def read_tests(campaign_dir):
    """Test run_ids of a campaign folder, in file order, from its conditions.csv.

    Raises WorkflowError naming the file and field when the file or its columns are missing, the
    campaign has fewer than two tests, or config `tests` names a run that is not a test.
    """
    path = Path(campaign_dir) / "conditions.csv"
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as err:
        raise WorkflowError(f"{path}: expected a campaign's conditions.csv ({err.strerror})")
    if not rows or not {"run_id", "source"} <= set(rows[0]):
        raise WorkflowError(f"{path}: expected columns run_id and source, got {list(rows[0]) if rows else 'no rows'}")
    tests = [r["run_id"].strip() for r in rows if r["source"].strip().lower() == "test"]
    wanted = config["tests"] or tests
    unknown = [t for t in wanted if t not in tests]
    if unknown:
        raise WorkflowError(f"config tests: {unknown} are not tests of {path} (tests: {tests})")
    if len(tests) < 2:
        raise WorkflowError(f"{path}: field source: leave-one-test-out needs at least 2 tests, found {len(tests)}")
    return wanted


def campaign_dir(wildcards=None):
    """The campaign folder; waits for the `campaign` checkpoint when the workflow generates it."""
    if GENERATED:
        return checkpoints.campaign.get().output.folder
    return CAMPAIGN


def fold_files(pattern):
    """`pattern` expanded over every fold: config inputs x ks x the campaign's (selected) tests, and the
    auto model's fold of each test with `auto`."""
    tests = read_tests(campaign_dir())
    out = expand(pattern, inputs=config["inputs"], model=[f"K{k}" for k in config["ks"]], test=tests)
    return out + (expand(pattern, inputs="auto", model="auto", test=tests) if config["auto"] else [])


# The diagnosis rolls out the state folds of its K instead of refitting its GMM-GPR rows when the workflow
# fits them for every test (config `tests` empty); else it fits its own.
DIAGNOSIS_READS_FOLDS = (DIAG["enabled"] and DIAG["residual"] and "state" in config["inputs"]
                         and DIAG["k"] in config["ks"] and not config["tests"])


def diagnosis_fold_models(wildcards):
    """The fold models the diagnosis reads (`crashfuse diagnose --fold-models`), or nothing."""
    if not DIAGNOSIS_READS_FOLDS:
        return []
    return expand(fold_path("model.cfmodel"), inputs="state", model=f"K{DIAG['k']}", test=read_tests(campaign_dir()))


def train_priority(wildcards):
    """The folds the diagnosis reads first: it is the longest job, and started last it runs alone."""
    return int(DIAGNOSIS_READS_FOLDS and wildcards.inputs == "state" and wildcards.model == f"K{DIAG['k']}")


def fold_models_flag(wildcards, input):
    """`--fold-models MODEL...` when the job reads the workflow's fold models."""
    return f"--fold-models {' '.join(shlex.quote(m) for m in input.fold_models)}" if input.fold_models else ""


PREDICT = config["predictions"]
_CONDITIONS = {c["name"]: c for c in PREDICT["conditions"]}


def condition_args(wildcards):
    """`crashfuse predict`'s condition options of the configured condition `wildcards.condition`."""
    c = _CONDITIONS[wildcards.condition]
    flags = [f"--v0-mph {c['v0_mph']}", f"--front-weight-lb {c['front_weight_lb']}",
             f"--rear-weight-lb {c['rear_weight_lb']}"]
    flags += [f"--{key} {shlex.quote(str(c[key]))}" for key in ("powertrain", "drive") if c.get(key) is not None]
    return " ".join(flags)


def prediction_label(wildcards):
    """How a prediction figure names its model: `auto`, or `state K1` ..."""
    return "auto" if wildcards.model == "auto" else f"{wildcards.inputs} K = {wildcards.model[1:]}"


PREDICT_MODELS = [("auto", "auto") if m == "auto" else Path(m).parts for m in PREDICT["models"]]


def prediction_files(suffix, models=PREDICT_MODELS):
    """`<results>/predictions/<inputs>/<model>/<condition><suffix>` of the configured (or given) models and
    every configured condition."""
    return [f"{RESULTS}/predictions/{i}/{m}/{c}{suffix}" for i, m in models for c in _CONDITIONS]


def registration(inputs, model):
    return f"{RESULTS}/registered/{inputs}/{model}.json"


def registration_inputs(wildcards):
    """A final model's registration waits for the tracking step and the model registered before it:
    one MLflow writer at a time (SQLite)."""
    me = PREDICT_MODELS.index((wildcards.inputs, wildcards.model))
    before = [registration(*PREDICT_MODELS[me - 1])] if me else []
    return [f"{RESULTS}/tracking.json", *before]


def all_outputs(wildcards):
    """The final targets: the table, its renderings, the summary figure, tracking, diagnosis, validations."""
    out = [
        f"{RESULTS}/iso_table.csv",
        f"{RESULTS}/tables/summary.md",
        f"{RESULTS}/figures/iso_summary.png",
    ]
    out += fold_files(fold_path("{test}.png"))
    out += prediction_files(".png")
    if config["tracking"]["enabled"]:
        out.append(f"{RESULTS}/tracking.json")
        out += [registration(*m) for m in PREDICT_MODELS]
    if config["diagnosis"]["enabled"]:
        out.append(f"{RESULTS}/diagnosis/diagnosis.json")
    if config["validation"]["enabled"]:
        out.append(f"{RESULTS}/diagnosis/validation.csv")
    if config["validation"]["method"]["enabled"]:
        out.append(f"{RESULTS}/validation/method_matrix.csv")
    return out
