"""The conditions table of a campaign (``conditions.csv``): its columns, units, parsing and rules.

One row per run; units are in the column names (``v0_mph``, ``front_weight_lb``, ...) and are
converted to SI here. The full format is in ``docs/campaign-format.md``.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pandas as pd

from crashfuse import units
from crashfuse.errors import InputError
from crashfuse.io.tables import finite_numbers, is_blank, read_raw_table, row_label, unit_column
from crashfuse.signals.pulse import MAX_SPEED, SOURCES

CONDITIONS = "conditions.csv"
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
LSDYNA = ("lsdyna_source", "lsdyna_units")  # what a binout pulse_path row reads, and the model's units
OPTIONAL = ("cae_run_id", "pulse_path", *LSDYNA)
CFC_CLASSES = (60, 180, 600, 1000)
DEFAULT_CFC = 60
RAW = "raw"
_RUN_ID = re.compile(r"[^./\\\s\x00-\x1f](?:[^/\\\x00-\x1f]*[^/\\\s\x00-\x1f])?")


def parse_conditions(path: Path) -> tuple[pd.DataFrame, list]:
    """conditions.csv as a canonical SI frame plus the per-row declared CFC (None = raw)."""
    _check_header(path)
    raw = read_raw_table(path, CONDITIONS, dtype=str)
    if raw.empty:
        raise InputError("expected at least one run (row), found none", path)
    out = {col: _text(raw, col, path, required=True) for col in TEXT_REQUIRED}
    out["source"] = [s and s.lower() for s in out["source"]]
    for col in OPTIONAL:
        if col in raw.columns:
            out[col] = _text(raw, col, path, required=False)
    check_table(out, path)
    used = set(TEXT_REQUIRED)
    for name, (table, si) in QUANTITIES.items():
        col = unit_column(raw.columns, name, table, path)
        factor = table[col.removeprefix(name + "_")]
        out[f"{name}_{si}"] = values = finite_numbers(raw[col], path, col, out["run_id"]) * factor
        low, high = RANGES[name]
        bad = np.flatnonzero((values <= low) | (values > high))
        if bad.size:
            i = int(bad[0])
            raise InputError(f"expected a value in ({low / factor:.6g}, {high / factor:.6g}], got "
                             f"{values[i] / factor:.6g} ({row_label(i, out['run_id'])})", path, col)
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


def _text(raw: pd.DataFrame, col: str, path: Path, required: bool) -> list:
    """A text column, stripped, with None for blank cells."""
    if col not in raw.columns:
        if required:
            raise InputError("missing required column", path, col)
        return [None] * len(raw)
    return [None if is_blank(v) else str(v).strip() for v in raw[col]]


def check_table(cols: dict[str, list], path: Path | None) -> None:
    """Rules on the text columns (lists with None for blanks): filled, unique run_ids, sources, companions."""
    ids = cols["run_id"]
    for col in TEXT_REQUIRED:
        for i, v in enumerate(cols[col]):
            if v is None:
                raise InputError(f"expected a value, got a blank cell ({row_label(i, ids)})", path, col)
    _check_run_ids(ids, path)
    for i, s in enumerate(cols["source"]):
        if s not in SOURCES:
            raise InputError(f"expected one of {SOURCES}, got {s!r} ({row_label(i, ids)})", path, "source")
    _check_companions(cols, path)
    _check_lsdyna(cols, path)


def _check_lsdyna(cols: dict, path: Path) -> None:
    """The LS-DYNA columns belong to pulse_path rows (which of those are binouts, the reader sees)."""
    paths = cols.get("pulse_path", [None] * len(cols["run_id"]))
    for col in LSDYNA:
        for i, (value, where) in enumerate(zip(cols.get(col, ()), paths)):
            if value is not None and where is None:
                raise InputError(f"expected {col} only on rows whose pulse_path names an LS-DYNA binout, got "
                                 f"{value!r} on a row without pulse_path ({row_label(i, cols['run_id'])})", path, col)


def _check_run_ids(ids: list[str], path: Path) -> None:
    seen = {}
    for i, rid in enumerate(ids):
        if not _RUN_ID.fullmatch(rid):
            raise InputError(f"expected a run_id usable as a file name (no '/', '\\', control characters or "
                             f"leading '.'), got {rid!r} ({row_label(i)})", path, "run_id")
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
            if not is_blank(value):
                raise InputError(f"expected a blank cfc for a pulse_path row (the source declares its own "
                                 f"filtering), got {value!r} ({row_label(i, out['run_id'])})", path, "cfc")
            cfcs.append(None)
        elif is_blank(value):
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
                                 f"({row_label(i, out['run_id'])})", path, "cfc")
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
                             f"({row_label(i, out['run_id'])})", path, "cae_run_id")
        if source.get(cae_id) != "cae":
            what = "no run" if cae_id not in source else "a test, not a CAE run"
            raise InputError(f"expected the run_id of a CAE run in this campaign, but {cae_id!r} is {what} "
                             f"({row_label(i, out['run_id'])})", path, "cae_run_id")


def _infer(col: pd.Series) -> pd.Series:
    """An extra column as numbers when every filled cell is one, else as text."""
    numeric = pd.to_numeric(col, errors="coerce")
    if numeric.notna().sum() == col.notna().sum():
        return numeric
    return col

