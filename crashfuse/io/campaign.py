"""The campaign folder: the contract between every part of crashfuse, and its reader.

A campaign folder holds ``conditions.csv`` (one row per run, units in the column names;
:mod:`crashfuse.io.conditions`) and ``pulses/<run_id>.csv`` (:mod:`crashfuse.io.pulse_csv`); a
row may instead point at an NHTSA EV5 or ISO-MME test folder or an LS-DYNA binout with
``pulse_path``. The full format is in ``docs/campaign-format.md``. Everything is converted to SI
once, when read; the writer is :mod:`crashfuse.io.campaign_write`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

import crashfuse
from crashfuse.errors import InputError
from crashfuse.io.checks import prepare_pulse
from crashfuse.io.conditions import (CANONICAL, CONDITIONS, DEFAULT_CFC, LSDYNA, OPTIONAL, TEXT_REQUIRED,
                                     check_table, parse_conditions)
from crashfuse.io.lsdyna import is_binout, read_binout
from crashfuse.io.pulse_csv import checked_pulse, plain_pulse_csv, plain_pulse_files
from crashfuse.io.tables import is_blank
from crashfuse.signals.pulse import Pulse

PULSES = "pulses"


@dataclasses.dataclass(eq=False)
class Campaign:
    """Crash tests and CAE runs with their impact conditions, in SI.

    Parameters
    ----------
    conditions : pandas.DataFrame, shape (n_runs, n_columns)
        One row per run with the canonical columns ``run_id, source, v0_mps, front_weight_kg,
        rear_weight_kg, powertrain, drive``, optionally ``cae_run_id`` (a test's companion CAE run)
        and ``pulse_path`` (an EV5 or ISO-MME folder or an LS-DYNA binout relative to ``root``, a
        binout with ``lsdyna_source`` and ``lsdyna_units``), plus any extra column.
    pulses : mapping of str to Pulse
        The pulse of every run, keyed by run_id, in SI (from first contact on as `read_campaign`
        leaves filtered pulses).
    root : Path or None
        The folder the campaign was read from (resolves ``pulse_path``); None if built in memory.
    source : str or None
        :func:`folder_digest` of the folder when the whole campaign was read from it unchanged; None if
        built in memory or a subset. A surrogate fitted on the campaign records it.
    known_hash : str or None
        The content hash, when `read_campaign` found the folder byte-identical to an earlier full read
        of it (its pulses are then read on first use).
    """

    conditions: pd.DataFrame
    pulses: Mapping[str, Pulse]
    root: Path | None = None
    source: str | None = None
    known_hash: str | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self):
        # The same rules as the reader, so that whatever is in memory can be written and read back.
        missing = [c for c in CANONICAL if c not in self.conditions.columns]
        if missing:
            raise InputError(f"expected the canonical columns {CANONICAL}, missing {missing}", self.root, "conditions")
        cols = [*TEXT_REQUIRED, *[c for c in OPTIONAL if c in self.conditions.columns]]
        check_table({c: [None if is_blank(v) else v for v in self.conditions[c]] for c in cols}, self.root)
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
        return None if is_blank(cae_id) else self.pulses[cae_id]

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
        if self.known_hash is not None:
            return self.known_hash
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


def read_campaign(folder: str | os.PathLike, cfc: int | None = DEFAULT_CFC, runs: Iterable[str] | None = None,
                  known: tuple[str | None, str | None] | None = None) -> Campaign:
    """Read and validate a campaign folder.

    Parameters
    ----------
    folder : path-like
        Folder with ``conditions.csv`` and ``pulses/``.
    cfc : int or None
        SAE J211 channel frequency class applied to raw pulses (EV5, unfiltered ISO-MME, CSV rows
        with ``cfc = raw``) before cropping at first contact; None keeps every pulse as read,
        pre-impact samples included. Processed pulses are never filtered again.
    runs : iterable of str, optional
        Read only these runs and the companion CAE runs their tests name (e.g. one fold's test for
        its score: a campaign of a thousand CAE runs takes seconds to read). Default every run.
    known : (str, str), optional
        ``(source, content_hash)`` of an earlier full read of this folder (what a CAE surrogate fitted
        on it records). If the folder's :func:`folder_digest` still equals ``source``, nothing else is
        parsed now: each pulse is read on first use and the content hash is the known one (a fold
        job needs a dozen of a thousand runs). Otherwise, and with ``runs``, the folder is read as
        without it.

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
    frame, cfcs = parse_conditions(path)
    if runs is not None:
        keep = _with_companions(frame, set(runs), path)
        cfcs = [c for c, k in zip(cfcs, keep) if k]
        frame = frame[keep].reset_index(drop=True)
    rows = frame.to_dict("records")
    if runs is None and known is not None and known[0] is not None:
        source = folder_digest(root, rows, cfc)
        if source == known[0]:
            pulses = _LazyPulses(root, path, {row["run_id"]: (row, c) for row, c in zip(rows, cfcs)}, cfc)
            return Campaign(frame, pulses, root, source=source, known_hash=known[1])
    plain = plain_pulse_files(_pulse_file(root, row) for row in rows if is_blank(row.get("pulse_path")))
    pulses = {}
    for row, row_cfc in zip(rows, cfcs):
        pulses[row["run_id"]] = _load_run(root, path, row, row_cfc, cfc, plain)
    return Campaign(frame, pulses, root, source=None if runs is not None else folder_digest(root, rows, cfc))


def folder_digest(root: Path, rows: list[dict], cfc: int | None) -> str | None:
    """SHA-256 (hex) of a campaign folder's bytes as this crashfuse version reads them with ``cfc``: the conditions
    file and each row's pulse file (or every file of its ``pulse_path`` folder); None if one cannot be read.

    Stricter than :meth:`Campaign.content_hash` (rewriting a file in other units changes it) and several times
    cheaper than parsing the runs: equal digests mean the same campaign.
    """
    h = hashlib.sha256(f"crashfuse {crashfuse.__version__}\0cfc={cfc}\0".encode())
    try:
        h.update((root / CONDITIONS).read_bytes())
        for row in rows:
            h.update(f"\0{row['run_id']}\0".encode())
            for name, file in _source_files(root, row):
                h.update(f"{name}\0".encode())
                h.update(file.read_bytes())
    except OSError:
        return None
    return h.hexdigest()


def _source_files(root: Path, row: dict) -> list[tuple[str, Path]]:
    """The files a conditions row's pulse is read from, with their names within its ``pulse_path`` folder."""
    if is_blank(row.get("pulse_path")):
        return [("", _pulse_file(root, row))]
    where = root / row["pulse_path"]
    if not where.is_dir():
        return [("", where)]
    return sorted((p.relative_to(where).as_posix(), p) for p in where.rglob("*") if p.is_file())


class _LazyPulses(Mapping):
    """A campaign folder's pulses keyed by run_id, each read on first use (read-only; pickles with what it read).

    ``rows`` maps each run_id to its conditions row and that row's filter class, in table order.
    """

    def __init__(self, root: Path, conditions: Path, rows: dict, cfc: int | None):
        self._root, self._conditions, self._rows, self._cfc, self._read = root, conditions, rows, cfc, {}

    def __getitem__(self, run_id: str) -> Pulse:
        if run_id not in self._read:
            row, row_cfc = self._rows[run_id]
            self._read[run_id] = _load_run(self._root, self._conditions, row, row_cfc, self._cfc, {})
        return self._read[run_id]

    def __iter__(self):
        return iter(self._rows)

    def __len__(self) -> int:
        return len(self._rows)


def _with_companions(frame, wanted: set, path: Path) -> np.ndarray:
    """Boolean mask of the rows of ``wanted`` runs and of the CAE runs their ``cae_run_id`` names."""
    unknown = sorted(wanted - set(frame["run_id"]))
    if unknown:
        raise InputError(f"expected runs of the campaign, got {unknown}", path, "run_id")
    rows = frame[frame["run_id"].isin(wanted)]
    companions = set(rows["cae_run_id"].dropna()) if "cae_run_id" in frame else set()
    return frame["run_id"].isin(wanted | {c for c in companions if isinstance(c, str) and c}).to_numpy()


def _pulse_file(root: Path, row: dict) -> Path:
    """Where a conditions row without ``pulse_path`` keeps its pulse: ``pulses/<run_id>.csv``."""
    return root / PULSES / f"{row['run_id']}.csv"


def _meta(row: dict) -> dict:
    skip = {"run_id", "source", "v0_mps", "front_weight_kg", "rear_weight_kg"}
    return {k: (None if is_blank(v) else (v.item() if isinstance(v, np.generic) else v))
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
        t, a = checked_pulse(path, plain[path] if path in plain else plain_pulse_csv(path))
        pulse = Pulse(t, a, meta={**meta, "cfc": row_cfc}, where=os.fspath(path), **fields)
    else:
        pulse = _foreign_run(root / meta["pulse_path"], conditions, fields, meta)
    return prepare_pulse(pulse, cfc)


def _foreign_run(where: Path, conditions: Path, fields: dict, meta: dict) -> Pulse:
    """A pulse_path row: the raw record read from its file or folder, the row's conditions winning."""
    raw = _foreign_record(where, conditions, fields, meta)
    warnings = [f"{name}: {conditions.name} gives {fields[name]:.6g}, {os.fspath(where)} gives "
                f"{getattr(raw, name):.6g} (SI); using {conditions.name}"
                for name in ("v0", "front_weight", "rear_weight")
                if abs(getattr(raw, name) - fields[name]) > 0.01 * abs(fields[name])]
    merged = {**raw.meta, **meta}
    if warnings:
        merged["warnings"] = [*raw.meta.get("warnings", []), *warnings]
    return raw.replace(meta=merged, **fields)


def _foreign_record(where: Path, conditions: Path, fields: dict, meta: dict) -> Pulse:
    """The raw pulse a pulse_path names: an LS-DYNA binout, an NHTSA EV5 or an ISO-MME test folder."""
    run = f"(run {fields['run_id']!r})"
    expected = ("expected pulse_path to name an NHTSA EV5 or ISO-MME test folder or an LS-DYNA binout "
                "(file or folder) relative to the campaign")
    if is_binout(where):
        missing = [c for c in LSDYNA if meta.get(c) is None]
        if missing:
            raise InputError(f"expected {missing[0]} on a row whose pulse_path names an LS-DYNA binout {run}",
                             conditions, missing[0])
        return read_binout(where, meta["lsdyna_source"], meta["lsdyna_units"], fields["front_weight"],
                           fields["rear_weight"], v0=fields["v0"], run_id=fields["run_id"])
    if not where.is_dir():
        raise InputError(f"{expected}, but {os.fspath(where)!r} is not a folder nor a binout file {run}", conditions,
                         "pulse_path")
    lsdyna = [c for c in LSDYNA if meta.get(c) is not None]
    if lsdyna:
        raise InputError(f"expected {lsdyna[0]} only on rows whose pulse_path names an LS-DYNA binout, but "
                         f"{os.fspath(where)!r} holds none {run}", conditions, lsdyna[0])
    raw = read_test_folder(where, fields["front_weight"], fields["rear_weight"])
    if raw is None:
        raise InputError(f"{expected}; found no *.EV5 (NHTSA), *.mme (ISO-MME) or binout* in {os.fspath(where)!r} "
                         f"{run}", conditions, "pulse_path")
    return raw


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

