"""Read NHTSA crash tests in the EV5 ASCII format (Test Reference Guide, version 5).

A test folder holds ``<name>.EV5``, the header, and ``<name>.NNN``, one file per channel NNN
with two tab-separated columns: time in s and value in the channel's units.

The header is a sequence of sections opened by ``----- NAME -----`` lines; each row is one
record with ``|``-separated fields in the order of the NHTSA Test Reference Guide (the field
names below are NHTSA's). The fields this reader relies on (0-based positions):

- TEST: 1 TITLE, 3 TSTDAT, 7 TSTTYP, 8 TSTCNF, 14 CLSSPD (closing speed, km/h).
- VEHICLE: 0 VEHNO, 1 MAKE (code), 2 MODEL (code), 3 YEAR, 6 VIN, 10 VEHTWT (test weight,
  kg), 11 CURBWT (kg), 12 WHLBAS (wheelbase, mm), 15 VEHCG (centre of gravity behind the
  front axle, mm).
- INSTRUMENTATION (20 fields): 0 VEHNO (0 = barrier), 1 CURNO (channel), 2 SENTYP (AC
  accelerometer, LC load cell ...), 3 SENLOC (occupant location or NA), 4 SENATT (attachment,
  e.g. FLLR / FLRR left / right rear floor), 5 AXIS (XG / XL: X global / local), 6 XUNITS,
  7 YUNITS (G'S, NWT ...), 8 PREFIL (Hz), 9 INSMAN, 10 CALDAT, 11 INSRAT, 12 CHLMAX,
  13 INIVEL, 14 NFP (first sample index), 15 NLP (last sample index), 16 DELT (time step,
  us), 17 DASTAT (data status: AM valid; NO and CF flag missing or failed data in 10146),
  18 CHSTAT (P primary, R redundant), 19 INSCOM (description).

Axes follow SAE J211: X positive forward, so a frontal crash pulse reads negative.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.io.channels import combine_x_channels
from crashfuse.signals.pulse import Pulse
from crashfuse.units import G0, KMH, MM

TEST_FIELDS = {"title": 1, "date": 3, "test_type": 7, "configuration": 8, "impact_speed_kmh": 14}
VEHICLE_FIELDS = {
    "vehicle_number": 0, "make_code": 1, "model_code": 2, "year": 3, "vin": 6,
    "test_weight_kg": 10, "curb_weight_kg": 11, "wheelbase_mm": 12, "cg_behind_front_axle_mm": 15,
}
INSTRUMENTATION_COLUMNS = [
    "object", "channel", "sensor_type", "location", "attachment", "axis", "time_units", "units",
    "prefilter_hz", "transducer", "calibration_date", "range", "channel_max", "initial_velocity_kmh",
    "first_index", "last_index", "time_step_us", "status", "primary_redundant", "description",
]
INT_COLUMNS = ("object", "channel", "first_index", "last_index", "time_step_us")
VALID_STATUS = "AM"
ACCEL_UNITS = {"G'S": G0}
# Rear-floor attachments: the rear-seat crossmember accelerometers, the usual vehicle pulse.
PULSE_ATTACHMENTS = ("FLLR", "FLRR")
VEHICLE = 1
BARRIER = 0
_SECTION = re.compile(r"^-----\s*(\w+)\s*-----")
_TEST_NUMBER = re.compile(r"Test Number:\s*(\d+)")


@dataclasses.dataclass(frozen=True)
class EV5Header:
    """The header of an NHTSA EV5 test.

    Attributes
    ----------
    path : Path
        The ``.EV5`` file.
    test : dict
        ``number`` (str), ``title``, ``date``, ``test_type``, ``configuration`` (str) and
        ``impact_speed_kmh`` (float, km/h).
    vehicle : dict
        The test vehicle (VEHNO 1): ``make_code``, ``model_code``, ``vin`` (str), ``year``
        (int), ``test_weight_kg``, ``curb_weight_kg`` (kg), ``wheelbase_mm`` and
        ``cg_behind_front_axle_mm`` (mm), all floats unless noted.
    instrumentation : DataFrame, shape (n_channels, 20)
        One row per channel, columns ``INSTRUMENTATION_COLUMNS``; ``object``, ``channel``,
        ``first_index``, ``last_index`` and ``time_step_us`` are integers, the rest strings.
    """

    path: Path
    test: dict
    vehicle: dict
    instrumentation: pd.DataFrame

    def channel_file(self, channel: int) -> Path:
        """Path of the data file of ``channel`` (it may not exist)."""
        return self.path.with_suffix(f".{channel:03d}")

    def row(self, channel: int) -> pd.Series:
        """The INSTRUMENTATION row of ``channel``; InputError if the header has none."""
        rows = self.instrumentation[self.instrumentation["channel"] == channel]
        if rows.empty:
            raise InputError(f"channel {channel} is not in the INSTRUMENTATION section", self.path, "CURNO")
        return rows.iloc[0]


# --- header -----------------------------------------------------------------------------


def _ev5_file(folder: str | os.PathLike) -> Path:
    path = Path(folder)
    if path.is_file():
        return path
    found = sorted(p for p in path.glob("*") if p.suffix.lower() == ".ev5") if path.is_dir() else []
    if len(found) != 1:
        raise InputError(f"expected one NHTSA header file *.EV5, found {len(found)}", path, "EV5")
    return found[0]


def _sections(path: Path) -> tuple[dict[str, list[list[str]]], str]:
    """Rows of each section, split at ``|``, and the comment lines before the first section."""
    try:
        text = path.read_text(encoding="latin-1")
    except OSError as err:
        raise InputError(f"cannot read the header: {err.strerror}", path, "EV5") from None
    sections: dict[str, list[list[str]]] = {}
    current, comments = None, []
    for line in text.splitlines():
        match = _SECTION.match(line)
        if match:
            current = sections.setdefault(match.group(1).upper(), [])
        elif current is not None and line.strip():
            current.append([f.strip() for f in line.split("|")])
        elif current is None:
            comments.append(line)
    return sections, "\n".join(comments)


def _section(sections: dict, name: str, path: Path) -> list[list[str]]:
    rows = sections.get(name)
    if not rows:
        raise InputError(f"missing or empty ----- {name} ----- section", path, name)
    return rows


def _number(value: str, path: Path, field: str, kind=float):
    try:
        return kind(value)
    except ValueError:
        raise InputError(f"expected a number, got {value!r}", path, field) from None


def _pick(row: list[str], fields: dict[str, int], section: str, path: Path) -> dict[str, str]:
    need = max(fields.values()) + 1
    if len(row) < need:
        raise InputError(f"row has {len(row)} fields, expected at least {need}", path, section)
    return {name: row[i] for name, i in fields.items()}


def _test(sections: dict, comments: str, path: Path) -> dict:
    test = _pick(_section(sections, "TEST", path)[0], TEST_FIELDS, "TEST", path)
    test["impact_speed_kmh"] = _number(test["impact_speed_kmh"], path, "TEST CLSSPD")
    match = _TEST_NUMBER.search(comments)
    test["number"] = match.group(1) if match else path.stem.lstrip("vV")
    return test


def _vehicle(sections: dict, path: Path) -> dict:
    rows = [r for r in _section(sections, "VEHICLE", path) if r[0] == str(VEHICLE)]
    if not rows:
        raise InputError(f"no row for the test vehicle (VEHNO {VEHICLE})", path, "VEHICLE VEHNO")
    vehicle = _pick(rows[0], VEHICLE_FIELDS, "VEHICLE", path)
    vehicle["year"] = _number(vehicle["year"], path, "VEHICLE YEAR", int)
    names = {"test_weight_kg": "VEHTWT", "curb_weight_kg": "CURBWT", "wheelbase_mm": "WHLBAS",
             "cg_behind_front_axle_mm": "VEHCG"}
    for key, field in names.items():
        vehicle[key] = _number(vehicle[key], path, f"VEHICLE {field}")
    return vehicle


def _instrumentation(sections: dict, path: Path) -> pd.DataFrame:
    rows = _section(sections, "INSTRUMENTATION", path)
    width = len(INSTRUMENTATION_COLUMNS)
    for i, row in enumerate(rows):
        if len(row) < width:
            raise InputError(f"row {i + 1} has {len(row)} fields, expected {width}", path, "INSTRUMENTATION")
    # A description containing '|' spills into extra fields: join them back.
    table = pd.DataFrame([r[: width - 1] + ["|".join(r[width - 1 :])] for r in rows], columns=INSTRUMENTATION_COLUMNS)
    for col in INT_COLUMNS:
        values = pd.to_numeric(table[col], errors="coerce")
        bad = values.isna() | (values != values.round())
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"row {i + 1}: expected an integer, got {table[col][i]!r}", path, f"INSTRUMENTATION {col}")
        table[col] = values.astype(int)
    return table


def read_header(folder: str | os.PathLike) -> EV5Header:
    """Read the ``.EV5`` header of an NHTSA test folder.

    Parameters
    ----------
    folder : path
        The test folder (holding exactly one ``*.EV5`` file) or the ``.EV5`` file itself.

    Returns
    -------
    EV5Header

    Raises
    ------
    InputError
        Missing file or section, short rows or non-numeric fields, naming file and field.
    """
    path = _ev5_file(folder)
    sections, comments = _sections(path)
    return EV5Header(path, _test(sections, comments, path), _vehicle(sections, path), _instrumentation(sections, path))


# --- channels ---------------------------------------------------------------------------


def _diagnose_columns(path: Path) -> InputError:
    """The first line of a channel file that is not two tab-separated numbers."""
    for number, line in enumerate(path.read_text(encoding="latin-1").splitlines(), start=1):
        parts = line.split("\t")
        if len(parts) != 2:
            return InputError(f"line {number}: expected 2 tab-separated columns (time s, value), got {len(parts)}",
                              path, "columns")
        for name, part in zip(("time", "value"), parts):
            try:
                finite = np.isfinite(float(part))
            except ValueError:
                finite = False
            if not finite:
                return InputError(f"line {number}: expected a finite number, got {part!r}", path, name)
    return InputError("expected two tab-separated columns of numbers, found no data", path, "columns")


def read_channel_file(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read one EV5 channel file.

    Parameters
    ----------
    path : path
        Two tab-separated columns, time in s and value, no header.

    Returns
    -------
    time, value : ndarray, shape (n,)
        As written in the file (units of the channel).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("channel file is missing", path, "channel")
    try:
        data = pd.read_csv(path, sep="\t", header=None, dtype=float, engine="c").to_numpy()
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
        raise _diagnose_columns(path) from None
    if data.ndim != 2 or data.shape[1] != 2 or not np.isfinite(data).all():
        raise _diagnose_columns(path)
    return data[:, 0], data[:, 1]


def _check_time(time: np.ndarray, row: pd.Series, path: Path) -> None:
    """The file's time column must be the header's grid NFP*DELT + i*DELT (to a quarter step)."""
    dt = row["time_step_us"] * 1e-6
    grid = (row["first_index"] + np.arange(time.size)) * dt
    off = np.abs(time - grid) > 0.25 * dt
    if off.any():
        i = int(np.flatnonzero(off)[0])
        raise InputError(f"expected uniform time steps of {row['time_step_us']} us from sample index "
                         f"{row['first_index']} (header), but line {i + 1} has t={time[i]} s", path, "time")


def channel_problem(header: EV5Header, channel: int) -> str | None:
    """Why ``channel`` cannot be used (missing file, flagged data status), or None."""
    row = header.row(channel)
    if row["status"] != VALID_STATUS:
        return f"channel {channel} is flagged {row['status']!r} (not {VALID_STATUS!r}): {row['description']}"
    if not header.channel_file(channel).is_file():
        return f"channel {channel} has no data file"
    return None


def read_channel(header: EV5Header, channel: int) -> tuple[np.ndarray, np.ndarray]:
    """One channel on its header time grid, cut at its last valid sample index (NLP).

    Returns
    -------
    time : ndarray, shape (n,)
        s, ``(NFP + i) * DELT``.
    value : ndarray, shape (n,)
        In the channel's units (YUNITS).
    """
    row, path = header.row(channel), header.channel_file(channel)
    time, value = read_channel_file(path)
    _check_time(time, row, path)
    n_valid = row["last_index"] - row["first_index"] + 1
    if time.size < n_valid:
        raise InputError(f"expected {n_valid} samples (index {row['first_index']} to {row['last_index']}), "
                         f"got {time.size}", path, "samples")
    time = (row["first_index"] + np.arange(n_valid)) * (row["time_step_us"] * 1e-6)
    return time, value[:n_valid]


# --- vehicle pulse ----------------------------------------------------------------------


def default_channels(header: EV5Header) -> list[int]:
    """Primary X accelerometers of the test vehicle on the rear floor (rear-seat crossmember)."""
    t = header.instrumentation
    pick = ((t["object"] == VEHICLE) & (t["sensor_type"] == "AC") & t["attachment"].isin(PULSE_ATTACHMENTS)
            & t["axis"].str.startswith("X") & (t["primary_redundant"] == "P"))
    return [int(c) for c in t.loc[pick, "channel"]]


def _select(header: EV5Header, channels, warnings: list[str]) -> list[int]:
    if channels is not None:
        chosen = [int(c) for c in channels]
        for c in chosen:
            problem = channel_problem(header, c)
            if problem:
                raise InputError(problem, header.channel_file(c), f"channel {c}")
        return chosen
    chosen = []
    for c in default_channels(header):
        problem = channel_problem(header, c)
        if problem:
            warnings.append(f"skipped {problem}")
        else:
            chosen.append(c)
    if not chosen:
        raise InputError(f"no usable primary X accelerometer at attachments {PULSE_ATTACHMENTS} of vehicle "
                         f"{VEHICLE}; pass channels=", header.path, "INSTRUMENTATION")
    return chosen


def _accel_si(header: EV5Header, channel: int) -> tuple[np.ndarray, np.ndarray]:
    row = header.row(channel)
    if row["sensor_type"] != "AC" or not row["axis"].startswith("X"):
        raise InputError(f"channel {channel} is {row['sensor_type']} on axis {row['axis']}, expected an X "
                         "accelerometer (AC, XG/XL)", header.path, f"channel {channel}")
    if row["units"] not in ACCEL_UNITS:
        raise InputError(f"channel {channel} has units {row['units']!r}, expected one of {list(ACCEL_UNITS)}",
                         header.path, "YUNITS")
    time, value = read_channel(header, channel)
    return time, value * ACCEL_UNITS[row["units"]]


def _axle_masses(header: EV5Header) -> tuple[float, float]:
    v = header.vehicle
    mass, wheelbase, cg = v["test_weight_kg"], v["wheelbase_mm"] * MM, v["cg_behind_front_axle_mm"] * MM
    if not 0 < cg < wheelbase:
        raise InputError(f"expected the CG between the axles (0 < VEHCG < WHLBAS = {v['wheelbase_mm']} mm), "
                         f"got {v['cg_behind_front_axle_mm']} mm", header.path, "VEHICLE VEHCG")
    return mass * (1 - cg / wheelbase), mass * cg / wheelbase


def read_nhtsa(folder: str | os.PathLike, channels=None) -> Pulse:
    """The raw vehicle crash pulse of an NHTSA EV5 test.

    Parameters
    ----------
    folder : path
        NHTSA EV5 test folder (``<name>.EV5`` and ``<name>.NNN`` channel files).
    channels : iterable of int, optional
        X accelerometer channel numbers to average. Default: the primary (CHSTAT P) X
        accelerometers of the vehicle at the rear-floor attachments FLLR / FLRR (the rear-seat
        crossmember), skipping flagged or missing ones with a warning.

    Returns
    -------
    Pulse
        Unfiltered (``meta['cfc'] = None``) mean deceleration in m/s^2, pre-impact samples
        kept, each channel's pre-impact mean removed; ``v0`` from CLSSPD; axle masses from
        the test weight split at the CG. ``meta`` holds ``test_number``, ``vehicle``,
        ``channels``, ``offsets_mps2``, ``files``, ``warnings``.

    Raises
    ------
    InputError
        Bad header or channel file, or a requested channel that is missing or flagged.
    """
    header = read_header(folder)
    warnings: list[str] = []
    chosen = _select(header, channels, warnings)
    data = [_accel_si(header, c) for c in chosen]
    record_end = header.instrumentation["last_index"].max()
    for c in chosen:
        row = header.row(c)
        if row["last_index"] < record_end:
            warnings.append(f"channel {c} valid only to {row['last_index'] * row['time_step_us'] * 1e-6:.6g} s "
                            f"(NLP {row['last_index']} < {record_end}): cut there")
    try:
        time, decel, offsets = combine_x_channels(data, [str(c) for c in chosen], warnings)
    except InputError as err:
        raise err.at(header.path) from None
    front, rear = _axle_masses(header)
    v = header.vehicle
    meta = {
        "cfc": None,
        "test_number": header.test["number"],
        "vehicle": {"title": header.test["title"], "year": v["year"], "make_code": v["make_code"],
                    "model_code": v["model_code"], "vin": v["vin"]},
        "channels": chosen,
        "offsets_mps2": offsets,
        "files": [str(header.path)] + [str(header.channel_file(c)) for c in chosen],
        "warnings": warnings,
    }
    return Pulse(time, decel, header.test["impact_speed_kmh"] * KMH, front, rear, run_id=f"v{header.test['number']}",
                 source="test", meta=meta, where=str(header.path))


# --- barrier ----------------------------------------------------------------------------


def barrier_channels(header: EV5Header) -> tuple[list[int], list[str]]:
    """The barrier load-cell X force channels (object 0, LC, axis X, newtons).

    Returns
    -------
    usable : list of int
        Cells with valid data and a data file.
    skipped : list of str
        Why each other cell was left out (in 10146 the lab flags cells 347 and 500 'CF', no
        valid data; their share of the force is unknown, so the sum is a lower bound there).
    """
    t = header.instrumentation
    pick = (t["object"] == BARRIER) & (t["sensor_type"] == "LC") & t["axis"].str.startswith("X") & (t["units"] == "NWT")
    usable, skipped = [], []
    for c in t.loc[pick, "channel"]:
        problem = channel_problem(header, int(c))
        (skipped if problem else usable).append(problem or int(c))
    return usable, skipped


def read_barrier_force(folder: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Total barrier force on the vehicle: the sum of the usable load-cell Fx channels.

    Cells the lab flags as invalid or without a file are left out (see ``barrier_channels``).

    Returns
    -------
    time : ndarray, shape (n,)
        s, the span common to all cells.
    force : ndarray, shape (n,)
        N, each cell's pre-impact mean removed; positive while the barrier pushes the vehicle
        back (the cells read compression as negative X force, so the sum is negated).
    """
    header = read_header(folder)
    cells, _ = barrier_channels(header)
    if not cells:
        raise InputError("no usable barrier load-cell Fx channels (object 0, LC, X, NWT)", header.path,
                         "INSTRUMENTATION")
    try:
        # combine_x_channels returns -mean of the offset-removed cells.
        data = [read_channel(header, c) for c in cells]
        time, minus_mean, _ = combine_x_channels(data, [str(c) for c in cells], [])
    except InputError as err:
        raise err.at(header.path) from None
    return time, minus_mean * len(cells)
