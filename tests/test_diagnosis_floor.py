"""scripts/diagnosis_floor.py: what separates a test from its CAE rollout when no effect is missing."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.io.campaign_write import write_campaign
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve
from project_scripts import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("diagnosis_floor")


@pytest.fixture(scope="module")
def control():
    return build(resolve("withheld", ["none"]), seed=0, n_cae=12)[0]


def test_the_mount_is_taken_out_and_the_rollout_replays_its_runs_loading(script, control):
    table = script.floor(control)
    assert list(table.test) == list(control.tests)
    overall = np.sqrt((table[["raw", "body", "loading"]] ** 2).mean())
    assert overall.body < 0.3 * overall.raw  # the world's tests ring on a 110 Hz mount; the chain reads it back
    assert overall.loading < 0.15  # g: up to its turnaround the rollout without effects is the CAE run


def test_a_campaign_without_companions_is_a_clear_error(script, control, tmp_path):
    folder = write_campaign(control.subset(list(control.cae)[:4]), tmp_path / "cae_only")
    with pytest.raises(SystemExit, match="companion"):
        script.main([str(folder)])
