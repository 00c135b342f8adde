"""The record of one fold (held-out test, input mode, K) and its JSON file, ``<test>.fold.json``.

The evaluation writes one per fold beside the fold's prediction CSV; tracking logs them
(:mod:`crashfuse.reporting.tracking`). The schema is documented in ``docs/tracking.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

from crashfuse.errors import InputError
from crashfuse.evaluation.iso_table import AUTO, ROW_INPUTS, SCORES, is_window, model_label, window_key
from crashfuse.io.atomic import write_text
from crashfuse.io.tables import read_json

FOLD_SCHEMA = "crashfuse.fold/1"
FOLD_SUFFIX = ".fold.json"
CONDITIONS = ("v0_mps", "front_weight_kg", "rear_weight_kg", "powertrain", "drive")  # numbers (SI), then text


@dataclasses.dataclass
class FoldRecord:
    """What one fold (held-out test, input mode, K) reports for tracking; schema in docs/tracking.md.

    Parameters
    ----------
    test_id : str
        The held-out test.
    inputs : {"paper", "state", "auto"}
        The GP input mode; ``auto`` for the auto model's fold (a copy of the candidate fold it chose,
        named in ``settings['chosen']``).
    k : int
        Number of GMM clusters (GP models), >= 1.
    seed : int
        The seed of every stochastic step of the fold.
    campaign : dict
        ``name`` and ``hash`` (``Campaign.content_hash()``) of the campaign the fold came from.
    conditions : dict
        The held-out test's ``v0_mps, front_weight_kg, rear_weight_kg, powertrain, drive`` (SI).
    settings : dict of str to scalar
        Method and GP settings (trend, nugget, restarts, grid points, Monte Carlo samples ...).
    iso : dict of str to dict of str to float
        The corrected prediction's ISO scores: window label (``'0-60'``) -> the five scores.
    metrics : dict of str to float
        Fit diagnostics and band coverage (e.g. ``coverage_95_0_60``, ``log_marginal_likelihood``).
    figures : list of str
        Figure files, relative to the JSON's folder (or absolute).
    prediction : str or None
        The fold's prediction CSV, relative to the JSON's folder (or absolute).
    run_time : dict
        ``start`` (the fit's) and ``end`` (the rollout's) in UNIX seconds; empty when unknown. The
        fold's tracked run carries them as its start and end time.
    """

    test_id: str
    inputs: str
    k: int
    seed: int
    campaign: dict[str, str]
    conditions: dict[str, Any]
    settings: dict[str, Any]
    iso: dict[str, dict[str, float]]
    metrics: dict[str, float] = dataclasses.field(default_factory=dict)
    figures: list[str] = dataclasses.field(default_factory=list)
    prediction: str | None = None
    run_time: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def model(self) -> str:
        """The ``model`` label of this fold in ``iso_table.csv``."""
        if self.inputs == AUTO:
            return AUTO
        return model_label(self.k, self.settings.get("effects", "none"))

    def iso_metrics(self) -> dict[str, float]:
        """The ISO scores as flat metric names ``iso_<score>_<start>_<end>`` (e.g. ``iso_overall_0_60``)."""
        return {f"iso_{s}_{window_key(w)}": float(scores[s]) for w, scores in self.iso.items() for s in SCORES}


def write_fold_json(path: str | os.PathLike, record: FoldRecord) -> Path:
    """Validate ``record`` and write it atomically as JSON to ``path`` (name ending in ``.fold.json``)."""
    path = Path(path)
    if not path.name.endswith(FOLD_SUFFIX):
        raise ValueError(f"a fold JSON file name ends in {FOLD_SUFFIX!r}, got {path.name!r}")
    doc = {"schema": FOLD_SCHEMA, **dataclasses.asdict(record)}
    _validate_fold(doc, path)
    write_text(path, json.dumps(doc, indent=2, sort_keys=True, allow_nan=False) + "\n")
    return path


def read_fold_json(path: str | os.PathLike) -> FoldRecord:
    """Read and validate a fold JSON; InputError names the file and field of any problem."""
    path = Path(path)
    doc = read_json(path, "expected a fold JSON, but the file does not exist")
    _validate_fold(doc, path)
    return FoldRecord(**{f.name: doc[f.name] for f in dataclasses.fields(FoldRecord) if f.name in doc})


def _validate_fold(doc: Any, path: Path) -> None:
    def fail(field, message):
        raise InputError(message, path, field)

    if not isinstance(doc, dict):
        fail(None, "expected a JSON object")
    if doc.get("schema") != FOLD_SCHEMA:
        fail("schema", f"expected {FOLD_SCHEMA!r}, got {doc.get('schema')!r}")
    required = [f.name for f in dataclasses.fields(FoldRecord) if f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING]
    for name in required:
        if name not in doc:
            fail(name, "expected this key")
    if not _is_text(doc["test_id"]):
        fail("test_id", f"expected a non-empty string, got {doc['test_id']!r}")
    if doc["inputs"] not in ROW_INPUTS:
        fail("inputs", f"expected one of {list(ROW_INPUTS)}, got {doc['inputs']!r}")
    for name, low in (("k", 1), ("seed", 0)):
        if not _is_int(doc[name]) or doc[name] < low:
            fail(name, f"expected an integer >= {low}, got {doc[name]!r}")
    _check_mapping(doc["campaign"], ("name", "hash"), path, "campaign", _is_text, "a non-empty string")
    _check_mapping(doc["conditions"], CONDITIONS[:3], path, "conditions", _is_number, "a finite number")
    _check_mapping(doc["conditions"], CONDITIONS[3:], path, "conditions", _is_text, "a non-empty string")
    _check_scalars(doc["settings"], path, "settings")
    _check_iso(doc["iso"], path)
    _check_scalars(doc.get("metrics", {}), path, "metrics", numbers_only=True)
    reserved = [m for m in doc.get("metrics", {}) if m.startswith("iso_")]
    if reserved:
        fail("metrics", f"names starting with 'iso_' are reserved for the scores in 'iso', got {reserved}")
    figures = doc.get("figures", [])
    if not isinstance(figures, list) or not all(isinstance(f, str) and f for f in figures):
        fail("figures", f"expected a list of file paths, got {figures!r}")
    if doc.get("prediction") is not None and not isinstance(doc["prediction"], str):
        fail("prediction", f"expected a file path or null, got {doc['prediction']!r}")
    run_time = doc.get("run_time", {})
    if run_time:
        _check_mapping(run_time, ("start", "end"), path, "run_time", _is_number, "UNIX seconds")
        if not 0 < run_time["start"] <= run_time["end"]:
            fail("run_time", f"expected 0 < start <= end, got {run_time!r}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_text(value: Any) -> bool:
    return isinstance(value, str) and value.strip() != ""


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_mapping(value: Any, keys: tuple, path: Path, field: str, ok, what: str) -> None:
    """Check that ``value`` is an object whose ``keys`` all pass ``ok`` (described by ``what``)."""
    if not isinstance(value, Mapping):
        raise InputError(f"expected an object with keys {list(keys)}, got {value!r}", path, field)
    for key in keys:
        if not ok(value.get(key)):
            raise InputError(f"expected {key!r} to be {what}, got {value.get(key)!r}", path, f"{field}.{key}")


def _check_scalars(value: Any, path: Path, field: str, numbers_only: bool = False) -> None:
    if not isinstance(value, Mapping):
        raise InputError(f"expected an object of name -> value, got {value!r}", path, field)
    for key, v in value.items():
        ok = _is_number(v) if numbers_only else (v is None or isinstance(v, (str, bool)) or _is_number(v))
        if not ok:
            what = "a finite number" if numbers_only else "a string, finite number, boolean or null"
            raise InputError(f"expected {what}, got {v!r}", path, f"{field}.{key}")


def _check_iso(iso: Any, path: Path) -> None:
    if not isinstance(iso, Mapping) or not iso:
        raise InputError(f"expected an object window -> scores, got {iso!r}", path, "iso")
    for window, scores in iso.items():
        if not is_window(window):
            raise InputError(f"expected a window '<start>-<end>' in ms, got {window!r}", path, "iso")
        if not isinstance(scores, Mapping):
            raise InputError(f"expected an object of the scores {list(SCORES)}", path, f"iso.{window}")
        for s in SCORES:
            v = scores.get(s)
            if not _is_number(v) or not 0.0 <= v <= 1.0:
                raise InputError(f"expected a score in [0, 1], got {v!r}", path, f"iso.{window}.{s}")


def fold_folder(out: str | os.PathLike, inputs: str, model: str, test_id: str) -> Path:
    """``out/<inputs>/<model>/<test_id>``: where one fold's files go (prediction CSV, fold JSON, figure)."""
    return Path(out) / inputs / model / test_id
