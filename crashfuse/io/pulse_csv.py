"""The single-pulse CSV format: ``time_s`` and ``decel_g`` or ``decel_mps2``, read and written.

A campaign's ``pulses/<run_id>.csv`` files and the CLI's prediction files use it. Reading
converts to SI (s, m/s^2); plain numeric files take a fast path (numpy or one pandas pass over
many files) that gives bit-identical numbers to the general reader.
"""

from __future__ import annotations

import codecs
import io
import os
import warnings
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

from crashfuse import units
from crashfuse.errors import InputError
from crashfuse.io.atomic import atomic_path
from crashfuse.io.tables import finite_numbers, read_raw_table, unit_column
from crashfuse.signals.pulse import check_samples

# 10 significant digits: round-trips to 5e-10 relative, and re-writing a read campaign gives the same bytes.
FLOAT_FORMAT = "%.10g"
_PLAIN_BYTES = b"0123456789+-.eE,\n"  # all a plain pulse CSV's data rows may hold


def read_pulse_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a single-pulse CSV (``time_s`` and ``decel_g`` or ``decel_mps2``).

    Other columns are ignored. Raises InputError naming the file and column for a missing
    column, a non-number or blank, fewer than 16 samples, non-increasing or non-uniform time,
    or a peak beyond 500 g (wrong units).

    Returns
    -------
    time_s : ndarray, shape (n,)
        Sample times in s.
    decel_mps2 : ndarray, shape (n,)
        Deceleration in m/s^2, positive while slowing.
    """
    path = Path(path)
    return checked_pulse(path, plain_pulse_csv(path))


def checked_pulse(path: Path, plain) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_pulse_csv` given the file's plain parse (None: pandas reads it, cell by cell)."""
    if plain is None:
        frame = read_raw_table(path, "pulse CSV")
        time_col = unit_column(frame.columns, "time", {"s": 1.0}, path)
        decel_col = unit_column(frame.columns, "decel", units.ACCEL, path)
        t = finite_numbers(frame[time_col], path, time_col)
        a = finite_numbers(frame[decel_col], path, decel_col)
    else:
        time_col, decel_col, t, a = plain
    a = a * units.ACCEL[decel_col.removeprefix("decel_")]
    check_samples(t, a, path, (time_col, decel_col))
    return t, a


def plain_pulse_csv(path: Path):
    """``(time_col, decel_col, t, decel)`` of a plain numeric pulse CSV, read by numpy, else None.

    A campaign's 1000-odd pulse files dominate reading it; numpy parses a plain file in about
    half the time pandas takes. Anything else (quotes, blanks, odd headers, non-finite values)
    returns None, so the pandas reader reports it cell by cell.
    """
    try:
        with open(path, encoding="utf-8-sig") as fh:
            header = [h.strip() for h in fh.readline().split(",")]
            if _pulse_columns(header) is None:
                return None
            with warnings.catch_warnings():  # a header without rows: numpy warns, the pandas reader names it
                warnings.simplefilter("ignore", UserWarning)
                data = np.loadtxt(fh, delimiter=",", ndmin=2, comments=None)  # ragged rows raise
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if data.shape[0] == 0 or data.shape[1] != len(header) or not np.isfinite(data).all():
        return None
    return _plain_columns(header, data)


def _pulse_columns(header: list[str]) -> str | None:
    """The decel column of a plain pulse CSV header (unique names, ``time_s``, one known ``decel_<unit>``), else None."""
    times, decels = ([c for c in header if c == name or c.startswith(name + "_")] for name in ("time", "decel"))
    if (len(set(header)) < len(header) or times != ["time_s"] or len(decels) != 1
            or decels[0].removeprefix("decel_") not in units.ACCEL):
        return None
    return decels[0]


def _plain_columns(header: list[str], data: np.ndarray) -> tuple:
    """``(time_col, decel_col, t, decel)`` from the parsed rows of a plain pulse CSV."""
    decel_col = _pulse_columns(header)
    return "time_s", decel_col, data[:, header.index("time_s")], data[:, header.index(decel_col)]


def plain_pulse_files(paths: Iterable[Path]) -> dict:
    """Plain pulse CSVs parsed together: ``{path: (time_col, decel_col, t, decel)}`` as :func:`plain_pulse_csv`.

    Parsing dominates reading a campaign. pandas' C reader (fast_float: correctly rounded, as numpy's
    reader is, so the numbers are the same) parses the rows of all files that share a header in one
    call, in a third of the time numpy takes file by file. Files whose rows hold anything else, and
    groups that do not parse cleanly, are left out: they are read and reported one by one.
    """
    groups = {}
    for path in paths:
        split = _plain_split(path)
        if split is not None:
            groups.setdefault(split[0], []).append((path, split[1]))
    parsed = {}
    for header, files in groups.items():
        parsed.update(_parse_together(list(header), files))
    return parsed


def _plain_split(path: Path):
    """``(header, rows)`` of a pulse CSV with a plain header and rows of plain bytes ending in a line feed, else None."""
    try:
        raw = path.read_bytes()
    except OSError:
        return None
    head, _, rows = raw.removeprefix(codecs.BOM_UTF8).partition(b"\n")
    if not rows or rows.translate(None, _PLAIN_BYTES):
        return None
    try:
        header = tuple(h.strip() for h in head.decode("utf-8").split(","))
    except UnicodeDecodeError:
        return None
    if _pulse_columns(list(header)) is None:
        return None
    return header, rows if rows.endswith(b"\n") else rows + b"\n"


def _parse_together(header: list[str], files: list[tuple[Path, bytes]]) -> dict:
    """The files' rows (same header) parsed in one pass and split back per file; empty if any row is not plain."""
    blob = b"".join(rows for _, rows in files)
    chars = np.frombuffer(blob, np.uint8)
    ends = np.flatnonzero(chars == ord("\n"))
    commas = np.bincount(np.searchsorted(ends, np.flatnonzero(chars == ord(","))), minlength=len(ends))
    if np.any(commas != len(header) - 1):  # a blank or ragged line: let the file-by-file readers say where
        return {}
    try:
        data = pd.read_csv(io.BytesIO(blob), header=None, dtype=np.float64, na_filter=False, engine="c").to_numpy()
    except (ValueError, pd.errors.ParserError):  # e.g. "1e" or an empty cell
        return {}
    if data.shape != (len(ends), len(header)) or not np.isfinite(data).all():
        return {}
    bounds = np.cumsum([0] + [rows.count(b"\n") for _, rows in files])
    return {path: _plain_columns(header, data[lo:hi]) for (path, _), lo, hi in zip(files, bounds[:-1], bounds[1:])}


def write_pulse_csv(path: str | os.PathLike, time_s: np.ndarray, decel_mps2: np.ndarray, unit: str = "g") -> None:
    """Write a single-pulse CSV atomically.

    Parameters
    ----------
    path : path-like
        Output file.
    time_s : ndarray, shape (n,)
        Sample times in s.
    decel_mps2 : ndarray, shape (n,)
        Deceleration in m/s^2, positive while slowing.
    unit : {"g", "mps2"}
        Unit of the written ``decel_<unit>`` column.
    """
    if unit not in units.ACCEL:
        raise InputError(f"expected an acceleration unit in {sorted(units.ACCEL)}, got {unit!r}", path, "unit")
    with atomic_path(path) as tmp:
        write_pulse_file(tmp, time_s, decel_mps2, unit)


def write_pulse_file(path: Path, time_s, decel_mps2, unit: str) -> None:
    """Write a pulse CSV in place, ``unit`` a key of ``units.ACCEL`` (not atomic: the campaign writer
    builds its whole folder aside)."""
    data = np.column_stack([np.asarray(time_s, float), np.asarray(decel_mps2, float) / units.ACCEL[unit]])
    np.savetxt(path, data, fmt=FLOAT_FORMAT, delimiter=",", header=f"time_s,decel_{unit}", comments="")

