"""Reading CSV tables with errors that name the file and the missing column."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd

from crashfuse.errors import InputError


def read_table(path: str | os.PathLike, columns, what: str, **read_csv) -> pd.DataFrame:
    """Read a CSV table that must hold ``columns``.

    Parameters
    ----------
    path : str or PathLike
        The CSV file.
    columns : sequence of str
        Columns that must be present (others are kept).
    what : str
        What the file should be, for messages (e.g. "an ISO score table").
    **read_csv
        Passed to :func:`pandas.read_csv`.

    Raises
    ------
    InputError
        Missing file, unreadable CSV, or a missing column (named as the field).
    """
    path = Path(path)
    try:
        frame = pd.read_csv(path, **read_csv)
    except FileNotFoundError:
        raise InputError(f"expected {what}, but the file does not exist", path) from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
        raise InputError(f"expected a CSV table: {err}", path) from None
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise InputError(f"expected the columns {list(columns)}, missing {missing}", path, missing[0])
    return frame
