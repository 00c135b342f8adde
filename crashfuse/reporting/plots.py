"""Figures of an evaluation (per-fold pulse predictions, the ISO score summary) and of a gap diagnosis.

The fold figure follows the paper's Figs. 5-8: deceleration in g against time in ms (0-100 ms),
the physical test, the CAE run and the bias-corrected mean with its 95 % band. The summary figure
shows the ISO score of every held-out test for CAE and each cluster count K, one panel per input
mode. Figures are built on a bare ``matplotlib.figure.Figure`` (Agg canvas, no pyplot state) and
saved as PNG without a Software/time stamp, atomically, so equal inputs give equal bytes.
The gap figures (:func:`bias_map_figure`, :func:`gap_pulses_figure`) draw a
:class:`crashfuse.diagnosis.gap.GapMap`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from crashfuse.errors import InputError
from crashfuse.evaluation.iso_table import AUTO, BASELINE, ROW_INPUTS, SCORES, model_order, model_tag, window_bounds
from crashfuse.evaluation.records import fold_folder
from crashfuse.io.atomic import atomic_path
from crashfuse.io.prediction import read_prediction_csv
from crashfuse.reporting.tables import natural_key, read_iso_table, table2, table_file
from crashfuse.signals.pulse import Pulse
from crashfuse.units import G0, MM, MPH, MS

T_END = 0.1  # s, the span of the paper's figures
DPI = 120
# Colour-blind safe (Okabe-Ito): test black, CAE vermillion, corrected blue.
COLORS = {"test": "black", "cae": "#D55E00", "mean": "#0072B2", "band": "#56B4E9"}
MODEL_COLORS = ["#7F7F7F", "#56B4E9", "#009E73", "#E69F00", "#CC79A7", "#0072B2", "#F0E442"]
# Significant regions of a gap diagnosis: test above CAE warm, below cool.
GAP_SHADES = {1: "#E69F00", -1: "#56B4E9"}


def fold_figure(test: Pulse | None, prediction: pd.DataFrame, title: str | None = None) -> Figure:
    """Test vs CAE vs corrected mean with its 95 % band, in the manner of the paper's Figs. 5-8.

    Parameters
    ----------
    test : Pulse or None
        The held-out physical test (SI, decel in m/s^2); None for a condition nobody tested.
    prediction : pandas.DataFrame, shape (n_samples, >= 5)
        A validated prediction table (see `read_prediction_csv`), deceleration in g.
    title : str, optional
        Figure title, e.g. ``'T03, paper inputs, K = 2'``.

    Returns
    -------
    matplotlib.figure.Figure
        One axes: deceleration in g against time in ms over 0-100 ms.
    """
    fig = _figure((6.4, 4.4))
    ax = fig.add_subplot()
    _draw_fold(ax, test, prediction)
    # Below the axes: pulses fill the plot area at every time.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4, frameon=False)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def panels_figure(test: Pulse, predictions: Mapping[str, pd.DataFrame], title: str | None = None) -> Figure:
    """One held-out test predicted by several models side by side (e.g. K = 1, 2, 3), as the paper's Figs. 5-8.

    Parameters
    ----------
    test : Pulse
        The held-out physical test (SI).
    predictions : mapping of str to pandas.DataFrame
        Panel label (e.g. ``'K = 2'``) -> validated prediction table, in panel order.
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        One axes per prediction on a shared deceleration axis, one legend below.
    """
    if not predictions:
        raise ValueError("expected at least one prediction")
    fig = _figure((3.6 * len(predictions) + 0.6, 4.0))
    axes = fig.subplots(1, len(predictions), sharey=True, squeeze=False)[0]
    for ax, (label, prediction) in zip(axes, predictions.items()):
        _draw_fold(ax, test, prediction)
        ax.set_title(label, fontsize="medium")
    for ax in axes[1:]:
        ax.set_ylabel("")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="lower center", ncol=4, frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    return fig


def _draw_fold(ax, test: Pulse | None, prediction: pd.DataFrame) -> None:
    t_ms = prediction["time_s"].to_numpy() / MS
    ax.fill_between(t_ms, prediction["decel_lo_g"], prediction["decel_hi_g"], color=COLORS["band"], alpha=0.35,
                    linewidth=0, label="95 % band")
    if test is not None:  # a condition nobody tested has no test to show
        keep = test.time <= T_END + 0.5 * test.dt
        ax.plot(test.time[keep] / MS, test.decel[keep] / G0, color=COLORS["test"], lw=1.4, label="test")
    ax.plot(t_ms, prediction["cae_decel_g"], color=COLORS["cae"], lw=1.2, ls="--", label="CAE")
    ax.plot(t_ms, prediction["decel_g"], color=COLORS["mean"], lw=1.6, label="corrected mean")
    ax.set_xlim(0, T_END / MS)
    ax.axhline(0, color="0.6", lw=0.6)
    ax.set_xlabel("time (ms)")
    ax.set_ylabel("deceleration (g)")
    ax.grid(alpha=0.3)


def iso_summary_figure(frame: pd.DataFrame, window: str = "0-60", score: str = "overall") -> Figure:
    """Grouped bars of the ISO score by held-out test and model, one panel per input mode.

    Parameters
    ----------
    frame : pandas.DataFrame
        A validated ISO table (see `crashfuse.reporting.tables.read_iso_table`).
    window : str
        The ``window_ms`` label to show.
    score : str
        The score column to show.

    Returns
    -------
    matplotlib.figure.Figure
        One row of bars per input mode present; bars CAE, K1, K2 ... per test; the legend gives
        each model's mean over the tests.
    """
    if score not in SCORES:
        raise InputError(f"expected a score in {SCORES}, got {score!r}", table_file(frame), "score")
    rows = frame[frame["window_ms"] == window]
    if rows.empty:
        windows = sorted(frame["window_ms"].unique(), key=window_bounds)
        raise InputError(f"expected a window_ms label of the table {windows}, got {window!r}", table_file(frame),
                         "window")
    modes = [m for m in ROW_INPUTS if (rows["inputs"] == m).any()]
    tests = sorted(rows["test_id"].unique(), key=natural_key)
    models = sorted(rows["model"].unique(), key=model_order)
    fig = _figure((max(6.4, 0.75 * len(tests) + 2.0), 2.8 * len(modes) + 0.4))
    axes = fig.subplots(len(modes), 1, squeeze=False, sharex=True)[:, 0]
    width = 0.8 / len(models)
    for ax, mode in zip(axes, modes):
        wide = table2(rows, mode, score)[window].unstack("model").reindex(index=tests, columns=models)
        for j, model in enumerate(models):
            values = wide[model].to_numpy(float)
            label = f"{model} (mean {np.nanmean(values):.3f})" if np.isfinite(values).any() else model
            ax.bar(np.arange(len(tests)) + (j - (len(models) - 1) / 2) * width, np.nan_to_num(values), width,
                   color=MODEL_COLORS[j % len(MODEL_COLORS)], label=label,
                   edgecolor="black" if model == BASELINE else "none", linewidth=0.5)
        ax.set_ylim(0, 1)
        ax.set_ylabel(f"ISO {score} ({window} ms)")
        ax.set_title(f"{mode} inputs", fontsize="medium")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False, fontsize="small")
    axes[-1].set_xticks(np.arange(len(tests)), tests)
    axes[-1].set_xlabel("held-out test")
    fig.tight_layout()
    return fig


def save_png(fig: Figure, path: str | os.PathLike) -> Path:
    """Save ``fig`` as a PNG atomically, without the Software metadata (no version or time stamp)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI, metadata={"Software": None})
    return path


def plot_fold(test: Pulse | None, prediction_csv: str | os.PathLike, path: str | os.PathLike,
              title: str | None = None) -> Path:
    """Read a prediction CSV and write its `fold_figure` as a PNG at ``path`` (``test`` None: a prediction at a
    condition nobody tested, CAE and corrected mean with its band)."""
    return save_png(fold_figure(test, read_prediction_csv(prediction_csv), title), path)


def plot_evaluation(result, out: str | os.PathLike, campaign) -> list[Path]:
    """Write every fold's `fold_figure` to ``<out>/<inputs>/K<k>/<test>/<test>.png``, beside its prediction CSV.

    Parameters
    ----------
    result : crashfuse.evaluation.loto.Evaluation
        The evaluation whose in-memory prediction tables are drawn.
    out : str or PathLike
        The evaluation folder (as given to :func:`crashfuse.evaluation.loto.evaluate`).
    campaign : crashfuse.io.campaign.Campaign
        The evaluated campaign: the held-out tests are drawn from first contact on.

    Returns
    -------
    list of Path
        The figures written, one per fold.
    """
    paths = []
    for (inputs, model, test_id), frame in result.predictions.items():
        test = campaign.pulses[test_id].after_contact()
        path = fold_folder(out, inputs, model, test_id) / f"{test_id}.png"
        title = f"{test_id}: {inputs} inputs, K = {model_tag(model)}".replace("+", " + ", 1)  # K1+auto: K = 1 + auto
        if model == AUTO:
            title = f"{test_id}: auto, chose {result.records[inputs, model, test_id].settings['chosen']}"
        paths.append(save_png(fold_figure(test, frame, title), path))
    return paths


def plot_panels(test: Pulse, prediction_csvs: Mapping[str, str | os.PathLike], path: str | os.PathLike,
                title: str | None = None) -> Path:
    """Read prediction CSVs (panel label -> file) and write their `panels_figure` as a PNG at ``path``."""
    frames = {label: read_prediction_csv(csv) for label, csv in prediction_csvs.items()}
    return save_png(panels_figure(test, frames, title), path)


def plot_iso_summary(iso_table: str | os.PathLike, path: str | os.PathLike, window: str = "0-60",
                     score: str = "overall") -> Path:
    """Read ``iso_table.csv`` (or the folder holding it) and write its `iso_summary_figure` as a PNG."""
    return save_png(iso_summary_figure(read_iso_table(iso_table), window, score), path)


def bias_map_figure(gap) -> Figure:
    """The loading-branch bias over displacement and impact speed, non-significant cells hatched.

    Parameters
    ----------
    gap : crashfuse.diagnosis.gap.GapMap

    Returns
    -------
    matplotlib.figure.Figure
        Mean bias (test minus CAE) in g on displacement (mm) x impact speed (mph), a diverging
        scale centred on 0 and clipped at the 99th percentile of ``|bias|``; non-significant
        cells (``map_significant`` False) hatched, cells beyond the crush the tests reach at that
        speed blank; each test a line at its speed up to its crush reach.
    """
    fig = _figure((7.2, 4.6))
    ax = fig.add_subplot()
    s_mm, v_mph = gap.s_grid / MM, gap.v0_grid / MPH
    mean_g = np.ma.masked_where(~gap.map_covered, gap.map_mean / G0)
    lim = float(np.percentile(np.abs(mean_g.compressed()), 99)) if mean_g.count() else 0.0
    lim = lim if lim > 0 else 1.0  # a few extreme edge cells must not wash out the map
    mesh = ax.pcolormesh(s_mm, v_mph, mean_g, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="nearest")
    quiet = (~gap.map_significant & gap.map_covered).astype(float)
    ax.contourf(s_mm, v_mph, quiet, levels=[0.5, 1.5], colors="none", hatches=["xx"])
    ax.contour(s_mm, v_mph, quiet, levels=[0.5], colors="0.3", linewidths=0.6)
    ax.scatter([t.profiles["loading"].x[-1] / MM for t in gap.tests], [t.v0 / MPH for t in gap.tests],
               color="black", s=14, zorder=3, label="tests (speed, crush reached)")
    for t in gap.tests:
        ax.plot([0, t.profiles["loading"].x[-1] / MM], [t.v0 / MPH] * 2, color="black", lw=0.5, alpha=0.5)
    fig.colorbar(mesh, ax=ax, label="bias, test - CAE (g)", extend="both")
    ax.set_xlabel("displacement s (mm)")
    ax.set_ylabel("impact speed (mph)")
    ax.set_title("loading-branch bias; hatched: not significant (95 % band or ISO inner corridor)",
                 fontsize="medium")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), frameon=False)
    fig.tight_layout()
    return fig


def gap_pulses_figure(gap, t_end: float = T_END) -> Figure:
    """Every test's pulse against its CAE pulse in time, its significant bias windows shaded.

    Parameters
    ----------
    gap : crashfuse.diagnosis.gap.GapMap
    t_end : float
        Time span shown, s.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per test (deceleration in g against time in ms); shading orange where the test
        decelerates significantly more than the CAE, blue where less (loading and unloading runs).
    """
    n = len(gap.tests)
    cols = min(n, 4)
    rows = -(-n // cols)
    fig = _figure((3.2 * cols + 0.4, 2.5 * rows + 0.6))
    axes = fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False).ravel()
    for ax, t in zip(axes, gap.tests):
        for _, lo, hi, sign in t.significant_windows():
            ax.axvspan(lo / MS, hi / MS, color=GAP_SHADES[sign], alpha=0.3, lw=0)
        keep, keep_cae = t.time <= t_end + 1e-12, t.cae_time <= t_end + 1e-12
        ax.plot(t.time[keep] / MS, t.decel[keep] / G0, color=COLORS["test"], lw=1.1, label="test")
        ax.plot(t.cae_time[keep_cae] / MS, t.cae_decel[keep_cae] / G0, color=COLORS["cae"], lw=1.0, ls="--",
                label="CAE")
        ax.set_title(f"{t.test_id}, {t.v0 / MPH:.1f} mph", fontsize="small")
        ax.set_xlim(0, t_end / MS)
        ax.grid(alpha=0.3)
    for ax in axes[n:]:
        ax.set_visible(False)
    for ax in axes[::cols]:
        ax.set_ylabel("deceleration (g)")
    for ax in axes[(rows - 1) * cols:]:
        ax.set_xlabel("time (ms)")
    handles = axes[0].get_legend_handles_labels()[0]
    shades = [Patch(color=GAP_SHADES[k], alpha=0.3, label=f"test {w} CAE (95 %)") for k, w in ((1, "above"),
                                                                                                (-1, "below"))]
    fig.legend(handles=[*handles, *shades], loc="lower center", ncol=4, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig


def _figure(size: tuple[float, float]) -> Figure:
    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    return fig


def effect_pulses_figure(campaign, diagnosis, t_end: float = T_END) -> Figure:
    """Every test of a gap diagnosis: measured, CAE and CAE + the chosen effects (held-out fits).

    Parameters
    ----------
    campaign : crashfuse.io.campaign.Campaign
    diagnosis : crashfuse.diagnosis.diagnose.Diagnosis
    """
    ids = diagnosis.case.test_ids
    cols = min(4, len(ids))
    rows = -(-len(ids) // cols)
    fig = _figure((3.2 * cols, 2.4 * rows))
    effects = " + ".join(diagnosis.verdict) or "no effect"
    for i, t in enumerate(ids):
        ax = fig.add_subplot(rows, cols, i + 1)
        test = campaign.pulses[t].after_contact()
        ax.plot(test.time / MS, test.decel / G0, color=COLORS["test"], lw=1.0, label="test")
        time = diagnosis.case.time / MS
        ax.plot(time, diagnosis.predictions["CAE"][i] / G0, color=COLORS["cae"], lw=1.0, label="CAE")
        ax.plot(time, diagnosis.predictions["CAE+effects"][i] / G0, color=COLORS["mean"], lw=1.0,
                label=f"CAE + {effects}")
        ax.set_xlim(0, t_end / MS)
        ax.set_title(t, fontsize=8)
        ax.tick_params(labelsize=7)
    fig.axes[0].legend(fontsize=6)
    fig.supxlabel("time since contact (ms)", fontsize=8)
    fig.supylabel("deceleration (g)", fontsize=8)
    fig.tight_layout()
    return fig
