"""The noise control: a campaign whose CAE model is exact, so its tests differ from their CAE runs by
measurement noise alone.

Issue 16's control: a bias correction must not lose a test the CAE already predicts. The worlds'
``none`` campaigns withhold no effect but keep a measurement chain (resonance, sensor, filter) the CAE
runs lack, so the CAE there is good, not right. Here each test's pulse is replaced by its companion CAE
run as the campaign reader sees it (cropped at contact, at CFC 60; over the test's record length) plus white noise of
:data:`NOISE_G` g at the record's sampling rate, filtered at CFC 60 over a longer record (as a test's
pre- and post-trigger data: no transients at the ends) - about 0.25 g rms after the filter. It reads and
writes campaign files only, so any campaign (not only a synthetic one) can be turned into its control.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.io.atomic import write_text
from crashfuse.io.campaign import read_campaign
from crashfuse.signals.filters import cfc_filter
from crashfuse.units import G0

NOISE_G = 2.0  # g rms of the white noise before the CFC 60 filter
NOISE_CFC = 60
PAD = 2000  # samples of noise filtered beyond each end of the record


def make_noise_control(folder, seed: int, noise_g: float = NOISE_G) -> Path:
    """Rewrite every test of the campaign in ``folder`` as its companion CAE run plus filtered noise.

    Parameters
    ----------
    folder : path
        A campaign folder (docs/campaign-format.md) whose tests have CSV pulses and companion CAE runs;
        changed in place (the test pulse files; a ``cfc`` column, if any, says 60 on the test rows).
    seed : int
        Seeds the noise.
    noise_g : float
        Std of the white noise in g before the filter.

    Returns
    -------
    Path
        ``folder``.

    Raises
    ------
    InputError
        A test without a companion CAE run, or one whose pulse is not a CSV file of the campaign.
    """
    folder = Path(folder)
    campaign = read_campaign(folder)
    conditions = pd.read_csv(folder / "conditions.csv", dtype=str, keep_default_na=False)
    for test in campaign.tests:  # every test checked before any file changes
        _check_test(folder, conditions, campaign, test)
    rng = np.random.default_rng(seed)
    for test in campaign.tests:
        companion = campaign.companion(test)
        keep = companion.time <= campaign.pulses[test].time[-1] + 1e-9  # the test's own record length
        time, decel = companion.time[keep], companion.decel[keep]
        noise = cfc_filter(rng.normal(0.0, noise_g, time.size + 2 * PAD), float(time[1] - time[0]), NOISE_CFC)
        table = pd.DataFrame({"time_s": time, "decel_g": decel / G0 + noise[PAD:-PAD]})
        write_text(folder / "pulses" / f"{test}.csv", table.to_csv(index=False))
    if "cfc" in conditions:
        conditions.loc[conditions["source"].str.lower() == "test", "cfc"] = str(NOISE_CFC)
        write_text(folder / "conditions.csv", conditions.to_csv(index=False))
    return folder


def _check_test(folder: Path, conditions: pd.DataFrame, campaign, test: str) -> None:
    """A test a noise control can rewrite: a companion CAE run and its own CSV pulse in ``pulses/``."""
    if campaign.companion(test) is None:
        raise InputError(f"{folder / 'conditions.csv'}: test {test} has no companion CAE run (cae_run_id); "
                         "a noise control needs one per test", field="cae_run_id")
    path = folder / "pulses" / f"{test}.csv"
    row = conditions.loc[conditions["run_id"] == test]
    if not path.is_file() or ("pulse_path" in row and row["pulse_path"].iloc[0].strip()):
        raise InputError(f"{path}: expected the test's CSV pulse (a noise control rewrites it)", field="pulse_path")
