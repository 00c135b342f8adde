"""ISO/TS 18571 rating of pulse CSV files: a predicted pulse against a test pulse (``crashfuse iso-score``)."""

from __future__ import annotations

import os

import numpy as np

from crashfuse.errors import InputError
from crashfuse.io.pulse_csv import read_pulse_csv
from crashfuse.signals.iso18571 import rate, resample, window_grid
from crashfuse.units import MS


def score_files(test_csv: str | os.PathLike, prediction_csv: str | os.PathLike, start_ms: float = 0.0,
                end_ms: float = 60.0) -> dict[str, float]:
    """ISO/TS 18571 rating of a predicted pulse CSV against a test pulse CSV.

    Parameters
    ----------
    test_csv, prediction_csv : str or PathLike
        Pulse CSVs (``time_s`` and ``decel_g`` or ``decel_mps2``), read with
        :func:`crashfuse.io.pulse_csv.read_pulse_csv`; the test is the reference.
    start_ms, end_ms : float
        Rating window in ms; both ends are included.

    Returns
    -------
    dict
        Floats in [0, 1] under ``overall``, ``corridor``, ``phase``, ``magnitude``, ``slope``.

    Raises
    ------
    InputError
        Located at the file whose curve is at fault (e.g. a prediction that ends before the
        window does names the prediction file); a bad window names the field ``window``.
    """
    t_ref, ref = read_pulse_csv(test_csv)
    t_cmp, cmp = read_pulse_csv(prediction_csv)
    grid = window_grid(start_ms * MS, end_ms * MS)
    try:
        ref_w = resample(t_ref, ref, grid, "reference")
    except InputError as err:
        raise err.at(test_csv) from None
    try:
        cmp_w = resample(t_cmp, cmp, grid, "compared signal")
    except InputError as err:
        raise err.at(prediction_csv) from None
    try:
        scores = rate(ref_w, cmp_w[np.newaxis])  # both curves are valid here: only the reference can fail
    except InputError as err:
        raise err.at(test_csv) from None
    return {key: float(val[0]) for key, val in scores.items()}
