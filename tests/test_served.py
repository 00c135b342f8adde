"""A final model as an MLflow model: registered per campaign, loaded as pyfunc, and served on loopback."""

from __future__ import annotations

import json
import os
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
import mlflow  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from crashfuse.cli import main  # noqa: E402
from crashfuse.method.config import MethodConfig  # noqa: E402
from crashfuse.method.model import fit_model, save_surrogate  # noqa: E402
from crashfuse.method.rollout import predict  # noqa: E402
from crashfuse.method.surrogate import CAESurrogate  # noqa: E402
from crashfuse.reporting.served import register_model  # noqa: E402
from crashfuse.units import LB, MPH  # noqa: E402
from crashfuse.world.generate import build  # noqa: E402
from crashfuse.world.presets import resolve  # noqa: E402
from servers import free_port, serving  # noqa: E402

pytestmark = pytest.mark.xdist_group("served")  # one worker fits and registers the model for the module

SAMPLES = 20
INSIDE = {"name": "inside", "v0_mph": 25.0, "front_weight_lb": 2100.0, "rear_weight_lb": 1560.0,
          "powertrain": "Type I", "drive": "FWD"}
BEYOND = {**INSIDE, "name": "beyond", "v0_mph": 39.0}  # the paper tests stop at 35 mph


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A final model (every test, state K1) and its surrogate file."""
    root = tmp_path_factory.mktemp("final")
    campaign = build(resolve("paper"), seed=0, n_cae=20)[0]
    surrogate = CAESurrogate(random_state=0).fit(campaign)
    save_surrogate(surrogate, root / "surrogate.cfmodel")
    model = fit_model(campaign, MethodConfig(k=1, inputs="state", n_grid=40, n_restarts=0), surrogate=surrogate)
    model.save(root / "model.cfmodel", surrogate_file=root / "surrogate.cfmodel")
    return root / "model.cfmodel", root / "surrogate.cfmodel", model


@pytest.fixture(scope="module")
def registered(tmp_path_factory, files):
    """The final model registered once in a store of its own; the tests only read it (registering it
    again must change nothing)."""
    root = tmp_path_factory.mktemp("registry")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    model_file, surrogate_file, _ = files
    (root / "inside.png").write_bytes(b"png")
    with pytest.MonkeyPatch.context() as env:
        env.delenv("MLFLOW_TRACKING_URI", raising=False)
        out = register_model(model_file, surrogate_file, "paper", inputs="state", model="K1",
                             example=pd.DataFrame([INSIDE, BEYOND]), artifacts=[root / "inside.png"],
                             tracking_uri=uri, n_samples=SAMPLES, random_state=3)
        yield uri, out


def _direct(model, condition):
    """The same prediction without MLflow."""
    return predict(model, condition["v0_mph"] * MPH, condition["front_weight_lb"] * LB,
                   condition["rear_weight_lb"] * LB, condition["powertrain"], condition["drive"],
                   n_samples=SAMPLES, random_state=3)


def test_a_registered_final_model_predicts_pulses_as_the_package_does(registered, files):
    uri, out = registered
    assert out["name"] == "crashfuse-paper-state-K1" and out["version"] == 1
    client = MlflowClient(tracking_uri=uri)
    run = client.get_run(out["run_id"])
    assert run.data.tags["crashfuse.role"] == "final" and run.data.params["n_samples"] == str(SAMPLES)
    assert client.get_experiment(run.info.experiment_id).name.startswith("crashfuse/paper-")
    assert "predictions/inside.png" in {a.path for a in client.list_artifacts(out["run_id"], "predictions")}

    mlflow.set_tracking_uri(uri)
    served = mlflow.pyfunc.load_model(out["model_uri"])
    got = served.predict(pd.DataFrame([INSIDE, BEYOND]))
    assert list(got["condition"].unique()) == ["inside", "beyond"]
    assert got.groupby("condition")["outside_tests"].first().to_dict() == {"inside": False, "beyond": True}
    want = _direct(files[2], INSIDE).frame()
    mine = got[got.condition == "inside"].drop(columns=["condition", "outside_tests"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(mine, want)


def test_registering_the_same_model_file_again_reuses_its_version(registered, files):
    uri, out = registered
    again = register_model(files[0], files[1], "paper", inputs="state", model="K1",
                           example=pd.DataFrame([INSIDE]), tracking_uri=uri, n_samples=SAMPLES, random_state=3)
    assert again == out
    assert len(MlflowClient(tracking_uri=uri).search_model_versions("name = 'crashfuse-paper-state-K1'")) == 1


def test_bad_conditions_are_refused_naming_the_column(tmp_path, files, capsys):
    model_file, surrogate_file, _ = files
    bad = json.dumps([{**INSIDE, "v0_mph": "fast"}])
    code = main(["register", str(model_file), "--surrogate", str(surrogate_file), "--campaign-name", "paper",
                 "--inputs", "state", "--label", "K1", "--conditions-json", bad,
                 "--tracking-uri", f"sqlite:///{tmp_path / 'mlflow.db'}"])
    err = capsys.readouterr().err
    assert code == 2 and "--conditions-json" in err and "v0_mph" in err and "positive numbers" in err
    missing = json.dumps([{k: v for k, v in INSIDE.items() if k != "rear_weight_lb"}])
    assert main(["register", str(model_file), "--surrogate", str(surrogate_file), "--campaign-name", "paper",
                 "--inputs", "state", "--label", "K1", "--conditions-json", missing]) == 2
    assert "rear_weight_lb" in capsys.readouterr().err
    assert not (tmp_path / "mlflow.db").exists()  # nothing logged


@pytest.mark.slow
def test_mlflow_models_serve_answers_a_prediction_request(registered, files, tmp_path):
    uri, out = registered
    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "mlflow").exists():
        pytest.skip("the mlflow command is not installed beside this Python")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    command = [str(bin_dir / "mlflow"), "models", "serve", "-m", out["model_uri"], "--env-manager", "local",
               "-h", "127.0.0.1", "-p", str(port)]
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    with serving(command, tmp_path / "serve.log", env, url + "/ping"):
        body = {"dataframe_split": {"columns": list(INSIDE), "data": [list(INSIDE.values())]}}
        request = urllib.request.Request(url + "/invocations", data=json.dumps(body).encode(),
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=60) as r:
            rows = pd.DataFrame(json.load(r)["predictions"])
        want = _direct(files[2], INSIDE)
        assert (rows["condition"] == "inside").all() and len(rows) == len(want.time)
        np.testing.assert_allclose(rows["decel_g"], want.frame()["decel_g"], rtol=1e-12)
        np.testing.assert_allclose(rows["decel_hi_g"], want.frame()["decel_hi_g"], rtol=1e-12)
