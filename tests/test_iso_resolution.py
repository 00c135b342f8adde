"""scripts/iso_resolution.py: how far a test's rating of its own CAE run moves under a smooth error."""

from __future__ import annotations

import numpy as np
import pytest

from crashfuse.io.campaign_write import write_campaign
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve
from project_scripts import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("iso_resolution")


@pytest.fixture(scope="module")
def campaign():
    return build(resolve("paper"), seed=0, n_cae=4)[0]


def test_an_error_far_below_the_pulse_loses_no_window_and_a_large_one_most(script, campaign):
    table = script.resolution(campaign, [1e-6, 3.0], "0-20", draws=20, seed=0)
    assert len(table) == 2 * len(campaign.tests)
    tiny, large = (table[table.rms_g == size] for size in (1e-6, 3.0))
    assert tiny.lost.max() == 0.0 and tiny["median"].abs().max() < 1e-3
    assert large.lost.mean() > 0.5 and (large["median"] < -0.01).all()


def test_the_errors_are_smooth_and_of_the_size_asked_over_the_window(script):
    rng = np.random.default_rng(0)
    inside = np.arange(2000) < 250
    errors = script.smooth_errors(2000, 8e-5, inside, 2.0, 3, rng)
    np.testing.assert_allclose(errors[:, inside].std(axis=1), 2.0)
    spectrum = np.abs(np.fft.rfft(errors, axis=1)) ** 2
    freq = np.fft.rfftfreq(2000, 8e-5)
    assert spectrum[:, freq > 500].sum() < 1e-3 * spectrum.sum()  # CFC 60: nothing left far above 100 Hz


def test_a_campaign_without_companions_is_a_clear_error(script, campaign, tmp_path):
    folder = write_campaign(campaign.subset([r for r in campaign.cae][:3]), tmp_path / "cae_only")
    with pytest.raises(SystemExit, match="companion"):
        script.main([str(folder), "--draws", "2"])
