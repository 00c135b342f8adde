"""The benchmark scripts run: their functions on a tiny campaign (figures not checked, shapes are)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from crashfuse.io.campaign_write import write_campaign
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
KEEP = ["T02", "T05", "T08"]


def _script(name: str):
    """Import ``benchmarks/<name>.py`` by path (benchmarks are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tiny_campaign(tmp_path_factory):
    """Three tests with their companions and 16 CAE runs of the `paper` world, written to a folder."""
    full = build(resolve("paper"), seed=0, n_cae=16)[0]
    runs = KEEP + [full.companion(t).run_id for t in KEEP] + [r for r in full.cae if r.startswith("C0")]
    campaign = full.subset(runs)
    return write_campaign(campaign, tmp_path_factory.mktemp("tiny") / "campaign")


def test_bench_thinning_runs_on_a_tiny_campaign(tiny_campaign, capsys):
    bench = _script("bench_thinning")
    assert bench.grid_for(np.array([10, 100]), 30) == 20  # min(20, 10) + min(20, 100)
    assert bench.grid_for(np.array([10, 100]), 10**6) == 100  # beyond the data: no thinning
    bench.main([str(tiny_campaign), "--holdout", "T05", "--folds", "T05", "--ks", "1", "--targets", "60", "120",
                "--grids", "20", "full", "--samples", "5", "--full-cap", "50", "--jobs", "1", "--json"])
    result = json.loads(capsys.readouterr().out)
    cost, thinning = result["cost"], result["thinning"]
    assert [r["n_grid"] for r in cost][2:] == ["full", "full-exact"]  # the tiny full set fits exactly
    assert abs(cost[0]["points"] - 60) <= 4 and abs(cost[1]["points"] - 120) <= 4  # 2 tests x 2 branches
    sod, exact = cost[2], cost[3]
    assert sod["points"] == exact["points"] > cost[1]["points"]
    assert sod["cond_max"] == 50 < sod["n_max"] == exact["cond_max"]
    assert sod["exact_gib"] == pytest.approx(16 * sod["n_max"] ** 2 / 2**30)
    assert all(r["fit_s"] > 0 and r["peak_mib"] > 0 for r in cost)
    by_grid = {r["n_grid"]: r for r in thinning}
    assert set(by_grid) == {20, "full", "full-exact"}
    assert by_grid["full"]["rel_data"] == 0 < by_grid[20]["rel_data"] < 1
    assert all(0 <= r["iso"] <= 1 and np.isfinite(r["rel_fit"]) and r["rel_held"] >= 0 for r in thinning)
    assert result["cae_iso"]["T05"] is not None


def test_bench_campaign_read_runs_on_a_tiny_campaign(tiny_campaign, capsys):
    bench = _script("bench_campaign_read")
    assert bench.main([str(tiny_campaign), "--repeat", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["runs"] == 22 and out["tests"] == 3
    # timings only: their order is the benchmark's finding, not a property a test may rely on
    assert min(out["full_s"], out["lazy_open_s"], out["lazy_tests_s"]) > 0
    assert out["ratio"] == pytest.approx(out["full_s"] / out["lazy_tests_s"])


def test_bench_effect_fit_runs_on_a_tiny_campaign(tiny_campaign, capsys):
    _script("bench_effect_fit").main([str(tiny_campaign), "--holdout", "T05", "--samples", "30",
                                      "--candidates", "mass", "--sizes", "4", "8"])
    out = capsys.readouterr().out
    assert out.count("identical: True") == 2  # shared tables, and a Jacobian's columns following the rollout
    assert "4 samples" in out and "8 samples" in out and "per rollout +" in out
    assert "one fold's `auto` effect choice (without T05, 2 tests)" in out and "batched rollouts" in out
    assert "Jacobians of" in out
