"""Writing a campaign folder: atomically, with deterministic bytes, in the units asked for."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Mapping

import pandas as pd

from crashfuse import units
from crashfuse.errors import InputError
from crashfuse.io.atomic import default_mode
from crashfuse.io.campaign import PULSES, Campaign
from crashfuse.io.conditions import CANONICAL, CONDITIONS, DEFAULT_CFC, OPTIONAL, QUANTITIES, RAW
from crashfuse.io.pulse_csv import FLOAT_FORMAT, write_pulse_file
from crashfuse.io.tables import is_blank
from crashfuse.signals.pulse import Pulse


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
        if is_blank(p):
            pulse = campaign.pulses[run_id]
            write_pulse_file(tmp / PULSES / f"{run_id}.csv", pulse.time, pulse.decel, accel_unit)


def _conditions_out(campaign: Campaign, final: Path, speed_unit, mass_unit) -> pd.DataFrame:
    src = campaign.conditions
    out = pd.DataFrame({"run_id": src["run_id"], "source": src["source"]})
    for name, (table, si), unit in zip(QUANTITIES, QUANTITIES.values(), (speed_unit, mass_unit, mass_unit)):
        out[f"{name}_{unit}"] = src[f"{name}_{si}"].to_numpy(float) / table[unit]
    out["powertrain"], out["drive"] = src["powertrain"], src["drive"]
    if "cae_run_id" in src:
        out["cae_run_id"] = src["cae_run_id"]
    if "pulse_path" in src:
        out["pulse_path"] = [None if is_blank(p) else _rebase(p, campaign.root, final) for p in src["pulse_path"]]
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

