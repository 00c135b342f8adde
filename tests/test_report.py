"""Report tables against the paper's own Table 2, the fold JSON round trip, and bad input."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crashfuse.evaluation import records
from crashfuse.reporting import tables as report
from crashfuse.cli import main
from crashfuse.errors import InputError

SCORES = ["overall", "corridor", "phase", "magnitude", "slope"]
WINDOWS = ["0-20", "0-40", "0-60"]
# The paper's Table 2 (overall ISO score, windows 0-20, 0-40, 0-60 ms), typed from the paper.
PAPER_TABLE2 = {
    "3": {"CAE": (0.774, 0.768, 0.822), "K1": (0.863, 0.828, 0.822), "K2": (0.867, 0.839, 0.801),
          "K3": (0.868, 0.841, 0.805)},
    "4": {"CAE": (0.651, 0.658, 0.681), "K1": (0.745, 0.762, 0.730), "K2": (0.776, 0.772, 0.742),
          "K3": (0.801, 0.808, 0.750)},
    "5": {"CAE": (0.477, 0.565, 0.656), "K1": (0.722, 0.786, 0.743), "K2": (0.737, 0.764, 0.725),
          "K3": (0.770, 0.873, 0.754)},
    "10": {"CAE": (0.647, 0.617, 0.541), "K1": (0.945, 0.894, 0.875), "K2": (0.964, 0.919, 0.889),
           "K3": (0.965, 0.922, 0.904)},
}


def paper_frame(inputs: str = "paper") -> pd.DataFrame:
    """The paper's Table 2 as iso_table rows, listed in a scrambled order (sub-scores: the overall score)."""
    rows = [dict(test_id=t, inputs=inputs, model=m, window_ms=w, **{s: v for s in SCORES})
            for t, models in PAPER_TABLE2.items() for m, values in models.items() for w, v in zip(WINDOWS, values)]
    return pd.DataFrame(rows).sample(frac=1.0, random_state=3).reset_index(drop=True)


def write_csv(tmp_path: Path, frame: pd.DataFrame) -> Path:
    path = tmp_path / "iso_table.csv"
    frame.to_csv(path, index=False)
    return path


def test_markdown_reproduces_the_papers_table2(tmp_path):
    frame = report.read_iso_table(write_csv(tmp_path, paper_frame()))
    md = report.table2_markdown(frame, "paper")
    rows = [[c.strip().strip("*") for c in line.strip("|").split("|")] for line in md.splitlines()
            if line.startswith("|")][2:]
    assert len(rows) == 16
    test = None
    for cells in rows:
        test = cells[0] or test  # the test number is printed on its first row only
        assert tuple(float(c) for c in cells[2:]) == PAPER_TABLE2[test][cells[1]]
    assert [r[0] for r in rows if r[0]] == ["3", "4", "5", "10"]  # natural order, not "10" < "3"
    assert [r[1] for r in rows[:4]] == ["CAE", "K1", "K2", "K3"]
    assert "(0, 20) ms | (0, 40) ms | (0, 60) ms" in md
    # The best per test and window is bold; ties all bold (test 3, 0-60: CAE and K1 both 0.822).
    assert "| 3 | CAE | 0.774 | 0.768 | **0.822** |" in md
    assert "|  | K1 | 0.863 | 0.828 | **0.822** |" in md
    assert "|  | K3 | **0.965** | **0.922** | **0.904** |" in md


def test_latex_table_has_the_paper_shape_and_escapes_text():
    frame = paper_frame()
    frame["test_id"] = frame["test_id"].map(lambda t: f"T_{t}%")
    tex = report.table2_latex(frame, "paper")
    assert tex.count(r"\begin{tabular}{llrrr}") == 1 and tex.rstrip().endswith(r"\end{tabular}")
    body = [line for line in tex.splitlines() if line.endswith(r"\\")]
    assert len(body) == 2 + 16  # two header lines, then test x model
    assert r"\multirow{4}{*}{T\_10\%} & CAE & 0.647 & 0.617 & 0.541 \\" in tex
    assert r" & K3 & \textbf{0.965} & \textbf{0.922} & \textbf{0.904} \\" in tex
    assert tex.count(r"\midrule") == 4 and tex.count(r"\bottomrule") == 1


def test_summary_is_the_mean_over_tests():
    frame = pd.concat([paper_frame("paper"), paper_frame("state").assign(overall=0.5)], ignore_index=True)
    out = report.summary(frame)
    assert len(out) == 2 * 4 * 3 and list(out.columns[:4]) == ["inputs", "model", "window_ms", "n_tests"]
    assert list(out["model"][:4]) == ["CAE", "CAE", "CAE", "K1"] and list(out["window_ms"][:3]) == WINDOWS
    for (model, j) in [("CAE", 0), ("K3", 2)]:
        want = np.mean([PAPER_TABLE2[t][model][j] for t in PAPER_TABLE2])
        row = out[(out.inputs == "paper") & (out.model == model) & (out.window_ms == WINDOWS[j])]
        assert row["overall"].item() == pytest.approx(want, abs=1e-12) and row["n_tests"].item() == 4
    assert (out.loc[out.inputs == "state", "overall"] == 0.5).all()


def test_write_tables_writes_every_mode_atomically(tmp_path):
    frame = pd.concat([paper_frame("paper"), paper_frame("state")], ignore_index=True)
    csv = write_csv(tmp_path, frame)
    written = report.write_tables(tmp_path, tmp_path / "tables")
    names = sorted(p.name for p in written)
    assert names == ["summary.csv", "summary.md", "table2_paper.md", "table2_paper.tex", "table2_state.md",
                     "table2_state.tex"]
    assert sorted(p.name for p in (tmp_path / "tables").iterdir()) == names  # no temporary files left
    frame = report.read_iso_table(csv)
    assert (tmp_path / "tables" / "table2_state.tex").read_text() == report.table2_latex(frame, "state")
    back = pd.read_csv(tmp_path / "tables" / "summary.csv")
    assert np.allclose(back["overall"], report.summary(frame)["overall"], atol=1e-6)


@pytest.mark.parametrize("edit, field, expected", [
    (lambda f: f.drop(columns="slope"), "slope", "missing ['slope']"),
    (lambda f: f.assign(inputs="physics"), "inputs", "one of ['paper', 'state', 'auto']"),
    (lambda f: f.assign(model=f["model"].replace("K2", "GP2")), "model", "'GP2'"),
    (lambda f: f.assign(model=f["model"].replace("K2", "K0")), "model", "'K0'"),
    (lambda f: f.assign(window_ms=f["window_ms"].replace("0-40", "40-0")), "window_ms", "'40-0'"),
    (lambda f: f.assign(phase=f["phase"].astype(object).where(f.index != 5, "n/a")), "phase", "'n/a'"),
    (lambda f: f.assign(corridor=f["corridor"].where(f.index != 7, 1.5)), "corridor", "in [0, 1]"),
    (lambda f: f.assign(magnitude=f["magnitude"].where(f.index != 2, np.nan)), "magnitude", "in [0, 1]"),
    (lambda f: pd.concat([f, f.iloc[[4]]]), "test_id", "repeated"),
    (lambda f: f.assign(test_id=f["test_id"].where(f.index != 0, "")), "test_id", "non-empty"),
    (lambda f: f.iloc[:0], "test_id", "at least one row"),
])
def test_bad_iso_tables_name_file_and_field(tmp_path, edit, field, expected):
    path = write_csv(tmp_path, edit(paper_frame()))
    with pytest.raises(InputError) as err:
        report.read_iso_table(path)
    assert err.value.file == str(path) and err.value.field == field and expected in err.value.message


def test_missing_and_garbled_tables(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        report.read_iso_table(tmp_path)
    (tmp_path / "iso_table.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError) as err:
        report.read_iso_table(tmp_path)
    assert err.value.file == str(tmp_path / "iso_table.csv")


def fold_record(**changes) -> records.FoldRecord:
    fields = dict(
        test_id="T03", inputs="state", k=2, seed=11, campaign={"name": "paper", "hash": "0f" * 32},
        conditions={"v0_mps": 16.7 * 0.44704, "front_weight_kg": 2120.1 * 0.45359237,
                    "rear_weight_kg": 1600.2 * 0.45359237, "powertrain": "Type I", "drive": "FWD"},
        settings={"trend": "linear", "nugget": 1e-6, "n_restarts": 5, "use_companion": True, "grid": None},
        iso={w: dict(zip(SCORES, v)) for w, v in zip(WINDOWS, np.linspace(0.5, 0.9, 15).reshape(3, 5).tolist())},
        metrics={"coverage_95_0_60": 0.93, "log_marginal_likelihood_loading": -123.4},
        figures=["T03.png"], prediction="T03_prediction.csv")
    fields.update(changes)
    return records.FoldRecord(**fields)


def test_fold_json_round_trip_and_metric_names(tmp_path):
    record = fold_record()
    path = records.write_fold_json(tmp_path / "state" / "K2" / "T03.fold.json", record)
    assert records.read_fold_json(path) == record
    doc = json.loads(path.read_text())
    assert doc["schema"] == "crashfuse.fold/1"
    names = record.iso_metrics()
    assert len(names) == 15 and names["iso_slope_0_20"] == pytest.approx(0.5 + 4 * 0.4 / 14)
    assert all(re.fullmatch(r"iso_[a-z]+_0_[246]0", n) for n in names) and record.model == "K2"


@pytest.mark.parametrize("change, field", [
    (dict(inputs="both"), "inputs"),
    (dict(k=0), "k"),
    (dict(seed=1.5), "seed"),
    (dict(campaign={"name": "paper"}), "campaign.hash"),
    (dict(conditions={"v0_mps": 7.0, "powertrain": "Type I", "drive": "FWD"}), "conditions.front_weight_kg"),
    (dict(conditions={"v0_mps": "7", "front_weight_kg": 1.0, "rear_weight_kg": 1.0, "powertrain": "I",
                      "drive": "FWD"}), "conditions.v0_mps"),
    (dict(conditions={"v0_mps": 7.0, "front_weight_kg": 1.0, "rear_weight_kg": 1.0, "powertrain": 1,
                      "drive": "FWD"}), "conditions.powertrain"),
    (dict(settings={"kernel": [1, 2]}), "settings.kernel"),
    (dict(metrics={"coverage": float("nan")}), "metrics.coverage"),
    (dict(metrics={"iso_overall_0_60": 0.5}), "metrics"),
    (dict(iso={"0-60": {"overall": 0.5}}), "iso.0-60.corridor"),
    (dict(iso={"60": {s: 0.5 for s in SCORES}}), "iso"),
    (dict(figures="T03.png"), "figures"),
])
def test_bad_fold_records_name_the_field(tmp_path, change, field):
    path = tmp_path / "x.fold.json"
    with pytest.raises(InputError) as err:
        records.write_fold_json(path, fold_record(**change))
    assert err.value.field == field and err.value.file == str(path)
    assert not path.exists()


def test_read_fold_json_refuses_other_documents(tmp_path):
    path = tmp_path / "a.fold.json"
    path.write_text('{"schema": "something/2"}')
    with pytest.raises(InputError) as err:
        records.read_fold_json(path)
    assert err.value.field == "schema"
    path.write_text("{not json")
    with pytest.raises(InputError, match="expected JSON"):
        records.read_fold_json(path)
    with pytest.raises(ValueError, match="fold.json"):
        records.write_fold_json(tmp_path / "a.json", fold_record())


def _fold_table(path, test, k, cae=0.7, corrected=0.8):
    rows = [dict(test_id=test, inputs="state", model=m, window_ms=w, overall=s, corridor=s, phase=s,
                 magnitude=s, slope=s)
            for m, s in (("CAE", cae), (f"K{k}", corrected)) for w in ("0-20", "0-40", "0-60")]
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_aggregate_keeps_each_cae_row_once_and_sorts(tmp_path):
    paths = [_fold_table(tmp_path / f"{t}{k}.csv", t, k) for t in ("T10", "T2") for k in (1, 2)]
    frame = report.aggregate_iso_tables(paths, tmp_path / "iso_table.csv")
    assert len(frame) == 2 * 3 * 3  # per test: CAE, K1, K2 x 3 windows
    assert list(frame["test_id"].drop_duplicates()) == ["T2", "T10"]
    assert list(frame["model"].drop_duplicates()) == ["CAE", "K1", "K2"]
    assert report.read_iso_table(tmp_path / "iso_table.csv").shape[0] == 18


def test_aggregate_refuses_fold_tables_that_disagree(tmp_path):
    a = _fold_table(tmp_path / "a.csv", "T1", 1, cae=0.7)
    b = _fold_table(tmp_path / "b.csv", "T1", 2, cae=0.6)
    c = _fold_table(tmp_path / "c.csv", "T1", 3, cae=0.7)
    with pytest.raises(InputError, match="disagree") as err:
        report.aggregate_iso_tables([a, c, b], tmp_path / "iso_table.csv")
    assert (err.value.file, err.value.field) == (str(b), "overall")  # the odd one out, not the first file
    assert str(a) in err.value.message
    assert not (tmp_path / "iso_table.csv").exists()


def test_aggregate_validates_every_fold_table(tmp_path):
    a = _fold_table(tmp_path / "a.csv", "T1", 1)
    b = _fold_table(tmp_path / "b.csv", "T1", 2)
    b.write_text(b.read_text().replace(",K2,", ",K0,"))  # not a model label read_iso_table accepts
    with pytest.raises(InputError) as err:
        report.aggregate_iso_tables([a, b], tmp_path / "iso_table.csv")
    assert (err.value.file, err.value.field) == (str(b), "model")
    assert not (tmp_path / "iso_table.csv").exists()


def test_bad_score_through_the_cli_names_the_table_and_option(tmp_path, capsys):
    path = write_csv(tmp_path, paper_frame())
    assert main(["report", str(path), "--out", str(tmp_path / "out"), "--score", "bogus"]) == 2
    err = capsys.readouterr().err
    assert f"{path}: field '--score'" in err and "bogus" in err
    assert not (tmp_path / "out").exists()
