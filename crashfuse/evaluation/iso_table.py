"""The ISO score table an evaluation writes (``iso_table.csv``): its columns and row labels.

One row per held-out test x input mode x model x window: the keys ``test_id, inputs, model,
window_ms``, then the five ISO/TS 18571 scores. ``model`` is ``CAE`` (the baseline: the test's
companion CAE run) or ``K<n>`` (the bias model with n clusters), ``K<n>+<effects>`` for the
physics-first hybrid (``K1+auto``, ``K2+strain_rate+powertrain``), or ``auto`` (per fold the candidate
with the smallest inner error, :mod:`crashfuse.method.selection`; its rows have ``inputs`` = ``auto`` too,
beside CAE rows of their own); ``window_ms`` is ``<start>-<end>`` in whole ms. :mod:`crashfuse.reporting.tables` reads and tabulates it.
"""

from __future__ import annotations

import re

ISO_TABLE = "iso_table.csv"
KEYS = ("test_id", "inputs", "model", "window_ms")
SCORES = ("overall", "corridor", "phase", "magnitude", "slope")
COLUMNS = (*KEYS, *SCORES)
BASELINE = "CAE"
AUTO = "auto"  # the model (and input mode) label of the auto model's rows
# The ``inputs`` labels of the table: the input modes (crashfuse.method.projection.INPUTS, not imported:
# a score job must not load the GP stack; tests/test_evaluate.py checks they agree) and auto.
ROW_INPUTS = ("paper", "state", AUTO)
WINDOWS = ("0-20", "0-40", "0-60")
_MODEL = re.compile(r"K([1-9][0-9]*)(\+[a-z_]+(?:\+[a-z_]+)*)?")
_WINDOW = re.compile(r"([0-9]+)-([0-9]+)")


def model_label(k: int, effects: str = "none") -> str:
    """The ``model`` label of the bias model with ``k`` clusters (``K1``, ``K2`` ...) on the CAE model plus
    ``effects`` (:func:`effects_label`; ``K1+auto`` ...)."""
    return f"K{int(k)}" if effects == "none" else f"K{int(k)}+{effects}"


def effects_label(effects) -> str:
    """A :class:`crashfuse.method.config.MethodConfig` ``effects`` as text: ``none``, ``auto`` or ``a+b``."""
    return effects if isinstance(effects, str) else "+".join(effects) or "none"


def window_bounds(label: str) -> tuple[int, int]:
    """Start and end in ms of a ``window_ms`` label such as ``'0-60'``.

    Raises
    ------
    ValueError
        If the label is not ``<start>-<end>`` with integer milliseconds and start < end.
    """
    m = _WINDOW.fullmatch(str(label))
    if not m or int(m[1]) >= int(m[2]):
        raise ValueError(f"expected a window '<start>-<end>' in whole ms with start < end, got {label!r}")
    return int(m[1]), int(m[2])


def window_key(label: str) -> str:
    """The metric-name form of a window label: ``'0-60'`` -> ``'0_60'``."""
    start, end = window_bounds(label)
    return f"{start}_{end}"


def model_order(model: str) -> tuple[int, int, str]:
    """Sort key of a ``model`` label: CAE first, then K ascending, each K's hybrids after it, auto last."""
    if model == BASELINE:
        return 0, 0, ""
    if model == AUTO:
        return 2, 0, ""
    m = _MODEL.fullmatch(model)
    return 1, int(m[1]), m[2] or ""


def is_model_label(label: str) -> bool:
    """Whether ``label`` is a ``model`` label: ``CAE``, ``auto`` or ``K<n>`` with n >= 1, optionally ``+<effects>``."""
    return label in (BASELINE, AUTO) or _MODEL.fullmatch(label) is not None


def model_tag(model: str) -> str:
    """The short form of a model label in run names and tags: ``K2+auto`` -> ``2+auto``, ``auto`` as is."""
    return model[1:] if _MODEL.fullmatch(model) else model


def is_window(label: str) -> bool:
    """Whether ``label`` is a ``window_ms`` label (see :func:`window_bounds`)."""
    try:
        window_bounds(label)
    except ValueError:
        return False
    return True
