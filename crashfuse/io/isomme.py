"""Read crash tests in the ISO-MME format (ISO/TS 13499).

A test folder holds ``<test>.mme`` (test information), ``Channel/<test>.chn`` (channel list)
and ``Channel/<test>.NNN`` (one channel: header lines, then one sample per line). Header lines
are ``name padded to 28 characters:value``; ``NOVALUE`` marks an empty field and a name may
repeat (``Comments``). File names are matched case-insensitively and CR/LF or LF line ends are
both accepted.

A channel code has 16 characters: test object (1), position (1), main location (4), fine
locations 1, 2, 3 (2 each), physical dimension (2), direction (1), filter class (1); for
example ``10VEHCCG0000ACXP`` is the CG X acceleration of test object 1, unfiltered.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import os
from pathlib import Path

import numpy as np

from crashfuse.errors import InputError
from crashfuse.io.channels import combine_x_channels
from crashfuse.signals.pulse import Pulse
from crashfuse.units import G0

NOVALUE = "NOVALUE"
NAME_WIDTH = 28
# Filter class letter -> CFC (None = unfiltered: P prefilter only, 0 no filter).
FILTER_CLASS = {"P": None, "0": None, "A": 1000, "B": 600, "C": 180, "D": 60}
ACCEL_UNITS = {"g": G0, "m/s^2": 1.0, "m/s**2": 1.0, "m/s2": 1.0}
CG_PATTERN = "1?VEHCCG0000ACX?"


@dataclasses.dataclass(frozen=True)
class ChannelCode:
    """The parts of a 16-character ISO-MME channel code."""

    code: str
    test_object: str
    position: str
    main_location: str
    fine_location_1: str
    fine_location_2: str
    fine_location_3: str
    dimension: str
    direction: str
    filter_class: str

    @classmethod
    def parse(cls, code: str, file=None) -> "ChannelCode":
        """Split ``code``; InputError (naming ``file``) if it is not 16 characters."""
        code = code.strip()
        if len(code) != 16:
            raise InputError(f"expected a 16-character channel code, got {code!r}", file, "channel code")
        cuts = (0, 1, 2, 6, 8, 10, 12, 14, 15, 16)
        return cls(code, *(code[a:b] for a, b in zip(cuts, cuts[1:])))

    @property
    def cfc(self) -> int | None:
        """The CFC of the filter class (None: unfiltered)."""
        if self.filter_class not in FILTER_CLASS:
            raise InputError(f"unknown filter class {self.filter_class!r}, expected one of {list(FILTER_CLASS)}",
                             field=f"channel code {self.code}")
        return FILTER_CLASS[self.filter_class]


def parse_fields(lines: list[str], path: Path) -> dict[str, list[str | None]]:
    """``name:value`` header lines -> {name: [values]} (NOVALUE -> None, repeats kept in order).

    The standard puts the ':' in column 29; a line that does not is split at its first ':'.
    """
    fields: dict[str, list[str | None]] = {}
    for number, line in enumerate(lines, start=1):
        cut = NAME_WIDTH if line[NAME_WIDTH : NAME_WIDTH + 1] == ":" else line.find(":")
        if cut <= 0:
            raise InputError(f"line {number}: expected 'name:value', got {line!r}", path, "header")
        value = line[cut + 1 :].strip()
        fields.setdefault(line[:cut].strip(), []).append(None if value == NOVALUE else value)
    return fields


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="latin-1").splitlines()
    except OSError as err:
        raise InputError(f"cannot read: {err.strerror}", path, "file") from None


def _get(fields: dict, name: str, path: Path, kind=str, required: bool = True):
    value = (fields.get(name) or [None])[0]
    if value is None:
        if required:
            raise InputError("missing or NOVALUE", path, name)
        return None
    try:
        return kind(value)
    except ValueError:
        raise InputError(f"expected a number, got {value!r}", path, name) from None


def _find(folder: Path, name: str, what: str) -> Path:
    """The entry of ``folder`` called ``name``, ignoring case."""
    matches = [p for p in folder.iterdir() if p.name.lower() == name.lower()] if folder.is_dir() else []
    if not matches:
        raise InputError(f"missing {what} {name!r}", folder, what)
    return matches[0]


@dataclasses.dataclass(frozen=True)
class MMETest:
    """An ISO-MME test folder: test fields and the channel list.

    Attributes
    ----------
    folder, mme, channel_dir : Path
    fields : dict
        ``.mme`` fields, name -> list of values (None for NOVALUE).
    channels : dict
        Channel number -> (ChannelCode, description) from the ``.chn`` file.
    """

    folder: Path
    mme: Path
    channel_dir: Path
    fields: dict
    channels: dict

    def channel_file(self, number: int) -> Path:
        """Path of channel ``number`` (case-insensitive match; InputError if missing)."""
        return _find(self.channel_dir, f"{self.mme.stem}.{number:03d}", "channel file")

    def find(self, pattern: str) -> list[int]:
        """Channel numbers whose code matches a ``?`` wildcard pattern."""
        return [n for n, (code, _) in self.channels.items() if fnmatch.fnmatchcase(code.code, pattern)]


def read_test(folder: str | os.PathLike) -> MMETest:
    """Read ``<test>.mme`` and ``Channel/<test>.chn`` of an ISO-MME folder."""
    folder = Path(folder)
    mmes = [p for p in folder.iterdir() if p.suffix.lower() == ".mme"] if folder.is_dir() else []
    if len(mmes) != 1:
        raise InputError(f"expected one ISO-MME test file *.mme, found {len(mmes)}", folder, "mme")
    mme = mmes[0]
    channel_dir = _find(folder, "Channel", "channel folder")
    chn = _find(channel_dir, f"{mme.stem}.chn", "channel list")
    chn_fields = parse_fields(_read_lines(chn), chn)
    channels = {}
    for name in chn_fields:
        if name.lower().startswith("name of channel"):
            number = name.split()[-1]
            if not number.isdigit():
                raise InputError("expected 'Name of channel NNN'", chn, name)
            code, _, description = _get(chn_fields, name, chn).partition("/")
            try:
                channels[int(number)] = (ChannelCode.parse(code), description.strip())
            except InputError as err:
                raise InputError(err.message, chn, name) from None
    n = _get(chn_fields, "Number of channels", chn, int)
    if n != len(channels):
        raise InputError(f"lists {len(channels)} channels, expected {n}", chn, "Number of channels")
    return MMETest(folder, mme, channel_dir, parse_fields(_read_lines(mme), mme), channels)


def read_channel(test: MMETest, number: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """One channel: time in s, values in the channel's unit, and its header fields.

    The header is the leading block of ``name:value`` lines; the samples follow, one a line.
    """
    path = test.channel_file(number)
    lines = _read_lines(path)
    n_header = next((i for i, line in enumerate(lines) if ":" not in line), len(lines))
    fields = parse_fields(lines[:n_header], path)
    samples = [line for line in lines[n_header:] if line.strip()]
    bad = next((i for i, s in enumerate(samples) if not _is_finite(s)), None)
    if bad is not None:
        raise InputError(f"sample {bad + 1}: expected a finite number, got {samples[bad]!r}", path, "data")
    values = np.array(samples, dtype=float)
    n = _get(fields, "Number of samples", path, int)
    if values.size != n:
        raise InputError(f"found {values.size} samples, expected {n}", path, "Number of samples")
    dt = _get(fields, "Sampling interval", path, float)
    if not dt > 0:
        raise InputError(f"expected a positive interval in s, got {dt}", path, "Sampling interval")
    time = _get(fields, "Time of first sample", path, float) + dt * np.arange(n)
    return time, values, fields


def _is_finite(text: str) -> bool:
    try:
        return np.isfinite(float(text))
    except ValueError:
        return False


def default_channels(test: MMETest) -> list[int]:
    """Vehicle CG X acceleration if present, else the primary rear-seat crossmember X channels.

    Rear-seat crossmember: object 1, main location SEAT, fine location 2 ``RE`` (rear), AC, X.
    Their redundant twins carry ``RE`` in fine location 3 and ``L1``/``R1`` in fine location 2
    (e.g. ``10SEATLEL1REACXP``), so they do not match.
    """
    cg = test.find(CG_PATTERN)
    return cg[:1] if cg else test.find("1?SEAT??RE??ACX?")


def _accel_si(test: MMETest, number: int) -> tuple[np.ndarray, np.ndarray, int | None]:
    code = test.channels[number][0]
    path = test.channel_file(number)
    if code.dimension != "AC" or code.direction != "X":
        raise InputError(f"channel {number} ({code.code}) is not an X acceleration (AC, X)", path, "channel code")
    time, values, fields = read_channel(test, number)
    unit = _get(fields, "Unit", path)
    if unit not in ACCEL_UNITS:
        raise InputError(f"expected one of {list(ACCEL_UNITS)}, got {unit!r}", path, "Unit")
    try:
        return time, values * ACCEL_UNITS[unit], code.cfc
    except InputError as err:
        raise err.at(path) from None


def _weights(total: float, front_weight, rear_weight, mme: Path, warnings: list[str], meta: dict):
    if (front_weight is None) != (rear_weight is None):
        raise InputError("give both axle masses or neither", mme, "front_weight/rear_weight")
    if front_weight is not None:
        return float(front_weight), float(rear_weight)
    warnings.append(f"ISO-MME has no axle split: mass {total} kg split evenly (assumed)")
    meta["axle_split"] = "assumed"
    return total / 2, total / 2


def read_isomme(folder: str | os.PathLike, channels=None, front_weight=None, rear_weight=None) -> Pulse:
    """The vehicle crash pulse of an ISO-MME test.

    Parameters
    ----------
    folder : path
        ISO-MME test folder.
    channels : iterable of int, optional
        Channel numbers (as in the ``.chn`` list) of X accelerations to average. Default:
        see ``default_channels``.
    front_weight, rear_weight : float, optional
        Axle masses in kg. ISO-MME carries only the total mass: without them it is split
        evenly and ``meta['axle_split'] = 'assumed'``.

    Returns
    -------
    Pulse
        Mean deceleration in m/s^2 (each channel's pre-impact mean removed, pre-impact samples
        kept); ``v0`` from 'Velocity test object 1' (m/s); ``meta['cfc']`` from the filter
        class; ``meta`` also holds ``test_number``, ``vehicle``, ``channels`` (codes),
        ``offsets_mps2``, ``mass_kg``, ``files`` and ``warnings``.
    """
    test = read_test(folder)
    chosen = [int(c) for c in channels] if channels is not None else default_channels(test)
    if not chosen:
        raise InputError(f"no {CG_PATTERN} or rear-seat crossmember X channel; pass channels=", test.folder, "channels")
    for c in chosen:
        if c not in test.channels:
            raise InputError(f"channel {c} is not in the channel list", test.folder, f"channel {c}")
    data = [_accel_si(test, c) for c in chosen]
    cfcs = {cfc for _, _, cfc in data}
    if len(cfcs) > 1:
        raise InputError(f"channels {chosen} mix filter classes {sorted(cfcs, key=str)}", test.folder, "channel code")
    names = [test.channels[c][0].code for c in chosen]
    warnings: list[str] = []
    try:
        time, decel, offsets = combine_x_channels([(t, a) for t, a, _ in data], names, warnings)
    except InputError as err:
        raise err.at(test.folder) from None
    v0 = _get(test.fields, "Velocity test object 1", test.mme, float)
    mass = _get(test.fields, "Mass test object 1", test.mme, float, required=front_weight is None)
    meta = {"cfc": cfcs.pop(), "test_number": _get(test.fields, "Customer test ref. number", test.mme, required=False),
            "vehicle": {"title": _get(test.fields, "Name of test object 1", test.mme, required=False)},
            "channels": names, "offsets_mps2": offsets, "mass_kg": mass,
            "files": [str(test.mme)] + [str(test.channel_file(c)) for c in chosen], "warnings": warnings}
    front, rear = _weights(mass, front_weight, rear_weight, test.mme, warnings, meta)
    return Pulse(time, decel, v0, front, rear, run_id=test.mme.stem, source="test", meta=meta, where=str(test.mme))
