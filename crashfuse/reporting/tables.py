"""Report tables from an evaluation: the paper's Table 2 and a summary.

An evaluation directory holds ``iso_table.csv`` (one row per held-out test x input mode x model
x window, columns ``test_id, inputs, model, window_ms, overall, corridor, phase, magnitude,
slope``; :mod:`crashfuse.evaluation.iso_table`). This module reads and validates it, combines the
per-fold tables, and renders the table in the shape of the paper's Table 2 (rows: test x
{CAE, K1, K2, K3}; columns: time windows; one table per input mode) as Markdown and LaTeX.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import pandas as pd

from crashfuse.errors import InputError
from crashfuse.evaluation.iso_table import (COLUMNS, ISO_TABLE, KEYS, ROW_INPUTS, SCORES, is_model_label, is_window, model_order,
                                            window_bounds)
from crashfuse.io.atomic import atomic_path, write_text
from crashfuse.io.tables import read_table

_NATURAL = re.compile(r"([0-9]+)")
_SOURCE = "source"  # frame.attrs key: the file a table was read from, to locate errors found later


# --- labels ------------------------------------------------------------------------------------


def natural_key(text: str) -> tuple:
    """Sort key comparing digit runs as numbers, so that T2 comes before T10."""
    return tuple(int(p) if p.isdigit() else p for p in _NATURAL.split(str(text)))


# --- iso_table.csv ---------------------------------------------------------------------------


def read_iso_table(path: str | os.PathLike) -> pd.DataFrame:
    """Read and validate an ``iso_table.csv``.

    Parameters
    ----------
    path : str or PathLike
        The CSV file, or an evaluation directory holding ``iso_table.csv``.

    Returns
    -------
    pandas.DataFrame, shape (n_rows, >= 9)
        The table with ``test_id, inputs, model, window_ms`` as text and the five scores as
        floats in [0, 1]; further columns are kept as read.

    Raises
    ------
    InputError
        Missing file or column, an unknown label (``inputs`` not paper/state, ``model`` not CAE
        or K<n>, ``window_ms`` not ``<start>-<end>``), a score that is not a number in [0, 1], or
        a repeated (test_id, inputs, model, window_ms) row.
    """
    path = Path(path)
    if path.is_dir():
        path = path / ISO_TABLE
    frame = read_table(path, COLUMNS, "an ISO score table", dtype={k: str for k in KEYS}, keep_default_na=False)
    if frame.empty:
        raise InputError("expected at least one row of scores, found only the header", path, "test_id")
    _check_labels(frame, path)
    for score in SCORES:
        frame[score] = _scores(frame, score, path)
    dup = frame.duplicated(list(KEYS))
    if dup.any():
        row = frame.loc[dup].iloc[0]
        raise InputError(f"expected one row per test, inputs, model and window; repeated {tuple(row[list(KEYS)])}",
                         path, "test_id")
    frame.attrs[_SOURCE] = os.fspath(path)
    return frame


def table_file(frame: pd.DataFrame) -> str | None:
    """The file an ISO table (or a selection of its rows) was read from by `read_iso_table`; None if built."""
    return frame.attrs.get(_SOURCE)


def _check_labels(frame: pd.DataFrame, path: Path) -> None:
    checks = {
        "test_id": (lambda v: v.strip() != "", "a non-empty test id"),
        "inputs": (lambda v: v in ROW_INPUTS, f"one of {list(ROW_INPUTS)}"),
        "model": (is_model_label, "'CAE', 'auto' or 'K<n>' (n >= 1), optionally '+<effects>'"),
        "window_ms": (is_window, "'<start>-<end>' in ms with start < end"),
    }
    for col, (ok, expected) in checks.items():
        for i, value in enumerate(frame[col]):
            if not ok(value):
                raise InputError(f"expected {expected}, got {value!r} in data row {i + 1}", path, col)


def _scores(frame: pd.DataFrame, col: str, path: Path) -> pd.Series:
    values = pd.to_numeric(frame[col], errors="coerce")
    bad = ~values.between(0.0, 1.0)  # also catches NaN from text or blanks
    if bad.any():
        i = int(bad.to_numpy().nonzero()[0][0])
        raise InputError(f"expected a score in [0, 1], got {frame[col].iloc[i]!r} in data row {i + 1}", path, col)
    return values.astype(float)


# --- Table 2 -----------------------------------------------------------------------------------


def table2(frame: pd.DataFrame, inputs: str, score: str = "overall") -> pd.DataFrame:
    """One input mode's scores in the shape of the paper's Table 2.

    Parameters
    ----------
    frame : pandas.DataFrame
        A validated ISO table (see `read_iso_table`).
    inputs : {"paper", "state"}
        The input mode to tabulate.
    score : str
        Which score column to show (default the overall ISO rating).

    Returns
    -------
    pandas.DataFrame, shape (n_tests * n_models, n_windows)
        Index (test_id, model) in natural test order with CAE first and K ascending; columns
        the windows in order of start then end. A missing cell is NaN.
    """
    if score not in SCORES:
        raise InputError(f"expected a score in {SCORES}, got {score!r}", table_file(frame), "score")
    rows = frame[frame["inputs"] == inputs]
    if rows.empty:
        raise InputError(f"expected rows with inputs {inputs!r}, found none", table_file(frame), "inputs")
    wide = rows.pivot(index=["test_id", "model"], columns="window_ms", values=score)
    order = sorted(wide.index, key=lambda tm: (natural_key(tm[0]), model_order(tm[1])))
    windows = sorted(wide.columns, key=window_bounds)
    return wide.loc[order, windows].rename_axis(columns=None)


def _best(table: pd.DataFrame) -> pd.DataFrame:
    """True where a cell holds the highest score of its test and window (ties all marked)."""
    top = table.groupby(level="test_id", sort=False).transform("max")
    return table.eq(top) & table.notna()


def _cell(value: float, digits: int) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def table2_markdown(frame: pd.DataFrame, inputs: str, score: str = "overall", digits: int = 3) -> str:
    """The Table 2 of one input mode as a Markdown pipe table; the best score per test and window is bold."""
    table = table2(frame, inputs, score)
    best = _best(table)
    head = ["Test", "Model", *(f"({a}, {b}) ms" for a, b in map(window_bounds, table.columns))]
    rule = _md_row(["---"] * 2 + ["---:"] * len(table.columns))
    lines = [f"**{score} ISO score, {inputs} inputs**", "", _md_row(head), rule]
    previous = None
    for (test, model), values in table.iterrows():
        cells = [_cell(v, digits) for v in values]
        cells = [f"**{c}**" if b else c for c, b in zip(cells, best.loc[(test, model)])]
        lines.append(_md_row([_md_escape(test) if test != previous else "", model, *cells]))
        previous = test
    return "\n".join(lines) + "\n"


def _md_row(cells) -> str:
    return "| " + " | ".join(cells) + " |"


def _md_escape(text: str) -> str:
    return re.sub(r"([\\|*_`])", r"\\\1", text)


_LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                  "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def _tex_escape(text: str) -> str:
    return "".join(_LATEX_SPECIAL.get(c, c) for c in text)


def table2_latex(frame: pd.DataFrame, inputs: str, score: str = "overall", digits: int = 3) -> str:
    """The Table 2 of one input mode as a LaTeX ``tabular`` (booktabs); the best per test and window is bold."""
    table = table2(frame, inputs, score)
    best = _best(table)
    n = len(table.columns)
    windows = " & ".join(f"({a}, {b})" for a, b in map(window_bounds, table.columns))
    lines = [
        f"% {score} ISO score, {_tex_escape(inputs)} inputs (crashfuse.reporting.tables)",
        rf"\begin{{tabular}}{{ll{'r' * n}}}",
        r"\toprule",
        rf"Test & Model & \multicolumn{{{n}}}{{c}}{{ISO score, time period in ms}} \\",
        rf"\cmidrule(lr){{3-{n + 2}}}",
        rf" & & {windows} \\",
        r"\midrule",
    ]
    for test, block in table.groupby(level="test_id", sort=False):
        for j, ((_, model), values) in enumerate(block.iterrows()):
            cells = [_cell(v, digits) for v in values]
            cells = [rf"\textbf{{{c}}}" if b else c for c, b in zip(cells, best.loc[(test, model)])]
            first = rf"\multirow{{{len(block)}}}{{*}}{{{_tex_escape(test)}}}" if j == 0 else ""
            lines.append(f"{first} & {_tex_escape(model)} & " + " & ".join(cells) + r" \\")
        lines.append(r"\midrule")
    lines[-1] = r"\bottomrule"
    lines.append(r"\end{tabular}")
    return "\n".join(lines) + "\n"


# --- summary -----------------------------------------------------------------------------------


def summary(frame: pd.DataFrame) -> pd.DataFrame:
    """Mean scores over the held-out tests per input mode, model and window.

    Returns
    -------
    pandas.DataFrame, shape (n_groups, 4 + 5)
        Columns ``inputs, model, window_ms, n_tests`` and the mean of each score, rows ordered
        by input mode, model (CAE first, K ascending) and window.
    """
    grouped = frame.groupby(["inputs", "model", "window_ms"], sort=False)
    out = grouped[list(SCORES)].mean()
    out.insert(0, "n_tests", grouped["test_id"].nunique())
    out = out.reset_index()
    order = sorted(out.index, key=lambda i: (ROW_INPUTS.index(out.at[i, "inputs"]), model_order(out.at[i, "model"]),
                                             window_bounds(out.at[i, "window_ms"])))
    return out.loc[order].reset_index(drop=True)


def summary_markdown(frame: pd.DataFrame, digits: int = 3) -> str:
    """The `summary` as a Markdown pipe table."""
    table = summary(frame)
    lines = [_md_row(list(table.columns)), _md_row(["---"] * 3 + ["---:"] * (len(table.columns) - 3))]
    for row in table.itertuples(index=False):
        scores = (_cell(getattr(row, s), digits) for s in SCORES)
        lines.append(_md_row([row.inputs, row.model, row.window_ms, str(row.n_tests), *scores]))
    return "\n".join(lines) + "\n"


def aggregate_iso_tables(paths, out: str | os.PathLike) -> pd.DataFrame:
    """Concatenate per-fold ISO tables into one, each CAE row once; write it atomically.

    Every K of a test and input mode rates the same CAE pulse, so its CAE rows repeat across
    fold tables; they must agree. Two different rows for one (test, inputs, model, window) are an
    error.

    Parameters
    ----------
    paths : sequence of str or PathLike
        Per-fold ``iso_table.csv`` files (or folders holding one).
    out : str or PathLike
        The combined ``iso_table.csv``.

    Returns
    -------
    pandas.DataFrame
        The combined table, sorted by test, inputs, model and window.

    Raises
    ------
    InputError
        A table that `read_iso_table` refuses, or one whose row disagrees with another table's
        (naming the later file and the first differing column).
    """
    frames = [read_iso_table(path) for path in paths]
    if not frames:
        raise InputError("expected at least one per-fold ISO table", field="tables")
    files = pd.concat([pd.Series(table_file(f), index=f.index) for f in frames], ignore_index=True)
    frame = pd.concat(frames, ignore_index=True)
    keep = ~frame.duplicated()
    frame, files = frame[keep], files[keep]
    clash = frame.duplicated(list(KEYS))  # a row that differs from an earlier one with the same keys
    if clash.any():
        _disagreement(frame, files, frame.index[clash][0])
    order = frame.assign(_t=frame["test_id"].map(natural_key), _m=frame["model"].map(model_order),
                         _w=frame["window_ms"].map(window_bounds))
    frame = order.sort_values(["_t", "inputs", "_m", "_w"]).drop(columns=["_t", "_m", "_w"]).reset_index(drop=True)
    with atomic_path(out) as tmp:
        frame.to_csv(tmp, index=False, float_format="%.6g")
    read_iso_table(out)  # the combined table obeys the contract
    return frame


def _disagreement(frame: pd.DataFrame, files: pd.Series, row) -> None:
    """Raise for ``row``, which repeats the keys of an earlier row of another table with other values."""
    key = frame.loc[row, list(KEYS)]
    first = frame.index[(frame[list(KEYS)] == key).all(axis=1)][0]
    key = tuple(key)
    columns = [c for c in frame.columns if not _same(frame.at[first, c], frame.at[row, c])]
    col = columns[0]
    raise InputError(f"disagrees with {files[first]} on {key}: {col} {frame.at[row, col]} against "
                     f"{frame.at[first, col]}", files[row], col)


def _same(a, b) -> bool:
    return a == b or (pd.isna(a) and pd.isna(b))


def write_tables(iso_table: str | os.PathLike, out_dir: str | os.PathLike, score: str = "overall") -> list[Path]:
    """Write the Table 2 of every input mode (Markdown and LaTeX) and the summary, atomically.

    Parameters
    ----------
    iso_table : str or PathLike
        ``iso_table.csv`` or the evaluation directory holding it.
    out_dir : str or PathLike
        Folder for ``table2_<inputs>.md``, ``table2_<inputs>.tex``, ``summary.csv`` and ``summary.md``.
    score : str
        The score shown in the Table 2 files.

    Returns
    -------
    list of Path
        The files written.
    """
    frame = read_iso_table(iso_table)
    out_dir = Path(out_dir)
    texts = {}
    for inputs in (m for m in ROW_INPUTS if (frame["inputs"] == m).any()):
        texts[f"table2_{inputs}.md"] = table2_markdown(frame, inputs, score)
        texts[f"table2_{inputs}.tex"] = table2_latex(frame, inputs, score)
    texts["summary.csv"] = summary(frame).to_csv(index=False, float_format="%.6f", lineterminator="\n")
    texts["summary.md"] = summary_markdown(frame)
    for name, text in texts.items():
        write_text(out_dir / name, text)
    return [out_dir / name for name in texts]
