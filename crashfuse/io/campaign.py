"""The campaign folder: the contract between every part of crashfuse.

A campaign folder holds ``conditions.csv`` (one row per run, units in the column names) and
``pulses/<run_id>.csv`` (``time_s`` and ``decel_g`` or ``decel_mps2``); a row may instead point at
an NHTSA EV5 or ISO-MME test folder with ``pulse_path``. The full format is in
``docs/campaign-format.md``. Everything is converted to SI once, here.
"""

from __future__ import annotations

import codecs
import csv
import dataclasses
import hashlib
import io
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd

from crashfuse import units
from crashfuse.errors import InputError
from crashfuse.io.atomic import atomic_path, default_mode
from crashfuse.signals.pulse import MAX_SPEED, SOURCES, Pulse, check_samples

CONDITIONS = "conditions.csv"
PULSES = "pulses"
# Quantities whose unit is the column-name suffix: name -> (unit table, SI suffix).
QUANTITIES = {
    "v0": (units.SPEED, "mps"),
    "front_weight": (units.MASS, "kg"),
    "rear_weight": (units.MASS, "kg"),
}
# Plausible SI ranges (upper bound inclusive), as the Pulse type checks them.
RANGES = {"v0": (0.0, MAX_SPEED), "front_weight": (0.0, 1e5), "rear_weight": (0.0, 1e5)}
TEXT_REQUIRED = ("run_id", "source", "powertrain", "drive")
CANONICAL = ("run_id", "source", "v0_mps", "front_weight_kg", "rear_weight_kg", "powertrain", "drive")
OPTIONAL = ("cae_run_id", "pulse_path")
CFC_CLASSES = (60, 180, 600, 1000)
DEFAULT_CFC = 60
RAW = "raw"
# 10 significant digits: round-trips to 5e-10 relative, and re-writing a read campaign gives the same bytes.
FLOAT_FORMAT = "%.10g"
# Restitution cannot exceed 1, so the velocity change of a pulse is at most 2 v0; the slack
# absorbs noise of raw records. A decel_g column holding m/s^2 integrates to ~10 v0.
MAX_DELTA_V_RATIO = 2.2
_RUN_ID = re.compile(r"[^./\\\s\x00-\x1f](?:[^/\\\x00-\x1f]*[^/\\\s\x00-\x1f])?")


@dataclasses.dataclass(eq=False)
class Campaign:
    """Crash tests and CAE runs with their impact conditions, in SI.

    Parameters
    ----------
    conditions : pandas.DataFrame, shape (n_runs, n_columns)
        One row per run with the canonical columns ``run_id, source, v0_mps, front_weight_kg,
        rear_weight_kg, powertrain, drive``, optionally ``cae_run_id`` (a test's companion CAE run)
        and ``pulse_path`` (an EV5 or ISO-MME folder relative to ``root``), plus any extra column.
    pulses : dict of str to Pulse
        The pulse of every run, keyed by run_id, in SI (from first contact on as `read_campaign`
        leaves filtered pulses).
    root : Path or None
        The folder the campaign was read from (resolves ``pulse_path``); None if built in memory.
    """

    conditions: pd.DataFrame
    pulses: dict[str, Pulse]
    root: Path | None = None

    def __post_init__(self):
        # The same rules as the reader, so that whatever is in memory can be written and read back.
        missing = [c for c in CANONICAL if c not in self.conditions.columns]
        if missing:
            raise InputError(f"expected the canonical columns {CANONICAL}, missing {missing}", self.root, "conditions")
        cols = [*TEXT_REQUIRED, *[c for c in OPTIONAL if c in self.conditions.columns]]
        _check_table({c: [None if _blank(v) else v for v in self.conditions[c]] for c in cols}, self.root)
        if set(self.conditions["run_id"]) != set(self.pulses):
            raise InputError("expected exactly one pulse per run_id", self.root, "run_id")

    @classmethod
    def from_pulses(cls, pulses: Iterable[Pulse], columns: Iterable[str] = ()) -> "Campaign":
        """Build a campaign in memory from pulses (e.g. to write a synthetic campaign).

        Parameters
        ----------
        pulses : iterable of Pulse
            The runs, in the order the conditions table should list them. Their ``meta`` supplies
            ``powertrain`` and ``drive`` (required), ``cae_run_id`` and ``pulse_path`` (optional)
            and ``cfc``, the filter class the decel carries (absent or None: raw, as in
            ``crashfuse.signals.filters``; set 60 for processed pulses).
        columns : iterable of str
            Further ``meta`` keys to keep as extra columns.
        """
        pulses = list(pulses)
        extra = [c for c in columns if c not in (*CANONICAL, *OPTIONAL, "cfc")]
        opt = [c for c in OPTIONAL if any(p.meta.get(c) is not None for p in pulses)]
        rows = []
        for p in pulses:
            row = dict(run_id=p.run_id, source=p.source, v0_mps=p.v0, front_weight_kg=p.front_weight,
                       rear_weight_kg=p.rear_weight)
            for c in ("powertrain", "drive", *opt, *extra):
                row[c] = p.meta.get(c)
            rows.append(row)
        frame = pd.DataFrame(rows, columns=[*CANONICAL, *opt, *extra])
        return cls(frame, {p.run_id: p for p in pulses})

    @property
    def tests(self) -> list[str]:
        """run_ids of the physical tests, in table order."""
        return self._ids("test")

    @property
    def cae(self) -> list[str]:
        """run_ids of the CAE runs, in table order."""
        return self._ids("cae")

    def _ids(self, source: str) -> list[str]:
        return self.conditions.loc[self.conditions["source"] == source, "run_id"].tolist()

    def companion(self, test_id: str) -> Pulse | None:
        """The CAE run named by a test's ``cae_run_id``, or None if the test names none."""
        row = self.conditions.loc[self.conditions["run_id"] == test_id]
        if row.empty:
            raise KeyError(f"no run {test_id!r} in this campaign")
        cae_id = row["cae_run_id"].iloc[0] if "cae_run_id" in row else None
        return None if _blank(cae_id) else self.pulses[cae_id]

    def subset(self, run_ids: Iterable[str]) -> "Campaign":
        """The campaign restricted to ``run_ids`` (kept in table order).

        A test kept without the CAE run its ``cae_run_id`` names is an InputError: include both.
        """
        wanted = set(run_ids)
        unknown = wanted - set(self.pulses)
        if unknown:
            raise KeyError(f"runs not in this campaign: {sorted(unknown)}")
        frame = self.conditions[self.conditions["run_id"].isin(wanted)].reset_index(drop=True)
        return Campaign(frame, {r: self.pulses[r] for r in frame["run_id"]}, self.root)

    def content_hash(self) -> str:
        """SHA-256 (hex) of the conditions and pulse data in SI, independent of row order.

        Reading the same folder twice gives the same hash; changing any value, unit-independent
        of how it was written, changes it.
        """
        h = hashlib.sha256()
        frame = self.conditions.sort_values("run_id", kind="stable")
        frame = frame[sorted(frame.columns)].drop(columns="pulse_path", errors="ignore")
        h.update(frame.to_csv(index=False, float_format="%.17g", lineterminator="\n").encode())
        for run_id in sorted(self.pulses):
            p = self.pulses[run_id]
            h.update(f"\0{run_id}\0{p.meta.get('cfc')}\0".encode())
            h.update(np.ascontiguousarray(p.time, "<f8").tobytes())
            h.update(np.ascontiguousarray(p.decel, "<f8").tobytes())
        return h.hexdigest()


# --- single pulse CSV ------------------------------------------------------------------------


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
    return _checked_pulse(path, _plain_pulse_csv(path))


def _checked_pulse(path: Path, plain) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_pulse_csv` given the file's plain parse (None: pandas reads it, cell by cell)."""
    if plain is None:
        frame = _read_csv(path, "pulse CSV")
        time_col = _unit_column(frame.columns, "time", {"s": 1.0}, path)
        decel_col = _unit_column(frame.columns, "decel", units.ACCEL, path)
        t = _numbers(frame[time_col], path, time_col)
        a = _numbers(frame[decel_col], path, decel_col)
    else:
        time_col, decel_col, t, a = plain
    a = a * units.ACCEL[decel_col.removeprefix("decel_")]
    check_samples(t, a, path, (time_col, decel_col))
    return t, a


def _plain_pulse_csv(path: Path):
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


_PLAIN_BYTES = b"0123456789+-.eE,\n"  # all a plain pulse CSV's data rows may hold


def _plain_pulse_files(paths: Iterable[Path]) -> dict:
    """Plain pulse CSVs parsed together: ``{path: (time_col, decel_col, t, decel)}`` as :func:`_plain_pulse_csv`.

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
        _write_pulse(tmp, time_s, decel_mps2, unit)


def _write_pulse(path: Path, time_s, decel_mps2, unit: str) -> None:
    data = np.column_stack([np.asarray(time_s, float), np.asarray(decel_mps2, float) / units.ACCEL[unit]])
    np.savetxt(path, data, fmt=FLOAT_FORMAT, delimiter=",", header=f"time_s,decel_{unit}", comments="")


# --- reading a campaign ----------------------------------------------------------------------


def read_campaign(folder: str | os.PathLike, cfc: int | None = DEFAULT_CFC) -> Campaign:
    """Read and validate a campaign folder.

    Parameters
    ----------
    folder : path-like
        Folder with ``conditions.csv`` and ``pulses/``.
    cfc : int or None
        SAE J211 channel frequency class applied to raw pulses (EV5, unfiltered ISO-MME, CSV rows
        with ``cfc = raw``) before cropping at first contact; None keeps every pulse as read,
        pre-impact samples included. Processed pulses are never filtered again.

    Returns
    -------
    Campaign
        Conditions in SI with canonical column names and one Pulse per run (from first contact on
        unless ``cfc`` is None).

    Raises
    ------
    InputError
        Naming the file, the field and what was expected, for any problem in the folder.
    """
    root = Path(folder)
    if not root.is_dir():
        what = "is not a folder" if root.exists() else "does not exist"
        raise InputError(f"campaign folder {what}; expected a folder with {CONDITIONS} and {PULSES}/", root)
    path = root / CONDITIONS
    if not path.is_file():
        raise InputError(f"missing {CONDITIONS}; expected a campaign folder with {CONDITIONS} and {PULSES}/", root)
    frame, cfcs = _parse_conditions(path)
    rows = frame.to_dict("records")
    plain = _plain_pulse_files(_pulse_file(root, row) for row in rows if _blank(row.get("pulse_path")))
    pulses = {}
    for row, row_cfc in zip(rows, cfcs):
        pulses[row["run_id"]] = _load_run(root, path, row, row_cfc, cfc, plain)
    return Campaign(frame, pulses, root)


def _pulse_file(root: Path, row: dict) -> Path:
    """Where a conditions row without ``pulse_path`` keeps its pulse: ``pulses/<run_id>.csv``."""
    return root / PULSES / f"{row['run_id']}.csv"


def _parse_conditions(path: Path) -> tuple[pd.DataFrame, list]:
    """conditions.csv as a canonical SI frame plus the per-row declared CFC (None = raw)."""
    _check_header(path)
    raw = _read_csv(path, CONDITIONS, dtype=str)
    if raw.empty:
        raise InputError("expected at least one run (row), found none", path)
    out = {col: _text(raw, col, path, required=True) for col in TEXT_REQUIRED}
    out["source"] = [s and s.lower() for s in out["source"]]
    for col in OPTIONAL:
        if col in raw.columns:
            out[col] = _text(raw, col, path, required=False)
    _check_table(out, path)
    used = set(TEXT_REQUIRED)
    for name, (table, si) in QUANTITIES.items():
        col = _unit_column(raw.columns, name, table, path)
        factor = table[col.removeprefix(name + "_")]
        out[f"{name}_{si}"] = values = _numbers(raw[col], path, col, out["run_id"]) * factor
        low, high = RANGES[name]
        bad = np.flatnonzero((values <= low) | (values > high))
        if bad.size:
            i = int(bad[0])
            raise InputError(f"expected a value in ({low / factor:.6g}, {high / factor:.6g}], got "
                             f"{values[i] / factor:.6g} ({_row(i, out['run_id'])})", path, col)
        used.add(col)
    used.update(OPTIONAL, ["cfc"])
    cfcs = _parse_cfc(raw, path, out)
    frame = pd.DataFrame({c: out[c] for c in (*CANONICAL, *[c for c in OPTIONAL if c in out])})
    for col in raw.columns:
        if col not in used:
            frame[col] = _infer(raw[col])
    return frame, cfcs


def _check_header(path: Path) -> None:
    """Reject an empty file or repeated column names (pandas would silently rename them)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            header = [h.strip() for h in next(csv.reader(fh), [])]
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise InputError(f"cannot read the file: {err}", path) from None
    if not any(header):
        raise InputError("empty file; expected a header row with column names", path)
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise InputError(f"duplicate column(s) {dup}; expected each column once", path, dup[0])


def _read_csv(path: Path, what: str, dtype=None) -> pd.DataFrame:
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


def _unit_column(columns, name: str, table: dict, path: Path) -> str:
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


def _row(i: int, run_ids=None) -> str:
    rid = f", run_id {run_ids[i]!r}" if run_ids is not None and i < len(run_ids) and run_ids[i] else ""
    return f"data row {i + 1}{rid}"


def _numbers(col: pd.Series, path: Path, name: str, run_ids=None) -> np.ndarray:
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
        got = "a blank cell" if _blank(cell) else f"{cell!r}"
        raise InputError(f"expected a finite number, got {got} ({_row(i, run_ids)})", path, name)
    return values


def _blank(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value)) or (
        isinstance(value, str) and not value.strip()) or value is pd.NA


def _text(raw: pd.DataFrame, col: str, path: Path, required: bool) -> list:
    """A text column, stripped, with None for blank cells."""
    if col not in raw.columns:
        if required:
            raise InputError("missing required column", path, col)
        return [None] * len(raw)
    return [None if _blank(v) else str(v).strip() for v in raw[col]]


def _check_table(cols: dict[str, list], path: Path | None) -> None:
    """Rules on the text columns (lists with None for blanks): filled, unique run_ids, sources, companions."""
    ids = cols["run_id"]
    for col in TEXT_REQUIRED:
        for i, v in enumerate(cols[col]):
            if v is None:
                raise InputError(f"expected a value, got a blank cell ({_row(i, ids)})", path, col)
    _check_run_ids(ids, path)
    for i, s in enumerate(cols["source"]):
        if s not in SOURCES:
            raise InputError(f"expected one of {SOURCES}, got {s!r} ({_row(i, ids)})", path, "source")
    _check_companions(cols, path)


def _check_run_ids(ids: list[str], path: Path) -> None:
    seen = {}
    for i, rid in enumerate(ids):
        if not _RUN_ID.fullmatch(rid):
            raise InputError(f"expected a run_id usable as a file name (no '/', '\\', control characters or "
                             f"leading '.'), got {rid!r} ({_row(i)})", path, "run_id")
        # Pulse file names must not collide on case-insensitive file systems either.
        if rid.lower() in seen:
            raise InputError(f"duplicate run_id {rid!r} (data rows {seen[rid.lower()] + 1} and {i + 1}); expected "
                             "unique run_ids (case-insensitively)", path, "run_id")
        seen[rid.lower()] = i


def _parse_cfc(raw: pd.DataFrame, path: Path, out: dict) -> list:
    """Declared CFC per row: the class, or None for raw CSV pulses and pulse_path rows (their reader says)."""
    paths = out.get("pulse_path", [None] * len(raw))
    if "cfc" not in raw.columns:
        return [DEFAULT_CFC if p is None else None for p in paths]
    cfcs = []
    for i, (value, p) in enumerate(zip(raw["cfc"], paths)):
        if p is not None:
            if not _blank(value):
                raise InputError(f"expected a blank cfc for a pulse_path row (the source declares its own "
                                 f"filtering), got {value!r} ({_row(i, out['run_id'])})", path, "cfc")
            cfcs.append(None)
        elif _blank(value):
            cfcs.append(DEFAULT_CFC)
        elif str(value).strip().lower() == RAW:
            cfcs.append(None)
        else:
            try:
                cls = int(float(value))
            except ValueError:
                cls = None
            if cls not in CFC_CLASSES:
                raise InputError(f"expected one of {CFC_CLASSES} or {RAW!r}, got {value!r} "
                                 f"({_row(i, out['run_id'])})", path, "cfc")
            cfcs.append(cls)
    return cfcs


def _check_companions(out: dict, path: Path) -> None:
    if "cae_run_id" not in out:
        return
    source = dict(zip(out["run_id"], out["source"]))
    for i, (rid, cae_id) in enumerate(zip(out["run_id"], out["cae_run_id"])):
        if cae_id is None:
            continue
        if source[rid] != "test":
            raise InputError(f"expected cae_run_id only on test rows, got {cae_id!r} on CAE run "
                             f"({_row(i, out['run_id'])})", path, "cae_run_id")
        if source.get(cae_id) != "cae":
            what = "no run" if cae_id not in source else "a test, not a CAE run"
            raise InputError(f"expected the run_id of a CAE run in this campaign, but {cae_id!r} is {what} "
                             f"({_row(i, out['run_id'])})", path, "cae_run_id")


def _infer(col: pd.Series) -> pd.Series:
    """An extra column as numbers when every filled cell is one, else as text."""
    numeric = pd.to_numeric(col, errors="coerce")
    if numeric.notna().sum() == col.notna().sum():
        return numeric
    return col


def _meta(row: dict) -> dict:
    skip = {"run_id", "source", "v0_mps", "front_weight_kg", "rear_weight_kg"}
    return {k: (None if _blank(v) else (v.item() if isinstance(v, np.generic) else v))
            for k, v in row.items() if k not in skip}


def _load_run(root: Path, conditions: Path, row: dict, row_cfc, cfc, plain: dict) -> Pulse:
    """The pulse of one conditions row, in SI, as `prepare_pulse` leaves it (``plain``: files already parsed)."""
    meta = _meta(row)
    fields = dict(v0=row["v0_mps"], front_weight=row["front_weight_kg"], rear_weight=row["rear_weight_kg"],
                  run_id=row["run_id"], source=row["source"])
    if meta.get("pulse_path") is None:
        path = _pulse_file(root, row)
        if not path.is_file():
            raise InputError(f"missing pulse file for run {row['run_id']!r}; expected {PULSES}/{row['run_id']}.csv "
                             f"with columns time_s and decel_g (or decel_mps2), or a pulse_path", path)
        t, a = _checked_pulse(path, plain[path] if path in plain else _plain_pulse_csv(path))
        pulse = Pulse(t, a, meta={**meta, "cfc": row_cfc}, where=os.fspath(path), **fields)
    else:
        pulse = _foreign_run(root / meta["pulse_path"], conditions, fields, meta)
    return prepare_pulse(pulse, cfc)


def _foreign_run(folder: Path, conditions: Path, fields: dict, meta: dict) -> Pulse:
    """A pulse_path row: the raw test read from its folder, the row's conditions winning."""
    if not folder.is_dir():
        raise InputError(f"expected pulse_path to name an NHTSA EV5 or ISO-MME test folder relative to the "
                         f"campaign, but {os.fspath(folder)!r} is not a folder (run {fields['run_id']!r})",
                         conditions, "pulse_path")
    raw = read_test_folder(folder, fields["front_weight"], fields["rear_weight"])
    if raw is None:
        raise InputError(f"expected a folder holding *.EV5 (NHTSA) or *.mme (ISO-MME), found neither in "
                         f"{os.fspath(folder)!r} (run {fields['run_id']!r})", conditions, "pulse_path")
    warnings = [f"{name}: {conditions.name} gives {fields[name]:.6g}, {os.fspath(folder)} gives "
                f"{getattr(raw, name):.6g} (SI); using {conditions.name}"
                for name in ("v0", "front_weight", "rear_weight")
                if abs(getattr(raw, name) - fields[name]) > 0.01 * abs(fields[name])]
    merged = {**raw.meta, **meta}
    if warnings:
        merged["warnings"] = [*raw.meta.get("warnings", []), *warnings]
    return raw.replace(meta=merged, **fields)


def read_test_folder(folder: Path, front_weight: float | None = None, rear_weight: float | None = None) -> Pulse | None:
    """The raw pulse of an NHTSA EV5 (``*.EV5``) or ISO-MME (``*.mme``) folder; None if neither.

    Parameters
    ----------
    folder : Path
        The test folder.
    front_weight, rear_weight : float, optional
        Axle masses in kg, passed to the ISO-MME reader (its files carry only the total mass).
    """
    if _has(folder, ".ev5"):
        from crashfuse.io.nhtsa import read_nhtsa

        return read_nhtsa(folder)
    if _has(folder, ".mme"):
        from crashfuse.io.isomme import read_isomme

        return read_isomme(folder, front_weight=front_weight, rear_weight=rear_weight)
    return None


def _has(folder: Path, suffix: str) -> bool:
    return any(p.suffix.lower() == suffix for p in folder.iterdir() if p.is_file())


def prepare_pulse(pulse: Pulse, cfc: int | None) -> Pulse:
    """Filter a raw pulse and crop it at first contact if ``cfc`` is given; check it is physically plausible.

    With ``cfc`` None the record is returned whole, pre-impact samples included, because whoever
    filters it later (e.g. `crashfuse.signals.metrics.pulse_metrics`) needs them as lead-in.
    """
    if cfc is not None:
        from crashfuse.signals.filters import filter_pulse  # filters only raw or lighter-class pulses

        pulse = filter_pulse(pulse, cfc).after_contact()
    if pulse.time[0] > 0.5 * pulse.dt:
        raise InputError(f"expected t = 0 at first contact, but the pulse starts at {pulse.time[0] * 1e3:.6g} ms",
                         pulse.where, "time_s")
    _check_delta_v(pulse)
    return pulse


def _check_delta_v(pulse: Pulse) -> None:
    """Velocity change must be positive and at most ~2 v0: catches flipped signs and wrong units."""
    dv = float(np.trapezoid(pulse.decel, pulse.time))
    if dv <= 0:
        raise InputError(f"expected deceleration positive while slowing, but the pulse integrates to a velocity "
                         f"change of {dv:.3g} m/s: sign flipped?", pulse.where, "decel")
    if dv > MAX_DELTA_V_RATIO * pulse.v0:
        raise InputError(f"the pulse integrates to a velocity change of {dv:.3g} m/s, more than "
                         f"{MAX_DELTA_V_RATIO} x the impact speed {pulse.v0:.3g} m/s: wrong units (m/s^2 in a "
                         f"_g column?) or wrong speed?", pulse.where, "decel")


# --- writing a campaign ----------------------------------------------------------------------


def write_campaign(campaign: Campaign, folder: str | os.PathLike, speed_unit: str = "mph", mass_unit: str = "lb",
                   accel_unit: str = "g", overwrite: bool = False,
                   extra_files: Mapping[str, str | bytes] | None = None) -> Path:
    """Write a campaign folder atomically, with deterministic bytes.

    Parameters
    ----------
    campaign : Campaign
        What to write. Rows with ``pulse_path`` keep it (re-based so it still names the same folder).
    folder : path-like
        Output folder; must not exist or be empty unless ``overwrite``.
    speed_unit : {"mph", "kmh", "mps"}
    mass_unit : {"lb", "kg"}
    accel_unit : {"g", "mps2"}
        Units of the written columns.
    overwrite : bool
        Replace a non-empty existing folder.
    extra_files : mapping of str to str or bytes, optional
        Further files beside ``conditions.csv`` (plain file names, e.g. ``world.json``; text is
        written as UTF-8). They are written with the campaign, so the folder appears with all of
        them or not at all.

    Returns
    -------
    Path
        The written folder.
    """
    folder = Path(folder)
    for name, table, unit in (("speed_unit", units.SPEED, speed_unit), ("mass_unit", units.MASS, mass_unit),
                              ("accel_unit", units.ACCEL, accel_unit)):
        if unit not in table:
            raise InputError(f"expected one of {sorted(table)}, got {unit!r}", field=name)
    extra_files = dict(extra_files or {})
    _check_extra(extra_files)
    if folder.exists() and not folder.is_dir():
        raise InputError("expected a folder, found a file", folder)
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise InputError("expected an empty or new output folder; this one is not empty and is left as it is", folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".part", dir=folder.parent))
    try:
        _write_into(campaign, tmp, folder, speed_unit, mass_unit, accel_unit)
        for name, content in extra_files.items():
            (tmp / name).write_bytes(content.encode() if isinstance(content, str) else content)
        tmp.chmod(default_mode(directory=True))  # mkdtemp makes 0700; the folder gets the usual permissions
        _swap_in(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def _check_extra(extra_files: dict) -> None:
    """Extra files are plain names that cannot clash with the campaign's own files, holding text or bytes."""
    for name, content in extra_files.items():
        if (not isinstance(name, str) or name in ("", ".", "..", CONDITIONS, PULSES) or Path(name).name != name
                or "\\" in name):
            raise InputError(f"expected a plain file name other than {CONDITIONS} and {PULSES}, got {name!r}",
                             field="extra_files")
        if not isinstance(content, (str, bytes)):
            raise InputError(f"expected str or bytes content, got {type(content).__name__}",
                             field=f"extra_files[{name!r}]")


def _write_into(campaign: Campaign, tmp: Path, final: Path, speed_unit, mass_unit, accel_unit) -> None:
    frame = _conditions_out(campaign, final, speed_unit, mass_unit)
    (tmp / CONDITIONS).write_bytes(frame.to_csv(index=False, float_format=FLOAT_FORMAT,
                                                lineterminator="\n").encode())
    (tmp / PULSES).mkdir()
    paths = campaign.conditions["pulse_path"] if "pulse_path" in campaign.conditions else [None] * len(frame)
    for run_id, p in zip(campaign.conditions["run_id"], paths):
        if _blank(p):
            pulse = campaign.pulses[run_id]
            _write_pulse(tmp / PULSES / f"{run_id}.csv", pulse.time, pulse.decel, accel_unit)


def _conditions_out(campaign: Campaign, final: Path, speed_unit, mass_unit) -> pd.DataFrame:
    src = campaign.conditions
    out = pd.DataFrame({"run_id": src["run_id"], "source": src["source"]})
    for name, (table, si), unit in zip(QUANTITIES, QUANTITIES.values(), (speed_unit, mass_unit, mass_unit)):
        out[f"{name}_{unit}"] = src[f"{name}_{si}"].to_numpy(float) / table[unit]
    out["powertrain"], out["drive"] = src["powertrain"], src["drive"]
    if "cae_run_id" in src:
        out["cae_run_id"] = src["cae_run_id"]
    if "pulse_path" in src:
        out["pulse_path"] = [None if _blank(p) else _rebase(p, campaign.root, final) for p in src["pulse_path"]]
    paths = out["pulse_path"] if "pulse_path" in out else [None] * len(src)
    cells = [_cfc_cell(campaign.pulses[r], p) for r, p in zip(src["run_id"], paths)]
    # The column is only needed when some CSV pulse is not the default CFC 60.
    if any(c not in (None, DEFAULT_CFC) for c in cells):
        out["cfc"] = cells
    for col in src.columns:
        if col not in (*CANONICAL, *OPTIONAL, "cfc"):
            out[col] = src[col]
    return out


def _cfc_cell(pulse: Pulse, pulse_path) -> str | int | None:
    """What the cfc column says of a row: blank for pulse_path rows, 'raw' or the CFC class."""
    if pulse_path is not None:
        return None
    cls = pulse.meta.get("cfc")  # absent means raw, as in crashfuse.signals.filters
    return RAW if cls is None else int(cls)


def _rebase(pulse_path: str, root: Path | None, final: Path) -> str:
    """pulse_path re-based from ``root`` to ``final`` so that it names the same folder."""
    if root is None or Path(pulse_path).is_absolute():
        return pulse_path
    target = os.path.abspath(root / pulse_path)  # abspath, not resolve: keep the user's symlinks
    return Path(os.path.relpath(target, os.path.abspath(final))).as_posix()


def _swap_in(tmp: Path, folder: Path) -> None:
    """Rename the finished temp folder onto ``folder``; an old folder is removed only afterwards."""
    if not folder.exists():
        os.rename(tmp, folder)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".old", dir=folder.parent))
    os.rename(folder, old / "x")
    try:
        os.rename(tmp, folder)
    except OSError:
        os.rename(old / "x", folder)
        raise
    finally:
        shutil.rmtree(old, ignore_errors=True)
