"""One entry point for "give me the pulses at this path", whatever format the folder holds."""

from __future__ import annotations

import os
from pathlib import Path

from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign, read_test_folder
from crashfuse.io.checks import prepare_pulse
from crashfuse.io.conditions import CONDITIONS, DEFAULT_CFC
from crashfuse.signals.pulse import Pulse

EXPECTED = (f"expected a campaign folder ({CONDITIONS} + pulses/), an NHTSA EV5 test folder (*.EV5) "
            "or an ISO-MME test folder (*.mme)")


def load_pulses(path: str | os.PathLike, cfc: int | None = DEFAULT_CFC) -> list[Pulse]:
    """The pulses of a campaign, NHTSA EV5 or ISO-MME folder, in SI.

    Parameters
    ----------
    path : path-like
        The folder, or a file in it (``conditions.csv``, ``*.EV5``, ``*.mme``).
    cfc : int or None
        SAE J211 channel frequency class applied to raw pulses, which are then cropped at first
        contact; None keeps every record whole, pre-impact samples included (what
        `crashfuse.signals.metrics.pulse_metrics` needs, as it filters before cropping).

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
    if path.is_file() and path.name != CONDITIONS and path.suffix.lower() not in (".ev5", ".mme"):
        raise InputError(f"is a file; {EXPECTED}", path)
    if (folder / CONDITIONS).is_file():
        return list(read_campaign(folder, cfc).pulses.values())
    pulse = read_test_folder(folder)
    if pulse is None:
        raise InputError(f"holds none of the known formats; {EXPECTED}", folder)
    return [prepare_pulse(pulse, cfc)]
