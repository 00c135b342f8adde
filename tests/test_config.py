"""MethodConfig: each input mode's defaults, validation naming the setting, the flag named by the CLI."""

import dataclasses

import numpy as np
import pytest

from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.evaluation.fold import fold_settings
from crashfuse.method.config import BIAS_SETTINGS, MODE_DEFAULTS, MethodConfig
from crashfuse.method.mixture import GMMGPBias
from crashfuse.method.projection import bias_columns, is_label


@pytest.mark.parametrize("inputs", ["paper", "state"])
def test_unset_mode_settings_take_the_input_modes_defaults(inputs):
    config = MethodConfig(k=2, inputs=inputs)
    assert {name: getattr(config, name) for name in MODE_DEFAULTS[inputs]} == MODE_DEFAULTS[inputs]
    assert MethodConfig(k=2, inputs=inputs, trend="linear", pooled=not config.pooled).pooled is not config.pooled


def test_the_two_modes_differ_where_the_method_says():
    paper, state = MethodConfig(inputs="paper"), MethodConfig(inputs="state")
    assert (paper.target, paper.trend, paper.pooled, paper.onset, paper.shrink, paper.use_companion) == (
        "absolute", "constant", False, False, False, False)
    assert (state.target, state.trend, state.pooled, state.onset, state.shrink, state.use_companion) == (
        "relative", "zero", True, False, True, True)
    assert (paper.cae_decel, state.cae_decel) == ("none", "unloading")
    assert (paper.extra_inputs, state.extra_inputs) == (False, True)


def test_a_default_state_config_hands_the_bias_model_its_defaults_with_the_state_bounds():
    config = MethodConfig(k=3, inputs="state")
    own = GMMGPBias(n_clusters=3, trend="zero", pooled=True, theta_bounds=(0.1, 1e3),
                    nugget_bounds=(1e-2, 10.0)).get_params()
    assert GMMGPBias(n_clusters=3, **config.bias_params()).get_params() == own
    assert config.changed_bias_settings() == {}


def test_the_labels_theta_is_bounded_by_the_bias_model_s_own_bound_the_other_inputs_by_theta_min():
    columns = bias_columns("state", {"powertrain": ["EV", "ICE"], "drive": ["AWD", "FWD", "RWD"]}, velocity="sqrt")
    assert [is_label(c) for c in columns] == [False] * 5 + [True] * 3
    lower, upper = MethodConfig(inputs="state").bias_params(columns)["theta_bounds"]
    assert lower == (0.1,) * 5 + (GMMGPBias().theta_bounds[0],) * 3 and upper == GMMGPBias().theta_bounds[1]
    assert MethodConfig(inputs="state").bias_params(columns[:5])["theta_bounds"][0] == 0.1


def test_a_default_paper_config_hands_the_bias_model_its_own_bounds():
    own = GMMGPBias(n_clusters=2).get_params()
    assert GMMGPBias(n_clusters=2, **MethodConfig(k=2, inputs="paper").bias_params()).get_params() == own
    assert MethodConfig(inputs="state", nugget_min=1e-4).bias_params()["nugget_bounds"] == (1e-4, 10.0)


@pytest.mark.parametrize("kw, field", [
    (dict(k=0), "k"),
    (dict(k=1.5), "k"),
    (dict(k=True), "k"),
    (dict(inputs="both"), "inputs"),
    (dict(assignment="vote"), "assignment"),
    (dict(n_grid=1), "n_grid"),
    (dict(random_state=-1), "random_state"),
    (dict(target="ratio"), "target"),
    (dict(trend="cubic"), "trend"),
    (dict(velocity="log"), "velocity"),
    (dict(cae_decel=True), "cae_decel"),
    (dict(cae_decel="loading"), "cae_decel"),
    (dict(pooled="yes"), "pooled"),
    (dict(inputs="paper", onset=True), "onset"),
    (dict(inputs="paper", shrink=True), "shrink"),
    (dict(inputs="state", shrink="yes"), "shrink"),
    (dict(n_restarts=-1), "n_restarts"),
    (dict(max_condition_points=0), "max_condition_points"),
    (dict(theta_max_candidates=()), "theta_max_candidates"),
    (dict(theta_max_candidates=(1.0, -2.0)), "theta_max_candidates"),
    (dict(theta_max_candidates="10"), "theta_max_candidates"),
    (dict(theta_max_candidates=(1.0, True)), "theta_max_candidates"),
    (dict(theta_min=0.0), "theta_min"),
    (dict(theta_min="small"), "theta_min"),
    (dict(theta_min=10.0, theta_max_candidates=(1.0, 10.0)), "theta_min"),
    (dict(nugget_min=0.0), "nugget_min"),
    (dict(nugget_min="none"), "nugget_min"),
    (dict(nugget_min=10.0), "nugget_min"),
])
def test_bad_settings_name_the_setting(kw, field):
    with pytest.raises(InputError) as err:
        MethodConfig(**kw)
    assert err.value.field == field


def test_numpy_scalars_become_plain_values():
    config = MethodConfig(k=np.int64(2), n_grid=np.int32(40), random_state=np.int64(7), weights=np.bool_(False),
                          theta_max_candidates=[1, 10])
    values = config.as_dict().values()
    assert all(v is None or type(v) in (str, int, float, bool, tuple) for v in values)
    assert (config.k, config.n_grid, config.random_state, config.weights) == (2, 40, 7, False)
    assert config.theta_max_candidates == (1.0, 10.0)


def test_fold_settings_list_only_the_bias_settings_a_fit_changed():
    plain = fold_settings(MethodConfig(k=1, inputs="state"), n_samples=200)
    assert not any(key.startswith("bias_") for key in plain) and plain["n_samples"] == 200
    assert {"k", "inputs", "random_state"}.isdisjoint(plain) and set(BIAS_SETTINGS).isdisjoint(plain)
    quick = fold_settings(MethodConfig(estimate_scatter=False, theta_max_candidates=(1.0, 10.0)), n_samples=5)
    assert quick["bias_estimate_scatter"] is False and quick["bias_theta_max_candidates"] == "(1.0, 10.0)"
    assert dataclasses.replace(MethodConfig(), n_restarts=0).changed_bias_settings() == {"n_restarts": 0}


@pytest.mark.parametrize("args, flag", [
    (["--inputs", "paper", "--onset"], "--onset"),
    (["--inputs", "paper", "--shrink"], "--shrink"),
    (["--inputs", "state", "--seed", "1", "--holdout", "T01"], None),  # the config is fine: the campaign is not
])
def test_the_cli_names_the_flag_of_a_bad_setting(tmp_path, capsys, args, flag):
    assert main(["fit", str(tmp_path / "nowhere"), "--k", "1", *args, "--out", str(tmp_path / "m.cfmodel")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    if flag:
        assert f"field '{flag}'" in err
    else:
        assert "nowhere" in err and "field '--" not in err
