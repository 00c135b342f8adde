"""Test-only writers of small synthetic NHTSA EV5 and ISO-MME test folders.

Each writer takes a plain spec (drawn by the hypothesis strategies below), writes the folder
and returns what it wrote, so a test can check that a reader recovers it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

G0 = 9.80665  # standard gravity, written here independently of crashfuse.units


def _pulse(time: np.ndarray, peak: float, length: float, offset: float, seed: int) -> np.ndarray:
    """A half-sine X acceleration (negative while slowing) plus offset and noise."""
    rng = np.random.default_rng(seed)
    a = np.where((time >= 0) & (time <= length), -peak * np.sin(np.pi * np.clip(time, 0, length) / length), 0.0)
    return a + offset + rng.normal(0, 0.05 * peak, time.size)


def _as_written(values: np.ndarray) -> np.ndarray:
    """Values as a reader sees them after ``%.6f`` formatting."""
    return np.array([float(f"{v:.6f}") for v in values])


# --- EV5 --------------------------------------------------------------------------------


@dataclasses.dataclass
class EV5Spec:
    test_number: int
    speed_kmh: float
    weight_kg: int
    wheelbase_mm: int
    cg_mm: int
    delt_us: int
    nfp: int
    n: int
    n_pulse: int  # primary rear-floor X channels (1 or 2)
    missing_default: bool  # add a primary rear-floor X channel flagged NO, without a file
    short_channel: bool  # cut the last pulse channel's NLP (and file) short
    crlf: bool
    seed: int


@st.composite
def ev5_specs(draw) -> EV5Spec:
    """Random but valid EV5 tests."""
    n = draw(st.integers(60, 400))
    return EV5Spec(
        test_number=draw(st.integers(1, 99999)),
        speed_kmh=draw(st.integers(1000, 9000)) / 100,
        weight_kg=draw(st.integers(800, 3000)),
        wheelbase_mm=(wb := draw(st.integers(2000, 3500))),
        cg_mm=draw(st.integers(int(0.3 * wb), int(0.6 * wb))),
        delt_us=draw(st.sampled_from([50, 80, 100, 125, 200])),
        nfp=-draw(st.integers(5, 50)),
        n=n,
        n_pulse=draw(st.integers(1, 2)),
        missing_default=draw(st.booleans()),
        short_channel=draw(st.booleans()),
        crlf=draw(st.booleans()),
        seed=draw(st.integers(0, 2**31)),
    )


@dataclasses.dataclass
class EV5Written:
    folder: Path
    header: Path
    pulse_channels: list[int]
    skipped: list[int]
    barrier_channels: list[int]
    data: dict  # channel -> (time s, value as written)


def _ev5_row(vehno, curno, sentyp, senatt, axis, units, nfp, nlp, delt, dastat, chstat, text) -> str:
    return "|".join(map(str, [vehno, curno, sentyp, "NA", senatt, axis, "SEC", units, 2800, "MFG: X", "01/JAN/2020",
                              100, 1, 0.0, nfp, nlp, delt, dastat, chstat, text]))


def write_ev5(folder: Path, spec: EV5Spec) -> EV5Written:
    """Write ``v<test>.EV5`` and its channel files into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"v{spec.test_number}"
    dt = spec.delt_us * 1e-6
    nlp = spec.nfp + spec.n - 1
    time = (spec.nfp + np.arange(spec.n)) * dt
    length = 0.4 * time[-1]
    # Channel plan: (curno, sentyp, senatt, axis, units, chstat, object, nlp, dastat)
    plan = [(1, "AC", "HDCG", "XL", "G'S", "P", 1, nlp, "AM")]  # occupant head, never a pulse channel
    pulse = [3 + i for i in range(spec.n_pulse)]
    plan += [(c, "AC", ("FLLR", "FLRR")[i], "XG", "G'S", "P", 1, nlp, "AM") for i, c in enumerate(pulse)]
    plan += [(7, "AC", "FLLR", "XG", "G'S", "R", 1, nlp, "AM"), (8, "AC", "FLLR", "ZG", "G'S", "P", 1, nlp, "AM")]
    skipped = [9] if spec.missing_default else []
    plan += [(9, "AC", "FLRR", "XG", "G'S", "P", 1, nlp, "NO")] if spec.missing_default else []
    barrier = [20, 22, 24]
    plan += [(c, "LC", "LC0101", "XG", "NWT", "P", 0, nlp, "AM") for c in barrier]
    plan += [(21, "LC", "LC0101", "YG", "NWM", "P", 0, nlp, "AM")]
    if spec.short_channel:
        c = pulse[-1]
        plan = [p[:7] + (nlp - spec.n // 4,) + p[8:] if p[0] == c else p for p in plan]
    rows, data = [], {}
    for k, (curno, sentyp, senatt, axis, units, chstat, obj, last, dastat) in enumerate(plan):
        rows.append(_ev5_row(obj, curno, sentyp, senatt, axis, units, spec.nfp, last, spec.delt_us, dastat, chstat,
                             f"CHANNEL {curno}"))
        if dastat != "AM":
            continue
        scale = 1e4 if units == "NWT" else 1.0
        values = _as_written(scale * _pulse(time, 20 + 10 * k, length, 0.3 * (k - 2), spec.seed + k))
        m = last - spec.nfp + 1  # the file runs on past a short channel's last valid sample
        data[curno] = (time[:m], values[:m])
        lines = [f"{t:.6f}\t{v:.6f}" for t, v in zip(time, values)]
        _write(folder / f"{stem}.{curno:03d}", lines, spec.crlf)
    header = [
        f"# Source: NHTSA Vehicle Database - Test Number: {spec.test_number}",
        "----- EV5 -----",
        "----- TEST -----",
        f"V5|FAKE TEST|OBJ|01/JAN/2020|LAB|C1|R1|NCA|VTB|CON|DRY|20|OTH|OTH|{spec.speed_kmh}|0|0|0|{len(plan)}|NONE",
        "----- VEHICLE -----",
        f"1|16|03|2020|M1|4S|VIN123|4CIF|2.5|AF|{spec.weight_kg}|{spec.weight_kg - 100}|{spec.wheelbase_mm}|4800|1800|"
        f"{spec.cg_mm}|UN|UNK|P||{spec.speed_kmh}",
        "----- INSTRUMENTATION -----",
        *rows,
        "----- END -----",
    ]
    path = folder / f"{stem}.EV5"
    _write(path, header, spec.crlf)
    return EV5Written(folder, path, pulse, skipped, barrier, data)



def write_ev5_pulse(folder: Path, test_number: int, time: np.ndarray, decel: np.ndarray, speed_kmh: float,
                    weight_kg: float, rear_share: float, lead: int = 20) -> Path:
    """An EV5 folder holding one rear-floor X accelerometer that records ``decel`` (m/s^2, t = 0 at contact)."""
    folder.mkdir(parents=True, exist_ok=True)
    dt = float(time[1] - time[0])
    accel = np.concatenate([np.zeros(lead), -np.asarray(decel) / G0])  # X acceleration: negative while slowing
    delt_us = round(dt * 1e6)
    row = _ev5_row(1, 1, "AC", "FLRR", "XG", "G'S", -lead, accel.size - lead - 1, delt_us, "AM", "P", "REAR FLOOR X")
    stamps = (np.arange(accel.size) - lead) * delt_us * 1e-6
    _write(folder / f"v{test_number}.001", [f"{t:.6f}\t{a:.6f}" for t, a in zip(stamps, accel)], False)
    wheelbase = 2800
    header = [
        "----- EV5 -----", "----- TEST -----",
        f"V5|FAKE TEST|OBJ|01/JAN/2020|LAB|C1|R1|NCA|VTB|CON|DRY|20|OTH|OTH|{speed_kmh:.2f}|0|0|0|1|NONE",
        "----- VEHICLE -----",
        f"1|16|03|2020|M1|4S|VIN123|4CIF|2.5|AF|{weight_kg:.0f}|{weight_kg - 100:.0f}|{wheelbase}|4800|1800|"
        f"{rear_share * wheelbase:.0f}|UN|UNK|P||{speed_kmh:.2f}",
        "----- INSTRUMENTATION -----", row, "----- END -----",
    ]
    _write(folder / f"v{test_number}.EV5", header, False)
    return folder


def _write(path: Path, lines: list[str], crlf: bool) -> None:
    path.write_bytes(("\r\n" if crlf else "\n").join(lines).encode("latin-1") + (b"\r\n" if crlf else b"\n"))


# --- ISO-MME ----------------------------------------------------------------------------


@dataclasses.dataclass
class MMESpec:
    v0: float
    mass: float
    dt_us: int
    k0: int  # first sample at -k0 * dt
    n: int
    with_cg: bool
    filter_class: str
    unit: str
    crlf: bool
    upper_names: bool
    padded: bool
    seed: int


@st.composite
def mme_specs(draw) -> MMESpec:
    """Random but valid ISO-MME tests."""
    return MMESpec(
        v0=draw(st.floats(3.0, 30.0)),
        mass=draw(st.floats(800.0, 3000.0)),
        dt_us=draw(st.sampled_from([10, 20, 50, 80, 100])),
        k0=draw(st.integers(5, 40)),  # n >= 60: always samples after contact
        n=draw(st.integers(60, 400)),
        with_cg=draw(st.booleans()),
        filter_class=draw(st.sampled_from(list("P0ABCD"))),
        unit=draw(st.sampled_from(["g", "m/s^2"])),
        crlf=draw(st.booleans()),
        upper_names=draw(st.booleans()),
        padded=draw(st.booleans()),
        seed=draw(st.integers(0, 2**31)),
    )


@dataclasses.dataclass
class MMEWritten:
    folder: Path
    pulse_channels: list[int]
    data: dict  # channel number -> (time s, value as written, unit)


def _field(name: str, value, padded: bool) -> str:
    value = "NOVALUE" if value is None else value
    return f"{name:<28}:{value}" if padded or len(name) >= 28 else f"{name}:{value}"


def write_mme(folder: Path, spec: MMESpec, test: str = "t1") -> MMEWritten:
    """Write an ISO-MME test folder; the rear-seat twins and a Z channel are always there."""
    rng = np.random.default_rng(spec.seed)
    dt = spec.dt_us * 1e-6  # float noise for most steps, as real writers produce
    time = -spec.k0 * dt + dt * np.arange(spec.n)
    f = spec.filter_class
    codes = [f"10SEATLERE00ACX{f}", f"10SEATRIRE00ACX{f}", f"10SEATLEL1REACX{f}", f"10SEATRIR1REACX{f}",
             f"10SEATLERE00ACZ{f}", f"10ENGNTP0000ACX{f}"]
    if spec.with_cg:
        codes.insert(int(rng.integers(0, len(codes) + 1)), f"10VEHCCG0000ACX{f}")
    pulse = [i for i, c in enumerate(codes, start=1) if c[2:6] == "VEHC"] or [1, 2]
    name = str.upper if spec.upper_names else str.lower
    chan_dir = folder / ("CHANNEL" if spec.upper_names else "Channel")
    chan_dir.mkdir(parents=True, exist_ok=True)
    p = spec.padded
    scale = 1.0 if spec.unit == "g" else G0
    data = {}
    for i, code in enumerate(codes, start=1):
        values = _as_written(scale * _pulse(time, 20 + 7 * i, 0.4 * time[-1], 0.2 * (i - 3), spec.seed + i))
        data[i] = (time, values, spec.unit)
        header = [_field("Test object number", 1, p), _field("Name of the channel", f"CHANNEL {i}", p),
                  _field("Channel code", code, p), _field("Comments", "first", p), _field("Comments", None, p),
                  _field("Unit", spec.unit, p), _field("Channel frequency class", None, p),
                  _field("Sampling interval", repr(dt), p), _field("Bit resolution", None, p),
                  _field("Time of first sample", repr(float(time[0])), p),
                  _field("Number of samples", spec.n, p)]
        _write(chan_dir / name(f"{test}.{i:03d}"), header + [f"{v:.6f}" for v in values], spec.crlf)
    chn = [_field("Instrumentation standard", "SAE J211", p), _field("Number of channels", len(codes), p)]
    chn += [_field(f"Name of channel {i:03d}", f"{c} / CHANNEL {i}", p) for i, c in enumerate(codes, start=1)]
    _write(chan_dir / name(f"{test}.chn"), chn, spec.crlf)
    mme = [_field("Data format edition number", "1.6", p), _field("Laboratory name", None, p),
           _field("Customer test ref. number", "42", p), _field("Comments", "a: b", p), _field("Comments", "c", p),
           _field("Number of test objects", 1, p), _field("Name of test object 1", "FAKE CAR", p),
           _field("Velocity test object 1", repr(spec.v0), p),
           _field("Mass test object 1", repr(spec.mass), p)]
    _write(folder / name(f"{test}.mme"), mme, spec.crlf)
    return MMEWritten(folder, pulse, data)


# --- LS-DYNA binout ---------------------------------------------------------------------


def write_binout(path: Path, time: np.ndarray, databases: dict, version: str = "fake R12") -> Path:
    """Write an LSDA ``binout`` laid out as LS-DYNA lays it out, with lasso-python's LSDA writer.

    ``databases`` maps a directory (``rwforc/forces``, ``matsum``, ``nodout``, ``glstat``) to
    ``(ids, {history name: array of shape (n_states,) or (n_states, n_ids)})``; ``time`` is in the
    model's time unit. Values are written in single precision, as LS-DYNA writes them.
    """
    from lasso.dyna.lsda_py3 import Lsda

    path.parent.mkdir(parents=True, exist_ok=True)
    lsda = Lsda(str(path), "w")
    for directory, (ids, histories) in databases.items():
        lsda.cd(f"/{directory}/metadata")
        if ids is not None:
            lsda.write("ids", Lsda.I4, [int(i) for i in ids])
        lsda.write("version", Lsda.I1, list(version.encode()))
        for k, t in enumerate(time):
            lsda.cd(f"/{directory}/d{k + 1:06d}")
            lsda.write("time", Lsda.R4, [float(t)])
            for name, values in histories.items():
                lsda.write(name, Lsda.R4, [float(v) for v in np.atleast_1d(values[k])])
    lsda.close()
    return path
