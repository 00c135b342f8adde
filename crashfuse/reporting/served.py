"""A final model as an MLflow model: the pyfunc flavour (a DataFrame of conditions in, pulses out),
logged in its campaign's experiment and registered under a name per campaign.

``mlflow models serve -m models:/<name>/<version> --env-manager local`` then answers
``POST /invocations`` with ``{"dataframe_split": {"columns": [...], "data": [[...]]}}`` (docs/tracking.md).
Input columns are the engineer's units, as in the workflow config's ``predictions``: ``v0_mph,
front_weight_lb, rear_weight_lb`` and optionally ``powertrain, drive, name``. The output is one block
of rows per condition: ``condition`` (its ``name``, else its row number), ``outside_tests`` (the
condition or the pulse leaves the bias data: the band is wide there) and the prediction CSV's
columns (:meth:`crashfuse.method.rollout.Prediction.frame`).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
from pathlib import Path

import mlflow
import pandas as pd
from mlflow.models import infer_signature
from mlflow.tracking import MlflowClient

import crashfuse
from crashfuse.evaluation.iso_table import AUTO
from crashfuse.reporting.tracking import PREFIX, ROLE, campaign_experiment, resolve_tracking_uri

__all__ = ["INPUT_COLUMNS", "OPTIONAL_COLUMNS", "PulseModel", "register_model", "registered_name"]

INPUT_COLUMNS = ("v0_mph", "front_weight_lb", "rear_weight_lb")
OPTIONAL_COLUMNS = ("powertrain", "drive", "name")
FINAL = "final"
MODEL_SHA = PREFIX + "model_sha256"
# What a served model imports; crashfuse itself travels with the model (code_paths).
RUNTIME = ("numpy", "scipy", "scikit-learn", "pandas", "threadpoolctl", "mlflow")


class PulseModel(mlflow.pyfunc.PythonModel):
    """Predict the bias-corrected crash pulse, with its band, at each condition of a DataFrame.

    Logged as code (``pulse_model_code.py``), not as a pickle; the model's ``model_config`` may set
    ``n_samples`` and ``random_state``.

    Parameters
    ----------
    n_samples : int
        Monte Carlo samples per condition.
    random_state : int
        Seed of every condition's samples (the same condition gives the same pulse).
    """

    def __init__(self, n_samples: int = 1000, random_state: int = 0):
        self.n_samples = n_samples
        self.random_state = random_state

    def load_context(self, context):
        from crashfuse.method.model import load_model, load_surrogate

        settings = context.model_config or {}
        self.n_samples = int(settings.get("n_samples", self.n_samples))
        self.random_state = int(settings.get("random_state", self.random_state))
        self.model_ = load_model(context.artifacts["model"], load_surrogate(context.artifacts["surrogate"]))

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        """Pulses at the conditions of ``model_input`` (one row each), stacked; see the module docstring."""
        from crashfuse.method.rollout import predict
        from crashfuse.units import LB, MPH

        conditions = _checked(model_input)
        blocks = []
        for i, row in conditions.iterrows():
            pred = predict(self.model_, row.v0_mph * MPH, row.front_weight_lb * LB, row.rear_weight_lb * LB,
                           row.powertrain, row.drive, n_samples=self.n_samples, random_state=self.random_state)
            frame = pred.frame()
            frame.insert(0, "outside_tests", bool(pred.extrapolation["any"]))
            frame.insert(0, "condition", row["name"] or str(i))
            blocks.append(frame)
        return pd.concat(blocks, ignore_index=True)


def _checked(frame) -> pd.DataFrame:
    """The conditions with numeric speeds and weights, every optional column (None where blank);
    ValueError names a missing or bad column."""
    if not isinstance(frame, pd.DataFrame) or frame.empty:
        raise ValueError(f"expected a non-empty DataFrame with columns {list(INPUT_COLUMNS)}")
    missing = [c for c in INPUT_COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError(f"missing column(s) {missing}; expected {list(INPUT_COLUMNS)} (mph, lb) and optionally "
                         f"{list(OPTIONAL_COLUMNS)}")
    out = frame.reset_index(drop=True).copy()
    for column in OPTIONAL_COLUMNS:
        values = out[column] if column in out else pd.Series([None] * len(out))
        out[column] = [None if pd.isna(v) or str(v) == "" else str(v) for v in values]
    for column in INPUT_COLUMNS:
        values = pd.to_numeric(out[column], errors="coerce")
        if values.isna().any() or (values <= 0).any():
            raise ValueError(f"column {column}: expected positive numbers, got {out[column].tolist()}")
        out[column] = values.astype(float)
    return out


def registered_name(campaign_name: str, inputs: str, model: str) -> str:
    """``crashfuse-<campaign>`` for the ``auto`` model, ``crashfuse-<campaign>-<inputs>-<model>`` otherwise."""
    base = f"crashfuse-{campaign_name}"
    return base if model == AUTO else f"{base}-{inputs}-{model}"


def register_model(model_file, surrogate_file, campaign_name: str, *, inputs: str, model: str,
                   example: pd.DataFrame, artifacts=(), tracking_uri: str | None = None,
                   n_samples: int = 1000, random_state: int = 0) -> dict:
    """Log a final model as an MLflow pyfunc model in its campaign's experiment and register it.

    A model file already registered (same SHA-256) is not logged again: its version is returned.

    Parameters
    ----------
    model_file, surrogate_file : path
        The fitted model (``crashfuse fit`` on every test) and the CAE surrogate file it refers to.
    campaign_name : str
        Names the experiment (with the model's campaign hash) and the registered model.
    inputs, model : str
        The model's input mode and label (``state``, ``K2``; ``auto``, ``auto``).
    example : DataFrame
        Conditions (:data:`INPUT_COLUMNS`, optionally :data:`OPTIONAL_COLUMNS`): the signature's input
        example (its first row is predicted to infer the output schema).
    artifacts : iterable of path
        Further files of the run (its predictions and their figures).
    tracking_uri : str, optional
        As in :func:`crashfuse.reporting.tracking.resolve_tracking_uri`.
    n_samples, random_state : int
        The served model's Monte Carlo samples and seed.

    Returns
    -------
    dict
        ``name``, ``version``, ``run_id``, ``model_uri`` (``models:/<name>/<version>``), ``tracking_uri``.
    """
    from crashfuse.method.model import load_model, load_surrogate

    example = _checked(example).head(1)  # before anything is written
    uri = resolve_tracking_uri(tracking_uri)
    client = MlflowClient(tracking_uri=uri)
    name = registered_name(campaign_name, inputs, model)
    sha = hashlib.sha256(Path(model_file).read_bytes()).hexdigest()
    found = _version_of(client, name, sha)
    if found is not None:
        return _answer(found, uri)
    fitted = load_model(model_file, load_surrogate(surrogate_file))
    exp_id = campaign_experiment(client, uri, campaign_name, fitted.campaign_hash)
    probe = PulseModel(n_samples=n_samples, random_state=random_state)
    probe.model_ = fitted  # infers the output schema; the logged instance loads its model from the artifacts
    mlflow.set_tracking_uri(uri)
    tags = {ROLE: FINAL, PREFIX + "inputs": inputs, PREFIX + "k": model, MODEL_SHA: sha,
            PREFIX + "campaign": campaign_name, PREFIX + "campaign_hash": fitted.campaign_hash}
    with mlflow.start_run(experiment_id=exp_id, run_name=f"final {inputs} {model}", tags=tags):
        mlflow.log_params({"inputs": inputs, "model": model, "n_samples": n_samples, "seed": random_state,
                           "training_tests": ",".join(fitted.training_tests)})
        for path in artifacts:
            mlflow.log_artifact(str(path), artifact_path="predictions")
        info = mlflow.pyfunc.log_model(
            name="model", python_model=str(Path(__file__).with_name("pulse_model_code.py")),
            model_config={"n_samples": n_samples, "random_state": random_state},
            artifacts={"model": str(model_file), "surrogate": str(surrogate_file)},
            signature=infer_signature(example, probe.predict(None, example)),
            input_example=example, code_paths=[str(Path(crashfuse.__file__).parent)],
            pip_requirements=[f"{p}=={importlib.metadata.version(p)}" for p in RUNTIME],
            registered_model_name=name)
    version = client.get_model_version(name, info.registered_model_version)
    client.set_model_version_tag(name, version.version, MODEL_SHA, sha)
    return _answer(client.get_model_version(name, version.version), uri)


def _version_of(client: MlflowClient, name: str, sha: str):
    """The registered version of ``name`` whose model file has SHA-256 ``sha``, or None."""
    for version in client.search_model_versions(f"name = '{name}'"):
        if version.tags.get(MODEL_SHA) == sha:
            return version
    return None


def _answer(version, uri: str) -> dict:
    return {"name": version.name, "version": int(version.version), "run_id": version.run_id,
            "model_uri": f"models:/{version.name}/{version.version}", "tracking_uri": uri}

