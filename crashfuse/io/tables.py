"""Reading CSV tables with errors that name the file, the column and the bad cell."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
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


# --- cells of a CSV table, with errors that locate the bad cell ---------------------------------


def read_raw_table(path: Path, what: str, dtype=None) -> pd.DataFrame:
    """A CSV table as written: blank cells NaN (no other NA spellings), column names stripped.

    Parameters
    ----------
    path : Path
        The CSV file.
    what : str
        What the file is, for messages (e.g. "pulse CSV").
    dtype : optional
        Passed to :func:`pandas.read_csv` (``str`` keeps every cell as text).

    Raises
    ------
    InputError
        Missing, empty or unreadable file.
    """
    if not path.is_file():
        raise InputError(f"missing {what}: file does not exist", path)
    try:
        frame = pd.read_csv(path, dtype=dtype, keep_default_na=False, na_values=[""], encoding="utf-8-sig",
                            skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise InputError("empty file; expected a header row with column names", path) from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as err:
        raise InputError(f"not a readable CSV table: {' '.join(str(err).split())}", path) from None
    frame.columns = [str(c).strip() for c in frame.columns]
    return frame


def unit_column(columns, name: str, table: dict, path: Path) -> str:
    """The single column ``<name>_<unit>`` with a known unit."""
    expected = ", ".join(f"{name}_{u}" for u in table)
    found = [c for c in columns if c == name or c.startswith(name + "_")]
    if not found:
        raise InputError(f"missing required column; expected one of {expected}", path, name)
    if len(found) > 1:
        raise InputError(f"two unit variants of the same quantity ({', '.join(found)}); expected exactly one "
                         f"of {expected}", path, found[1])
    col = found[0]
    if col == name:
        raise InputError(f"the unit is missing from the column name; expected one of {expected}", path, col)
    if col.removeprefix(name + "_") not in table:
        raise InputError(f"unknown unit suffix {col.removeprefix(name + '_')!r}; expected one of {expected}",
                         path, col)
    return col


def row_label(i: int, run_ids=None) -> str:
    """How messages name data row ``i`` (0-based): ``data row 3, run_id 'T01'``."""
    rid = f", run_id {run_ids[i]!r}" if run_ids is not None and i < len(run_ids) and run_ids[i] else ""
    return f"data row {i + 1}{rid}"


def finite_numbers(col: pd.Series, path: Path, name: str, run_ids=None) -> np.ndarray:
    """A column as finite floats, or an InputError locating the first bad cell."""
    if pd.api.types.is_bool_dtype(col.dtype):
        values = np.full(len(col), np.nan)
    elif pd.api.types.is_numeric_dtype(col.dtype):
        values = col.to_numpy(dtype=float)
    else:
        values = pd.to_numeric(col, errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        i = int(bad[0])
        cell = col.iloc[i]
        got = "a blank cell" if is_blank(cell) else f"{cell!r}"
        raise InputError(f"expected a finite number, got {got} ({row_label(i, run_ids)})", path, name)
    return values


def is_blank(value: Any) -> bool:
    """Whether a cell is empty: None, NaN, pandas' NA or whitespace only."""
    return value is None or (isinstance(value, float) and math.isnan(value)) or (
        isinstance(value, str) and not value.strip()) or value is pd.NA



def read_json(path: Path, missing: str) -> Any:
    """The JSON document in ``path``; InputError naming the file when it is absent (``missing`` says what
    was expected) or not JSON."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(missing, path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"expected JSON: {err}", path) from None
