"""The noise control: a campaign whose CAE model is exact, so its tests differ from their CAE runs by
measurement noise alone.

Issue 16's control: a bias correction must not lose a test the CAE already predicts. The worlds'
``none`` campaigns withhold no effect but keep a measurement chain (resonance, sensor, filter) the CAE
runs lack, so the CAE there is good, not right. Here each test's pulse is replaced by its companion CAE
run as the campaign reader sees it (cropped at contact, at CFC 60; over the test's record length) plus
white noise at the record's sampling rate filtered at CFC 60 over a longer record (as a test's pre- and
post-trigger data: no transients at the ends), scaled to :data:`NOISE_G` g rms after the filter: what
NHTSA 10146's accelerometers read before contact. It works on campaign files only (read, then written by
the campaign writer), so any campaign, not only a synthetic one, can be turned into its control.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import numpy as np

from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign, read_campaign
from crashfuse.io.campaign_write import write_campaign
from crashfuse.signals.filters import cfc_filter, filtered_noise
from crashfuse.units import G0

# g rms after CFC 60: one of NHTSA 10146's rear-floor X accelerometers (channels 93 and 94: 0.040 and 0.047 g;
# their average, the reader's pulse, 0.038 g) over the 45 ms before contact (tests/test_nhtsa.py). Until
# decisions.md section 84 it was 0.258 g.
NOISE_G = 0.044
NOISE_CFC = 60
KEPT_FILES = ("world.json",)  # a generated campaign's answer key travels with it


def noise_control(campaign: Campaign, seed: int, noise_g: float = NOISE_G) -> Campaign:
    """The campaign with every test replaced by its companion CAE run plus filtered noise.

    Parameters
    ----------
    campaign : Campaign
        Every test needs a companion CAE run (``cae_run_id``).
    seed : int
        Seeds the noise.
    noise_g : float
        Rms of the noise in g after the CFC 60 filter (of a long record; a test's own record varies about it).

    Returns
    -------
    Campaign
        The same runs and conditions; the tests' pulses new (at CFC 60, no ``pulse_path``).

    Raises
    ------
    InputError
        A test without a companion CAE run; ``noise_g`` not a finite number >= 0.
    """
    _check_level(noise_g)
    rng = np.random.default_rng(seed)
    pulses = dict(campaign.pulses)
    for test in campaign.tests:
        own, companion = campaign.pulses[test], campaign.companion(test)
        if companion is None:
            raise InputError(f"test {test} has no companion CAE run (cae_run_id); a noise control needs one per test",
                             field="cae_run_id")
        keep = companion.time <= own.time[-1] + 1e-9  # the test's own record length
        time = companion.time[keep]
        dt = float(time[1] - time[0])
        noise = filtered_noise(rng, time.size, dt, NOISE_CFC, noise_g / _filter_gain(dt))
        pulses[test] = dataclasses.replace(own, time=time, decel=companion.decel[keep] + G0 * noise,
                                           meta={**own.meta, "cfc": NOISE_CFC})
    conditions = campaign.conditions.copy()
    if "pulse_path" in conditions:
        conditions.loc[conditions["source"] == "test", "pulse_path"] = None
    return Campaign(conditions, pulses, root=campaign.root)


def make_noise_control(source: str | os.PathLike, out: str | os.PathLike, seed: int, noise_g: float = NOISE_G,
                       overwrite: bool = False) -> Path:
    """Write the noise control of the campaign folder ``source`` into ``out`` (atomically; ``out`` may be
    ``source`` with ``overwrite``); a ``world.json`` beside it is kept. See :func:`noise_control`."""
    _check_level(noise_g)
    source = Path(source)
    campaign = read_campaign(source)
    try:
        control = noise_control(campaign, seed, noise_g)
    except InputError as err:
        raise InputError(err.message, source / "conditions.csv", field=err.field) from None
    kept = {name: (source / name).read_bytes() for name in KEPT_FILES if (source / name).is_file()}
    return write_campaign(control, out, overwrite=overwrite, extra_files=kept)


def _check_level(noise_g) -> None:
    if not np.isfinite(noise_g) or noise_g < 0:
        raise InputError(f"expected a noise level in g rms (a finite number >= 0), got {noise_g!r}", field="noise_g")


@functools.lru_cache(maxsize=8)
def _filter_gain(dt: float) -> float:
    """The rms of unit white noise at ``dt`` s after the CFC 60 filter: the root sum of squares of its
    impulse response (once per sampling step: a campaign's tests share one)."""
    impulse = np.zeros(8001)
    impulse[4000] = 1.0
    return float(np.sqrt(np.sum(cfc_filter(impulse, dt, NOISE_CFC) ** 2)))
