"""Figures: what is drawn (units, span, band, bars), deterministic PNG bytes, atomic writes, bad input."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PolyCollection

from crashfuse import Pulse
from crashfuse.reporting import plots
from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.reporting.tables import read_iso_table

G = 9.80665  # standard gravity (CGPM 1901), m/s^2 per g, written here independently of crashfuse.units
SHARED = Path(__file__).resolve().parents[2] / "shared"
V10146 = SHARED / "data" / "nhtsa" / "v10146"
SCORES = ["overall", "corridor", "phase", "magnitude", "slope"]


def half_sine(v0: float = 15.0, peak_g: float = 30.0, length: float = 0.08, dt: float = 1e-4) -> Pulse:
    t = np.arange(int(0.15 / dt) + 1) * dt
    a = np.where(t <= length, peak_g * G * np.sin(np.pi * t / length), 0.0)
    return Pulse(time=t, decel=a, v0=v0, front_weight=900.0, rear_weight=700.0, run_id="T01")


def prediction_frame(test: Pulse, dt: float = 2e-4) -> pd.DataFrame:
    t = np.arange(0, 0.1 + dt / 2, dt)
    mean = np.interp(t, test.time, test.decel) / G * 0.95
    return pd.DataFrame({"time_s": t, "decel_g": mean, "decel_lo_g": mean - 1.5, "decel_hi_g": mean + 2.0,
                         "cae_decel_g": 0.8 * mean})


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """The chunks of a PNG, each checked against its CRC."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    out, i = [], 8
    while i < len(data):
        (n,) = struct.unpack(">I", data[i:i + 4])
        kind, body = data[i + 4:i + 8], data[i + 8:i + 8 + n]
        assert struct.unpack(">I", data[i + 8 + n:i + 12 + n])[0] == zlib.crc32(kind + body)
        out.append((kind, body))
        i += 12 + n
    return out


def test_fold_figure_draws_test_cae_mean_and_band_in_g_and_ms():
    test = half_sine()
    pred = prediction_frame(test)
    fig = plots.fold_figure(test, pred, title="T01, paper inputs, K = 2")
    (ax,) = fig.axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    x, y = lines["test"].get_data()
    assert x.max() == pytest.approx(100.0) and x.min() == 0.0  # cropped to the 0-100 ms span
    assert np.max(y) == pytest.approx(30.0, rel=1e-6)  # the half-sine peak, in g
    assert np.allclose(lines["CAE"].get_ydata(), 0.8 * pred["decel_g"])
    assert np.allclose(lines["corrected mean"].get_xdata(), pred["time_s"] * 1000.0)
    band = [c for c in ax.collections if isinstance(c, PolyCollection)]
    verts = band[0].get_paths()[0].vertices
    assert verts[:, 1].min() == pytest.approx(pred["decel_lo_g"].min()) and verts[:, 1].max() == pytest.approx(
        pred["decel_hi_g"].max())
    assert ax.get_xlim() == (0.0, 100.0) and "(g)" in ax.get_ylabel() and "(ms)" in ax.get_xlabel()
    assert {t.get_text() for t in ax.get_legend().get_texts()} == {"test", "CAE", "corrected mean", "95 % band"}


def test_panels_figure_shows_each_model_beside_the_others(tmp_path):
    test = half_sine()
    preds = {f"K = {k}": prediction_frame(test).assign(decel_g=lambda f, k=k: f["decel_g"] * k) for k in (1, 2, 3)}
    fig = plots.panels_figure(test, preds, title="T01, paper inputs")
    assert [ax.get_title() for ax in fig.axes] == list(preds)
    for ax, pred in zip(fig.axes, preds.values()):
        mean = next(line for line in ax.get_lines() if line.get_label() == "corrected mean")
        assert np.allclose(mean.get_ydata(), pred["decel_g"])
    assert fig.axes[0].get_ylim() == fig.axes[2].get_ylim()  # one deceleration scale for all panels
    paths = {}
    for k, pred in preds.items():
        paths[k] = tmp_path / f"{k[-1]}.csv"
        pred.to_csv(paths[k], index=False)
    out = plots.plot_panels(test, paths, tmp_path / "panels.png")
    assert png_chunks(out.read_bytes())[0][0] == b"IHDR"


@pytest.mark.skipif(not (V10146 / "v10146.093").exists(), reason="NHTSA test 10146 data absent")
def test_fold_figure_of_the_real_test_10146(tmp_path):
    from crashfuse.io.loading import load_pulses

    (test,) = load_pulses(V10146)
    pred = prediction_frame(test)
    path = tmp_path / "10146.png"
    csv = tmp_path / "pred.csv"
    pred.to_csv(csv, index=False)
    plots.plot_fold(test, csv, path, title="NHTSA 10146")
    assert png_chunks(path.read_bytes())[0][0] == b"IHDR"
    (ax,) = plots.fold_figure(test, pred).axes
    x, y = next(line for line in ax.get_lines() if line.get_label() == "test").get_data()
    keep = test.time <= 0.1 + test.dt / 2
    assert np.allclose(y, test.decel[keep] / G) and np.allclose(x, test.time[keep] * 1000.0)
    assert 20 < np.max(y) < 60  # a 56 km/h full-frontal pulse peaks at a few tens of g


def test_png_bytes_are_deterministic_and_carry_no_stamp(tmp_path):
    test = half_sine()
    csv = tmp_path / "pred.csv"
    prediction_frame(test).to_csv(csv, index=False)
    a = plots.plot_fold(test, csv, tmp_path / "a.png").read_bytes()
    b = plots.plot_fold(test, csv, tmp_path / "b.png").read_bytes()
    assert a == b
    kinds = [k for k, _ in png_chunks(a)]
    assert b"tIME" not in kinds and not any(b"Software" in body for k, body in png_chunks(a) if k == b"tEXt")


def test_a_failed_save_leaves_no_file(tmp_path, monkeypatch):
    fig = plots.fold_figure(half_sine(), prediction_frame(half_sine()))
    path = tmp_path / "out.png"
    path.write_bytes(b"old")

    def broken(target, **kwargs):
        Path(target).write_bytes(b"\x89PNG half")
        raise RuntimeError("disk full")

    monkeypatch.setattr(fig, "savefig", broken)
    with pytest.raises(RuntimeError):
        plots.save_png(fig, path)
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["out.png"]


def iso_table(tmp_path: Path) -> Path:
    rows = []
    for j, mode in enumerate(["paper", "state"]):
        for i, test in enumerate(["T10", "T2", "T1"]):
            for m, model in enumerate(["K3", "CAE", "K1", "K2"]):
                for w, window in enumerate(["0-20", "0-40", "0-60"]):
                    score = 0.1 + 0.2 * j + 0.05 * i + 0.01 * m + 0.001 * w
                    rows.append(dict(test_id=test, inputs=mode, model=model, window_ms=window,
                                     **{s: score for s in SCORES}))
    path = tmp_path / "iso_table.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_iso_summary_bars_are_the_table_scores(tmp_path):
    frame = read_iso_table(iso_table(tmp_path))
    fig = plots.iso_summary_figure(frame, window="0-40")
    assert [ax.get_title() for ax in fig.axes] == ["paper inputs", "state inputs"]
    assert [t.get_text() for t in fig.axes[-1].get_xticklabels()] == ["T1", "T2", "T10"]
    for j, ax in enumerate(fig.axes):
        labels = [c.get_label() for c in ax.containers]
        assert [label.split()[0] for label in labels] == ["CAE", "K1", "K2", "K3"]
        for container, model_index in zip(ax.containers, [1, 2, 3, 0]):
            heights = [bar.get_height() for bar in container]
            want = [0.1 + 0.2 * j + 0.05 * i + 0.01 * model_index + 0.001 for i in (2, 1, 0)]
            assert np.allclose(heights, want)
        mean_cae = np.mean([0.1 + 0.2 * j + 0.05 * i + 0.01 + 0.001 for i in range(3)])
        assert labels[0] == f"CAE (mean {mean_cae:.3f})"
    path = plots.plot_iso_summary(tmp_path, tmp_path / "summary.png")
    assert png_chunks(path.read_bytes())[0][0] == b"IHDR"
    with pytest.raises(InputError, match="window_ms"):
        plots.iso_summary_figure(frame, window="0-80")


@pytest.mark.parametrize("option, value", [("--window", "0-80"), ("--score", "bogus")])
def test_bad_summary_option_through_the_cli_names_the_table(tmp_path, capsys, option, value):
    table = iso_table(tmp_path)
    out = tmp_path / "summary.png"
    assert main(["plot", "summary", str(table), "--out", str(out), option, value]) == 2
    err = capsys.readouterr().err
    assert f"{table}: field '{option}'" in err and value in err
    assert not out.exists()


@pytest.mark.parametrize("edit, field", [
    (lambda f: f.drop(columns="decel_hi_g"), "decel_hi_g"),
    (lambda f: f.assign(decel_g=f["decel_g"].where(f.index != 3, np.nan)), "decel_g"),
    (lambda f: f.assign(cae_decel_g=f["cae_decel_g"].astype(object).where(f.index != 3, "x")), "cae_decel_g"),
    (lambda f: f.assign(time_s=f["time_s"][::-1].to_numpy()), "time_s"),
    (lambda f: f.assign(decel_lo_g=f["decel_hi_g"] + 1.0), "decel_lo_g"),
    (lambda f: f.iloc[:1], "time_s"),
])
def test_bad_prediction_csv_names_file_and_field(tmp_path, edit, field):
    path = tmp_path / "pred.csv"
    edit(prediction_frame(half_sine())).to_csv(path, index=False)
    with pytest.raises(InputError) as err:
        plots.plot_fold(half_sine(), path, tmp_path / "out.png")
    assert err.value.file == str(path) and err.value.field == field
    assert not (tmp_path / "out.png").exists()
