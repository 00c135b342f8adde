"""MLflow tracking of an evaluation: one experiment per campaign, a parent run per (inputs, K) and a
child run per held-out test.

Logging is one serial step after all folds have finished (`log_evaluation`), not one writer per
fold job: SQLite allows a single writer at a time, so parallel fold jobs would meet "database is
locked" errors, and two jobs creating the same experiment race (one of them fails on the unique
name). A serial step also lets every child of a parent be checked for identical param and metric
keys before anything is written. Runs are keyed by tags (campaign hash through the experiment,
role, inputs, K, test id): logging again updates the runs it finds instead of adding new ones.
The run and tag keys and the fold JSON schema are documented in ``docs/tracking.md``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd
from mlflow.entities import Metric, Param, RunTag, ViewType
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from crashfuse.errors import InputError
from crashfuse.gp.threads import cpu_kernels
from crashfuse.evaluation.iso_table import AUTO, BASELINE, ISO_TABLE, SCORES, model_order, model_tag, window_key
from crashfuse.evaluation.records import CONDITIONS, FOLD_SUFFIX, FoldRecord, read_fold_json
from crashfuse.reporting.tables import read_iso_table

DEFAULT_DB = "mlflow.db"
ARTIFACTS = "mlartifacts"
PREFIX = "crashfuse."
ROLE, PARENT, FOLD = PREFIX + "role", "parent", "fold"
KEY_TAGS = (ROLE, PREFIX + "inputs", PREFIX + "k", PREFIX + "test_id")
PARENT_RUN = "mlflow.parentRunId"
# The UI opens an experiment of this kind on its runs, not on the GenAI overview (MLflow 3)
EXPERIMENT_KIND = {"mlflow.experimentKind": "custom_model_development"}
FIXED_PARAMS = ("k", "test_id", "inputs", "seed", "campaign", *CONDITIONS)
ISO_TOLERANCE = 1e-5  # fold JSON vs iso_table.csv, which evaluate writes with 6 significant digits
BATCH = 100  # MLflow's limit of params (and tags) per log_batch call


@dataclasses.dataclass
class Fold:
    """One fold as logged: its JSON record, where it was read from, and its CAE baseline scores."""

    path: Path
    record: FoldRecord
    cae_iso: dict[str, float]

    @property
    def key(self) -> tuple[str, str, str]:
        return self.record.inputs, self.record.model, self.record.test_id

    def params(self) -> dict[str, str]:
        """Flat run params: K, test id, inputs, seed, campaign, conditions and settings."""
        r = self.record
        fixed = dict(k=r.k, test_id=r.test_id, inputs=r.inputs, seed=r.seed, campaign=r.campaign["name"],
                     **{c: r.conditions[c] for c in CONDITIONS})
        return {k: str(v) for k, v in {**fixed, **r.settings}.items()}

    def metrics(self) -> dict[str, float]:
        """ISO scores of the corrected prediction and of CAE, fit diagnostics and coverage."""
        return {**self.record.iso_metrics(), **self.cae_iso, **self.record.metrics}

    def run_time(self) -> tuple[int, int] | None:
        """The fold's (start, end) in UNIX milliseconds, None when its record does not know them."""
        t = self.record.run_time
        return (int(t["start"] * 1000), int(t["end"] * 1000)) if t else None

    def files(self) -> dict[str, list[Path]]:
        """Artifact folder -> files: figures, the prediction CSV and the fold JSON itself."""
        here = self.path.parent
        out = {"figures": [here / f for f in self.record.figures], "fold": [self.path]}
        if self.record.prediction:
            out["prediction"] = [here / self.record.prediction]
        return out


def resolve_tracking_uri(uri: str | None = None, project_dir: str | os.PathLike | None = None) -> str:
    """The tracking URI: ``uri`` (from config), else ``MLFLOW_TRACKING_URI``, else the embedded store.

    The embedded store is ``sqlite:///<project_dir>/mlflow.db`` (project_dir defaults to the
    current directory).
    """
    chosen = uri or os.environ.get("MLFLOW_TRACKING_URI")
    if chosen:
        return chosen
    return f"sqlite:///{Path(project_dir or Path.cwd()).resolve() / DEFAULT_DB}"


def experiment_name(campaign_name: str, campaign_hash: str) -> str:
    """One experiment per campaign: ``crashfuse/<name>-<first 12 hex digits of the content hash>``."""
    return f"crashfuse/{campaign_name}-{campaign_hash[:12]}"


def config_hash(config: str | os.PathLike | Mapping | None) -> str:
    """SHA-256 of a config file's bytes or of a mapping as canonical JSON; ``''`` for None."""
    if config is None:
        return ""
    if isinstance(config, Mapping):
        data = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str).encode()
    else:
        try:
            data = Path(config).read_bytes()
        except OSError as err:
            raise InputError(f"expected a readable config file: {err.strerror}", config) from None
    return hashlib.sha256(data).hexdigest()


def git_commit(project_dir: str | os.PathLike | None = None) -> str:
    """The commit checked out in ``project_dir`` (``git rev-parse HEAD``), or ``'unknown'``."""
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=project_dir, capture_output=True, text=True,
                              timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return done.stdout.strip()


# --- reading and checking an evaluation directory ----------------------------------------------


def load_folds(results_dir: str | os.PathLike,
               fold_files: Iterable[str | os.PathLike] | None = None) -> tuple[pd.DataFrame, list[Fold]]:
    """Read ``iso_table.csv`` of ``results_dir`` and the fold JSON files and check they agree.

    Parameters
    ----------
    results_dir : str or PathLike
        Holds ``iso_table.csv``.
    fold_files : iterable of path, optional
        The fold JSON files of this evaluation (the workflow passes its fold list, so folds left
        over from an earlier, wider config are not read). Default: every ``*.fold.json`` below
        ``results_dir``.

    Returns
    -------
    iso : pandas.DataFrame
        The validated ISO table.
    folds : list of Fold
        Sorted by (inputs, K, test id).

    Raises
    ------
    InputError
        No fold JSON; folds from different campaigns; a repeated fold; a fold whose scores differ
        from its iso_table.csv rows or that has no CAE rows; a K row of the table without fold
        JSON; a missing figure or prediction file; or folds of one (inputs, K) whose settings,
        metrics or windows have different names (the UI's compare view needs identical keys).
    """
    results_dir = Path(results_dir)
    iso = read_iso_table(results_dir / ISO_TABLE)
    if fold_files is None:
        paths = sorted(results_dir.rglob(f"*{FOLD_SUFFIX}"))
        if not paths:
            raise InputError(f"expected fold JSON files (*{FOLD_SUFFIX}) below this folder, found none", results_dir)
    else:
        paths = [Path(p) for p in fold_files]
        if not paths:
            raise InputError("expected at least one fold JSON file, got an empty list", field="fold_files")
    scores = iso.set_index(["inputs", "model", "test_id", "window_ms"])[list(SCORES)]
    folds, seen = [], {}
    for path in paths:
        record = read_fold_json(path)
        fold = Fold(path, record, _cae_metrics(scores, record, path, results_dir))
        if fold.key in seen:
            raise InputError(f"repeats the fold {fold.key} of {seen[fold.key]}", path, "test_id")
        seen[fold.key] = path
        _check_scores(scores, record, path, results_dir)
        _check_files(fold)
        folds.append(fold)
    _check_campaign(folds)
    _check_coverage(iso, seen, results_dir)
    _check_same_keys(folds)
    return iso, sorted(folds, key=lambda f: (f.record.inputs, model_order(f.record.model), f.record.test_id))


def _cae_metrics(scores: pd.DataFrame, record: FoldRecord, path: Path, results_dir: Path) -> dict[str, float]:
    out = {}
    for window in record.iso:
        try:
            row = scores.loc[(record.inputs, BASELINE, record.test_id, window)]
        except KeyError:
            raise InputError(f"has no {BASELINE} row for test {record.test_id}, inputs {record.inputs}, window "
                             f"{window} (needed as the baseline of {path.name})", results_dir / ISO_TABLE,
                             "model") from None
        out.update({f"cae_iso_{s}_{window_key(window)}": float(row[s]) for s in SCORES})
    return out


def _check_scores(scores: pd.DataFrame, record: FoldRecord, path: Path, results_dir: Path) -> None:
    for window, values in record.iso.items():
        key = (record.inputs, record.model, record.test_id, window)
        if key not in scores.index:
            raise InputError(f"has no row {key} for the fold {path}", results_dir / ISO_TABLE, "test_id")
        row = scores.loc[key]
        off = [s for s in SCORES if abs(row[s] - values[s]) > ISO_TOLERANCE]
        if off:
            raise InputError(f"expected the scores of {results_dir / ISO_TABLE} for {key}, but {off[0]} is "
                             f"{values[off[0]]} here and {row[off[0]]} there", path, f"iso.{window}.{off[0]}")


def _check_files(fold: Fold) -> None:
    for folder, files in fold.files().items():
        for f in files:
            if not f.is_file():
                raise InputError(f"names {f}, which does not exist", fold.path, folder)


def _check_campaign(folds: list[Fold]) -> None:
    first = folds[0]
    for fold in folds[1:]:
        if fold.record.campaign != first.record.campaign:
            raise InputError(f"expected the campaign {first.record.campaign} of {first.path}, got "
                             f"{fold.record.campaign}", fold.path, "campaign")


def _check_coverage(iso: pd.DataFrame, seen: dict, results_dir: Path) -> None:
    rows = iso[iso["model"] != BASELINE]
    for inputs, model, test in rows[["inputs", "model", "test_id"]].drop_duplicates().itertuples(index=False):
        if (inputs, model, test) not in seen:
            raise InputError(f"has scores for test {test}, inputs {inputs}, model {model} but no fold JSON "
                             f"(*{FOLD_SUFFIX}) for it among the folds read", results_dir / ISO_TABLE, "model")


def _check_same_keys(folds: list[Fold]) -> None:
    groups: dict[tuple, Fold] = {}
    for fold in folds:
        ref = groups.setdefault(fold.key[:2], fold)
        for what, keys in (("params", Fold.params), ("metrics", Fold.metrics)):
            extra, missing = set(keys(fold)) - set(keys(ref)), set(keys(ref)) - set(keys(fold))
            if extra or missing:
                raise InputError(f"expected the same {what} names as {ref.path} (same inputs and K), but has "
                                 f"{sorted(extra)} extra and {sorted(missing)} missing", fold.path, what)
        clash = set(fold.record.settings) & set(FIXED_PARAMS)
        if clash:
            raise InputError(f"setting names {sorted(clash)} clash with the fixed params {FIXED_PARAMS}",
                             fold.path, "settings")


# --- logging -----------------------------------------------------------------------------------


def log_evaluation(results_dir: str | os.PathLike, tracking_uri: str | None = None,
                   config: str | os.PathLike | Mapping | None = None,
                   project_dir: str | os.PathLike | None = None,
                   fold_files: Iterable[str | os.PathLike] | None = None) -> dict[str, Any]:
    """Log an evaluation directory to MLflow, creating or updating its runs.

    Parameters
    ----------
    results_dir : str or PathLike
        Holds ``iso_table.csv`` and, unless ``fold_files`` is given, the ``*.fold.json`` files (at
        any depth) with their figures.
    tracking_uri : str, optional
        Tracking URI from config; else ``MLFLOW_TRACKING_URI``; else ``sqlite:///<project_dir>/mlflow.db``.
    config : path or mapping, optional
        The workflow config; its hash is tagged on every run.
    project_dir : str or PathLike, optional
        The project (git checkout, home of the embedded store); default the current directory.
    fold_files : iterable of path, optional
        The fold JSON files to log (see :func:`load_folds`); default every one below ``results_dir``.

    Returns
    -------
    dict
        ``tracking_uri``, ``experiment_id``, ``experiment_name``, ``parents`` {"inputs/K<k>": run_id}
        and ``folds`` {"inputs/K<k>/test_id": run_id}.
    """
    iso, folds = load_folds(results_dir, fold_files)
    uri = resolve_tracking_uri(tracking_uri, project_dir)
    client = MlflowClient(tracking_uri=uri)
    campaign = folds[0].record.campaign
    name = experiment_name(campaign["name"], campaign["hash"])
    exp_id = campaign_experiment(client, uri, campaign["name"], campaign["hash"])
    common = {PREFIX + "campaign": campaign["name"], PREFIX + "campaign_hash": campaign["hash"],
              PREFIX + "git_commit": git_commit(project_dir), PREFIX + "config_hash": config_hash(config),
              PREFIX + "kernels": cpu_kernels()}
    existing = _existing_runs(client, exp_id)
    out = {"tracking_uri": uri, "experiment_id": exp_id, "experiment_name": name, "parents": {}, "folds": {}}
    iso_file = Path(results_dir) / ISO_TABLE
    for (inputs, model), group in _groups(folds).items():
        k = model_tag(model)  # the K tag: the cluster count, the hybrid's effects after it; or auto
        key = (PARENT, inputs, str(k), "")
        name = AUTO if model == AUTO else f"{inputs} K={k}"
        tags = {**common, **dict(zip(KEY_TAGS, key)), "mlflow.runName": name}
        parent = _upsert(client, exp_id, existing.get(key, []), tags, _parent_params(group), _mean_metrics(group),
                         {"": [iso_file]}, _span(group))
        out["parents"][f"{inputs}/{model}"] = parent
        for fold in group:
            key = (FOLD, inputs, str(k), fold.record.test_id)
            tags = {**common, **dict(zip(KEY_TAGS, key)), PARENT_RUN: parent,
                    "mlflow.runName": f"{fold.record.test_id} {name}"}
            run = _upsert(client, exp_id, existing.get(key, []), tags, fold.params(), fold.metrics(), fold.files(),
                          fold.run_time())
            out["folds"][f"{inputs}/{model}/{fold.record.test_id}"] = run
    return out


def _groups(folds: list[Fold]) -> dict[tuple[str, str], list[Fold]]:
    out: dict[tuple[str, str], list[Fold]] = {}
    for fold in folds:
        out.setdefault(fold.key[:2], []).append(fold)
    return out


def _span(group: list[Fold]) -> tuple[int, int] | None:
    """A parent's (start, end): its first fold's start to its last fold's end; None if any is unknown."""
    times = [fold.run_time() for fold in group]
    if None in times:
        return None
    return min(t[0] for t in times), max(t[1] for t in times)


def _parent_params(group: list[Fold]) -> dict[str, str]:
    """The params every child of the parent shares (K, inputs, seed, campaign, common settings)."""
    shared = group[0].params()
    for fold in group[1:]:
        shared = {k: v for k, v in shared.items() if fold.params().get(k) == v}
    return shared


def _mean_metrics(group: list[Fold]) -> dict[str, float]:
    """Each child metric's mean over the held-out tests, under the same name, plus ``n_folds``."""
    names = group[0].metrics()
    means = {m: float(np.mean([f.metrics()[m] for f in group])) for m in names}
    return {**means, "n_folds": float(len(group))}


def campaign_experiment(client: MlflowClient, uri: str, campaign_name: str, campaign_hash: str) -> str:
    """The id of the campaign's experiment (:func:`experiment_name`), created or restored as needed."""
    name = experiment_name(campaign_name, campaign_hash)
    return _experiment(client, name, _artifact_location(uri, name))


def _artifact_location(uri: str, name: str) -> str | None:
    """Beside an embedded SQLite store, ``mlartifacts/<experiment>``; a server chooses its own."""
    if not uri.startswith("sqlite:///"):
        return None
    db = Path(uri.removeprefix("sqlite:///"))
    return (db.resolve().parent / ARTIFACTS / name.replace("/", "_")).as_uri()


def _experiment(client: MlflowClient, name: str, artifact_location: str | None) -> str:
    found = client.get_experiment_by_name(name)
    if found is None:
        try:
            return client.create_experiment(name, artifact_location=artifact_location, tags=EXPERIMENT_KIND)
        except MlflowException as err:
            if err.error_code != "RESOURCE_ALREADY_EXISTS":
                raise
            found = client.get_experiment_by_name(name)  # another process created it meanwhile
    if found.lifecycle_stage == "deleted":
        client.restore_experiment(found.experiment_id)
    for key, value in EXPERIMENT_KIND.items():
        if found.tags.get(key) != value:  # an experiment logged before the tag existed
            client.set_experiment_tag(found.experiment_id, key, value)
    return found.experiment_id


def _existing_runs(client: MlflowClient, exp_id: str) -> dict[tuple, list]:
    """Active runs of the experiment by their key tags (one query per page, oldest first)."""
    out: dict[tuple, list] = {}
    token = None
    while True:
        page = client.search_runs([exp_id], run_view_type=ViewType.ACTIVE_ONLY, max_results=1000,
                                  order_by=["attributes.start_time ASC"], page_token=token)
        for run in page:
            key = tuple(run.data.tags.get(t, "") for t in KEY_TAGS)
            if key[0]:
                out.setdefault(key, []).append(run)
        token = page.token
        if not token:
            return out


def _upsert(client: MlflowClient, exp_id: str, found: list, tags: dict, params: dict, metrics: dict,
            files: dict[str, list[Path]], span: tuple[int, int] | None = None) -> str:
    """Update the run keyed by ``tags`` or create it; return its id.

    MLflow params and a run's start time are immutable, so a run whose params changed (a new
    config) or whose fold ran again (``span``: its start and end, UNIX ms) is replaced: the old one
    is deleted (restorable until ``mlflow gc``) and a fresh run takes its key.
    """
    keep = next((r for r in found if r.data.params == params
                 and (span is None or r.info.start_time == span[0])), None)
    for run in found:
        if run is not keep:
            client.delete_run(run.info.run_id)
    if keep is None:
        run_id = client.create_run(exp_id, start_time=span and span[0], tags=tags,
                                   run_name=tags["mlflow.runName"]).info.run_id
        old_metrics = {}
    else:
        run_id, old_metrics = keep.info.run_id, keep.data.metrics
    now = int(time.time() * 1000)
    new = [Metric(k, v, now, 0) for k, v in metrics.items() if old_metrics.get(k) != v]
    pending = [Param(k, v) for k, v in params.items()] if keep is None else []
    run_tags = [RunTag(k, str(v)) for k, v in tags.items()]
    for i in range(0, max(len(new), len(pending), len(run_tags)), BATCH):
        client.log_batch(run_id, metrics=new[i:i + BATCH], params=pending[i:i + BATCH], tags=run_tags[i:i + BATCH])
    for folder, paths in files.items():
        for path in paths:
            client.log_artifact(run_id, str(path), artifact_path=folder or None)
    client.set_terminated(run_id, "FINISHED", end_time=span and span[1])
    return run_id
