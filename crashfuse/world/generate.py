"""Generate a synthetic campaign folder and its ``world.json`` answer key.

The campaign is the paper's shape: the 11 tests of Table 1 (T01..T11) from the physical-test
simulator, each with a companion CAE run at the same condition (CT01..CT11, named in
``cae_run_id``), and ``n_cae`` CAE runs over a seeded Latin hypercube (C0001..). Pulses are CFC 60,
100 ms at 12.5 kHz from contact. ``world.json`` records every parameter used and which effects each
side carries; only validation harnesses may read it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.io.campaign_write import write_campaign
from crashfuse.signals.pulse import Pulse
from crashfuse.world import WORLD_VERSION
from crashfuse.world.presets import N_CAE, Design, cae_design, table1_tests
from crashfuse.world.simulate import DURATION, MEASUREMENT, OUT_RATE, RAW_RATE, Runs, simulate
from crashfuse.world.vehicle import VEHICLE

WORLD_JSON = "world.json"


def runs_of(frame: pd.DataFrame) -> Runs:
    """Simulator conditions from a conditions frame (SI columns, powertrain and drive labels)."""
    return Runs(v0=frame["v0_mps"].to_numpy(float), front=frame["front_weight_kg"].to_numpy(float),
                rear=frame["rear_weight_kg"].to_numpy(float), type2=(frame["powertrain"] == "Type II").to_numpy(),
                awd=(frame["drive"] == "AWD").to_numpy())


def all_params(design: Design) -> dict:
    """Every parameter the simulators use: vehicle, effects and measurement (SI)."""
    return {**VEHICLE, **design.params, **MEASUREMENT}


def build(design: Design, seed: int = 0, n_cae: int = N_CAE) -> tuple[Campaign, dict]:
    """Simulate the campaign in memory.

    Parameters
    ----------
    design : Design
        Resolved preset (see :func:`crashfuse.world.presets.resolve`).
    seed : int
        Seeds the CAE Latin hypercube and the tests' accelerometer noise.
    n_cae : int
        Number of Latin-hypercube CAE runs (the paper has 1009).

    Returns
    -------
    campaign : Campaign
    world : dict
        The answer key written as ``world.json``.
    """
    seed = _check_seed(seed)
    if not (isinstance(n_cae, (int, np.integer)) and n_cae >= 0):
        raise InputError(f"expected a count >= 0, got {n_cae!r}", field="n_cae")
    params = all_params(design)
    tests = table1_tests()
    companions = tests.assign(run_id=["C" + r for r in tests["run_id"]])
    tests["cae_run_id"] = companions["run_id"]
    cae = pd.concat([companions, cae_design(n_cae, seed)], ignore_index=True)
    rngs = [np.random.default_rng([seed, i]) for i in range(len(tests))]
    test_decel = simulate(runs_of(tests), design.test_effects, params, rngs)
    cae_decel = simulate(runs_of(cae), design.cae_effects, params)
    pulses = _pulses(tests, test_decel, "test") + _pulses(cae, cae_decel, "cae")
    campaign = Campaign.from_pulses(pulses)
    return campaign, world_key(design, seed, params, len(tests), len(cae))


def _pulses(frame: pd.DataFrame, decel: np.ndarray, source: str) -> list[Pulse]:
    """Pulse objects (CFC 60, t = 0 at contact) for the rows of ``frame`` and ``decel`` (n, m) m/s^2."""
    time = np.arange(decel.shape[1]) / OUT_RATE
    out = []
    for row, a in zip(frame.to_dict("records"), decel):
        meta = {"powertrain": row["powertrain"], "drive": row["drive"], "cae_run_id": row.get("cae_run_id"),
                "cfc": 60}
        out.append(Pulse(time, a, row["v0_mps"], row["front_weight_kg"], row["rear_weight_kg"],
                         run_id=row["run_id"], source=source, meta=meta))
    return out


def world_key(design: Design, seed: int, params: dict, n_tests: int, n_cae: int) -> dict:
    """The answer key: version, seed, preset, withheld effects, every parameter per side."""
    def effects_of(names):
        return {e: {k.split(".", 1)[1]: params[k] for k in sorted(params) if k.startswith(e + ".")} for e in names}

    def group(prefix):
        return {k.split(".", 1)[1]: params[k] for k in sorted(params) if k.startswith(prefix + ".")}

    return {
        "world_version": WORLD_VERSION,
        "seed": seed,
        "preset": design.preset,
        "strength": design.strength,
        "withheld": list(design.withheld),
        "effects": {"test": effects_of(design.test_effects), "cae": effects_of(design.cae_effects)},
        "vehicle": group("vehicle"),
        "measurement": {**group("measurement"), "applies_to": "test", "raw_rate_hz": RAW_RATE, "cfc": 60},
        "sampling": {"rate_hz": OUT_RATE, "duration_s": DURATION, "t0": "first contact"},
        "runs": {"tests": n_tests, "cae": n_cae},
        "units": "SI (N, m, s, kg); parameter names as in crashfuse.world.effects",
    }


def generate(out: str | os.PathLike, design: Design, seed: int = 0, n_cae: int = N_CAE) -> Path:
    """Write the campaign folder ``out`` (mph, lb, g) with ``world.json`` beside conditions.csv.

    The folder, ``world.json`` included, is written atomically by
    :func:`crashfuse.io.campaign_write.write_campaign` (which refuses a non-empty folder): a campaign never
    appears without its answer key.
    """
    campaign, world = build(design, seed, n_cae)
    key = json.dumps(world, indent=2, sort_keys=True, allow_nan=False) + "\n"
    return write_campaign(campaign, out, extra_files={WORLD_JSON: key})


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"expected an integer seed >= 0, got {seed!r}", field="seed")
    return int(seed)
