"""CAE runs straight from LS-DYNA ``binout`` files, read with lasso-python.

LS-DYNA is unit-agnostic, so a binout is read with the model's unit system (``mm-ms-kg``, ``mm-s-t``,
``m-s-kg``, ...) and a named source:

* ``rwforc[:<wall id>]`` - the normal force on a rigid wall, divided by the run's mass;
* ``matsum:<part id>`` - a part's rigid-body velocity, differentiated;
* ``nodout:<node id>[:acceleration|:velocity]`` - a node's acceleration (default) or velocity.

Sign convention: a run travels along model X (either sign, taken from its initial velocity) and its
deceleration is positive while it slows along that direction, as everywhere in crashfuse. The wall's
normal force presses the run back, so force / mass is the deceleration. The record is moved to the
campaign's 10 kHz grid by averaging over each grid interval (the velocity change is kept exactly, and
finer output is not aliased), its time is shifted so that t = 0 at first contact (pre-contact samples
kept as filter lead-in), and it is returned raw: the campaign reader filters it to CFC 60 as it does
raw test data. Output sampled coarser than 10 kHz is refused, naming the rate found.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np

from crashfuse.errors import InputError
from crashfuse.signals.iso18571 import DT as STEP
from crashfuse.signals.pulse import MIN_SAMPLES, Pulse

SOURCE_FIELD = "lsdyna_source"
UNITS_FIELD = "lsdyna_units"
LENGTHS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}  # m per model length unit
TIMES = {"s": 1.0, "ms": 1e-3}  # s per model time unit
MASSES = {"kg": 1.0, "g": 1e-3, "t": 1e3}  # kg per model mass unit
MIN_RATE = 1.0 / STEP  # Hz: a crash pulse needs 10 kHz (ISO/TS 18571's sampling; CFC 60 data)
RATE_SLACK = 1.05  # LS-DYNA writes at the first solver step past each output time: intervals jitter
CONTACT_FRACTION = 1e-3  # of the peak deceleration: below it, the run has not yet touched the wall
INSTALL = "pip install --no-deps -r lsdyna-requirements.txt"
_SOURCE = re.compile(r"(rwforc)(?::(\d+))?|(matsum):(\d+)|(nodout):(\d+)(?::(acceleration|velocity))?")


@dataclasses.dataclass(frozen=True)
class UnitSystem:
    """A consistent LS-DYNA unit system, as SI factors of its base units."""

    name: str
    length: float  # m
    time: float  # s
    mass: float  # kg

    @property
    def velocity(self) -> float:
        return self.length / self.time

    @property
    def acceleration(self) -> float:
        return self.length / self.time**2

    @property
    def force(self) -> float:
        return self.mass * self.acceleration


@dataclasses.dataclass(frozen=True)
class Source:
    """What a binout row reads: database, entity id (wall, part or node; None = the only wall), quantity."""

    database: str
    entity: int | None
    quantity: str  # force, velocity or acceleration


def unit_system(text: str, where: str | os.PathLike | None = None) -> UnitSystem:
    """Parse ``length-time-mass`` (e.g. ``mm-ms-kg``); InputError naming ``lsdyna_units`` otherwise."""
    parts = str(text).strip().lower().split("-")
    if len(parts) != 3 or parts[0] not in LENGTHS or parts[1] not in TIMES or parts[2] not in MASSES:
        raise InputError(f"expected the model's unit system as length-time-mass, e.g. mm-ms-kg, mm-s-t or m-s-kg "
                         f"(length {'|'.join(LENGTHS)}, time {'|'.join(TIMES)}, mass {'|'.join(MASSES)}), "
                         f"got {text!r}", where, UNITS_FIELD)
    return UnitSystem("-".join(parts), LENGTHS[parts[0]], TIMES[parts[1]], MASSES[parts[2]])


def parse_source(text: str, where: str | os.PathLike | None = None) -> Source:
    """Parse ``rwforc[:id]``, ``matsum:<part>`` or ``nodout:<node>[:acceleration|:velocity]``."""
    m = _SOURCE.fullmatch(str(text).strip().lower())
    if m is None:
        raise InputError(f"expected rwforc[:<wall id>], matsum:<part id> or nodout:<node id>[:acceleration|"
                         f":velocity], got {text!r}", where, SOURCE_FIELD)
    if m[1]:
        return Source("rwforc", None if m[2] is None else int(m[2]), "force")
    if m[3]:
        return Source("matsum", int(m[4]), "velocity")
    return Source("nodout", int(m[6]), m[7] or "acceleration")


def is_binout(path: Path) -> bool:
    """A file named ``binout*`` (LS-DYNA's SMP ``binout``, MPP ``binout0000``) or a folder holding one."""
    if path.is_file():
        return path.name.lower().startswith("binout")
    return path.is_dir() and any(p.is_file() and p.name.lower().startswith("binout") for p in path.iterdir())


def read_binout(path: str | os.PathLike, source: str, units: str, front_weight: float, rear_weight: float,
                v0: float | None = None, run_id: str = "run") -> Pulse:
    """The raw CAE pulse of an LS-DYNA binout, in SI, t = 0 at first contact.

    Parameters
    ----------
    path : path-like
        A ``binout`` file (its ``%NNN`` continuations are read with it) or a folder holding ``binout*``.
    source : str
        What to read (see the module docstring), e.g. ``rwforc``, ``matsum:2000001``, ``nodout:81234``.
    units : str
        The model's unit system, ``length-time-mass`` (e.g. ``mm-ms-kg``).
    front_weight, rear_weight : float
        Axle masses in kg; their sum divides the wall force.
    v0 : float, optional
        Impact speed in m/s, used when the binout gives none (a wall force without ``glstat``);
        otherwise the speed is the initial velocity the binout shows.
    run_id : str
        Identifier of the run.

    Returns
    -------
    Pulse
        ``source='cae'``, sampled at 10 kHz with pre-contact samples (t < 0) kept, ``meta['cfc']``
        None (raw), ``meta['lsdyna']`` naming database, entity, unit system and solver version.

    Raises
    ------
    InputError
        Naming the file and the field: unreadable binout, missing database, unknown id or unit
        system, output too coarse for a crash pulse (rate needed vs found), lasso-python missing.
    """
    path = Path(path)
    system = unit_system(units, path)
    wanted = parse_source(source, path)
    binout = _open(path)
    time, data, initial = _history(binout, wanted, path)
    time = time * system.time
    _check_rate(time, wanted, system, path)
    direction, speed = _direction(initial, system, v0, path)
    if wanted.quantity == "velocity":
        dv = direction * (data[0] - data) * system.velocity
    else:
        # The wall's force pushes the run back along its travel; a node's acceleration is along model X.
        force = wanted.quantity == "force"
        dv = _cumulative(time, data * (system.force / (front_weight + rear_weight) if force
                                       else -direction * system.acceleration))
    steps, decel = _resample(time, dv, _contact(time, dv, path, wanted))
    meta = {"cfc": None, "lsdyna": {"database": wanted.database, "entity": wanted.entity,
                                    "quantity": wanted.quantity, "units": system.name,
                                    "version": _version(binout, wanted)}}
    return Pulse(steps * STEP, decel, speed, front_weight, rear_weight, run_id=run_id, source="cae", meta=meta,
                 where=os.fspath(path))


def _open(path: Path):
    try:
        from lasso.dyna import Binout
    except ImportError:
        raise InputError(f"reading LS-DYNA binout files needs lasso-python: {INSTALL}", path) from None
    pattern = path / "binout*" if path.is_dir() else path
    try:
        binout = Binout(os.fspath(pattern))
        binout.read()
    except Exception as err:  # lasso raises whatever its parser hits on a file that is not LSDA
        raise InputError(f"cannot read as an LS-DYNA binout: {err}", path) from None
    return binout


def _read(binout, path: Path, *keys):
    databases = binout.read()
    if keys[0] not in databases:
        raise InputError(f"the binout has no {keys[0]} database (it holds {', '.join(sorted(databases))}); write "
                         f"it with *DATABASE_{keys[0].upper()} or name another source", path, SOURCE_FIELD)
    if keys[-1] not in binout.read(*keys[:-1]):
        raise InputError(f"the binout's {'/'.join(keys[:-1])} has no {keys[-1]!r} history", path, SOURCE_FIELD)
    return np.asarray(binout.read(*keys))


def _history(binout, source: Source, path: Path):
    """Time (model units), the source's history at its entity, and the initial X velocity if known."""
    if source.database == "rwforc":
        keys = ("rwforc", "forces")
        column = _column(_read(binout, path, *keys, "ids"), source, "wall", path)
        data = _read(binout, path, *keys, "normal_force")
        initial = _glstat_speed(binout)
    else:
        keys = (source.database,)
        name = "x_rbvelocity" if source.database == "matsum" else f"x_{source.quantity}"
        what = "part" if source.database == "matsum" else "node"
        column = _column(_read(binout, path, *keys, "ids"), source, what, path)
        data = _read(binout, path, *keys, name)
        velocity = data if source.quantity == "velocity" else _read(binout, path, *keys, "x_velocity")
        initial = float(_at(velocity, column)[0])
    time = _read(binout, path, *keys, "time")
    return time.astype(float), _at(data, column).astype(float), initial


def _column(ids: np.ndarray, source: Source, what: str, path: Path) -> int:
    ids = np.atleast_1d(ids).astype(int)
    if source.entity is None:
        if ids.size > 1:
            raise InputError(f"the binout has {ids.size} rigid walls (ids {', '.join(map(str, ids))}); name one as "
                             "rwforc:<wall id>", path, SOURCE_FIELD)
        return 0
    hits = np.flatnonzero(ids == source.entity)
    if hits.size == 0:
        shown = ", ".join(map(str, ids[:10])) + (", ..." if ids.size > 10 else "")
        raise InputError(f"{what} {source.entity} is not in {source.database} (ids {shown})", path, SOURCE_FIELD)
    return int(hits[0])


def _at(data: np.ndarray, column: int) -> np.ndarray:
    return data if data.ndim == 1 else data[:, column]


def _glstat_speed(binout) -> float | None:
    if "glstat" in binout.read() and "global_x_velocity" in binout.read("glstat"):
        return float(np.asarray(binout.read("glstat", "global_x_velocity"))[0])
    return None


def _direction(initial: float | None, system: UnitSystem, v0: float | None, path: Path) -> tuple[float, float]:
    """Travel direction along X (+1 or -1) and the impact speed in m/s."""
    if initial is not None and initial != 0:
        return float(np.sign(initial)), abs(initial) * system.velocity
    if v0 is None:
        raise InputError("the binout shows no initial velocity (no glstat global X velocity for a wall force); "
                         "give the impact speed", path, "v0")
    return 1.0, float(v0)


def _check_rate(time: np.ndarray, source: Source, system: UnitSystem, path: Path) -> None:
    if time.size < 2 or time[-1] - time[0] < MIN_SAMPLES * STEP:
        raise InputError(f"{source.database} covers {(time[-1] - time[0]) * 1e3:.3g} ms in {system.name} units "
                         f"({time.size} samples): too short for a crash pulse - wrong unit system?", path, UNITS_FIELD)
    step = float((time[-1] - time[0]) / (time.size - 1))  # mean: LS-DYNA output steps jitter
    if not step <= RATE_SLACK * STEP:
        raise InputError(
            f"{source.database} is written every {step * 1e3:.3g} ms ({1 / step / 1e3:.3g} kHz over {time.size} "
            f"samples): too coarse for a crash pulse, which needs at least {MIN_RATE / 1e3:g} kHz (an output "
            f"interval of at most {STEP * 1e3:g} ms: DT <= {STEP / system.time:.3g} {system.name.split('-')[1]} on "
            f"*DATABASE_{source.database.upper()})", path, SOURCE_FIELD)


def _cumulative(time: np.ndarray, decel: np.ndarray) -> np.ndarray:
    """Velocity change (m/s) from t[0] on, by the trapezoid rule."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (decel[1:] + decel[:-1]) * np.diff(time))])


def _resample(time: np.ndarray, dv: np.ndarray, t0: float) -> tuple[np.ndarray, np.ndarray]:
    """Deceleration on the 10 kHz grid through contact ``t0``: grid indices (0 at contact) and, at each, the
    mean over its interval (velocity change / STEP), for the intervals lying wholly inside the record."""
    steps = np.arange(int(np.ceil((time[0] - t0) / STEP + 0.5)), int(np.floor((time[-1] - t0) / STEP - 0.5)) + 1)
    edges = t0 + STEP * np.append(steps - 0.5, steps[-1] + 0.5)
    return steps, np.diff(np.interp(edges, time, dv)) / STEP


def _contact(time: np.ndarray, dv: np.ndarray, path: Path, source: Source) -> float:
    """Time of first contact: the start of the first output interval whose mean deceleration exceeds 0.1 % of
    the peak (CAE output before contact is zero up to round-off)."""
    rate = np.abs(np.diff(dv) / np.diff(time))
    peak = float(rate.max())
    if peak == 0:
        raise InputError(f"the {source.database} history is zero throughout: no contact", path, SOURCE_FIELD)
    return float(time[np.argmax(rate > CONTACT_FRACTION * peak)])


def _version(binout, source: Source) -> str | None:
    keys = ("rwforc", "forces") if source.database == "rwforc" else (source.database,)
    return str(binout.read(*keys, "version")).strip() if "version" in binout.read(*keys) else None
