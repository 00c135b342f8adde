"""One entry point for "give me the pulses at this path", whatever format the folder holds."""

from __future__ import annotations

import os
from pathlib import Path

from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign, read_test_folder
from crashfuse.io.checks import prepare_pulse
from crashfuse.io.conditions import CONDITIONS, DEFAULT_CFC
from crashfuse.io.lsdyna import SOURCE_FIELD, UNITS_FIELD, is_binout, read_binout
from crashfuse.signals.pulse import Pulse

EXPECTED = (f"expected a campaign folder ({CONDITIONS} + pulses/), an NHTSA EV5 test folder (*.EV5), "
            "an ISO-MME test folder (*.mme) or an LS-DYNA binout")


def load_pulses(path: str | os.PathLike, cfc: int | None = DEFAULT_CFC, lsdyna: dict | None = None) -> list[Pulse]:
    """The pulses of a campaign, NHTSA EV5 or ISO-MME folder or LS-DYNA binout, in SI.

    Parameters
    ----------
    path : path-like
        The folder, or a file in it (``conditions.csv``, ``*.EV5``, ``*.mme``).
    cfc : int or None
        SAE J211 channel frequency class applied to raw pulses, which are then cropped at first
        contact; None keeps every record whole, pre-impact samples included (what
        `crashfuse.signals.metrics.pulse_metrics` needs, as it filters before cropping).
    lsdyna : dict, optional
        For a binout: ``lsdyna_source``, ``lsdyna_units`` and ``mass_kg`` (the run's mass, split
        evenly over the axles as ISO-MME's total mass is), as `crashfuse.io.lsdyna.read_binout` takes them.

    Returns
    -------
    list of Pulse
        One per run, in the campaign's table order (one for a single test folder).

    Raises
    ------
    InputError
        If the path is missing, holds none of the three formats, or its content is bad.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"does not exist; {EXPECTED}", path)
    folder = path if path.is_dir() else path.parent
    if is_binout(path) and not (path / CONDITIONS).is_file():
        return [prepare_pulse(_binout(path, lsdyna or {}), cfc)]
    if path.is_file() and path.name != CONDITIONS and path.suffix.lower() not in (".ev5", ".mme"):
        raise InputError(f"is a file; {EXPECTED}", path)
    if (folder / CONDITIONS).is_file():
        return list(read_campaign(folder, cfc).pulses.values())
    pulse = read_test_folder(folder)
    if pulse is None:
        raise InputError(f"holds none of the known formats; {EXPECTED}", folder)
    return [prepare_pulse(pulse, cfc)]


def _binout(path: Path, lsdyna: dict) -> Pulse:
    for key in (SOURCE_FIELD, UNITS_FIELD, "mass_kg"):
        if lsdyna.get(key) is None:
            raise InputError(f"an LS-DYNA binout is read with its source, unit system and the run's mass: give "
                             f"--{key.replace('_', '-')}", path, key)
    half = 0.5 * float(lsdyna["mass_kg"])
    pulse = read_binout(path, lsdyna[SOURCE_FIELD], lsdyna[UNITS_FIELD], half, half, run_id=path.name)
    return pulse.replace(meta={**pulse.meta, "axle_split": "assumed"})
