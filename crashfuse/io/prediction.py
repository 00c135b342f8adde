"""The prediction CSV a rollout writes (``<test>_prediction.csv``): reading it back, validated.

The columns are :meth:`crashfuse.method.rollout.Prediction.frame`'s, deceleration in g (positive
while slowing), time in s.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.io.tables import read_table

__all__ = ["PREDICTION_COLUMNS", "read_prediction_csv"]

PREDICTION_COLUMNS = ("time_s", "decel_g", "decel_lo_g", "decel_hi_g", "cae_decel_g")


def read_prediction_csv(path: str | os.PathLike) -> pd.DataFrame:
    """Read and validate a fold's prediction CSV.

    Parameters
    ----------
    path : str or PathLike
        CSV with at least ``time_s, decel_g, decel_lo_g, decel_hi_g, cae_decel_g`` (deceleration
        in g, positive while slowing); other columns are kept.

    Returns
    -------
    pandas.DataFrame, shape (n_samples, >= 5)
        The table, with the five columns as floats.

    Raises
    ------
    InputError
        Missing file or column, non-finite value, time not strictly increasing, or a band with
        ``decel_lo_g > decel_hi_g``.
    """
    path = Path(path)
    frame = read_table(path, PREDICTION_COLUMNS, "a prediction CSV")
    if len(frame) < 2:
        raise InputError(f"expected at least 2 samples, got {len(frame)}", path, "time_s")
    for col in PREDICTION_COLUMNS:
        values = pd.to_numeric(frame[col], errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise InputError(f"expected finite numbers, got {frame[col].iloc[bad[0]]!r} in data row {bad[0] + 1}",
                             path, col)
        frame[col] = values
    step = np.diff(frame["time_s"].to_numpy())
    if np.any(step <= 0):
        raise InputError(f"expected strictly increasing time, not at data row {int(np.argmin(step > 0)) + 2}",
                         path, "time_s")
    crossed = np.flatnonzero(frame["decel_lo_g"].to_numpy() > frame["decel_hi_g"].to_numpy())
    if crossed.size:
        raise InputError(f"expected decel_lo_g <= decel_hi_g, not at data row {crossed[0] + 1}", path, "decel_lo_g")
    return frame
