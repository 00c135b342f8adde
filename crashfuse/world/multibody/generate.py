"""Generate a campaign folder of the second world and its ``world.json`` answer key.

The campaign: the tests of a matrix (``table1`` or ``wide``, T01..T11) from the test simulator
(CFC 60, 10 kHz, 0-100 ms), each with a companion CAE run at its condition (CT01.., named in
``cae_run_id``), and ``n_cae`` CAE runs over the shared seeded Latin hypercube (C0001..). CAE
pulses are raw history output (``cfc = raw`` in conditions.csv, 10 kHz, -10 to 120 ms); the
campaign reader filters them to CFC 60. Written through :func:`crashfuse.io.campaign_write.write_campaign`.
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
from crashfuse.world.multibody import WORLD_NAME, WORLD_VERSION
from crashfuse.world.multibody.presets import N_CAE, Design, configuration, matrix_tests
from crashfuse.world.multibody.simulate import (CAE_DURATION, CAE_LEAD, CAE_RATE, DURATION, MEASUREMENT, RAW_RATE,
                                                TEST_RATE, Runs, simulate_cae, simulate_tests)
from crashfuse.world.multibody.structure import VEHICLE
from crashfuse.world.presets import cae_design

WORLD_JSON = "world.json"


def runs_of(frame: pd.DataFrame) -> Runs:
    """Simulator conditions from a conditions frame (SI columns, powertrain and drive labels)."""
    type2, awd = configuration(frame)
    return Runs(v0=frame["v0_mps"].to_numpy(float), front=frame["front_weight_kg"].to_numpy(float),
                rear=frame["rear_weight_kg"].to_numpy(float), type2=type2, awd=awd)


def all_params(design: Design) -> dict:
    """Every parameter the simulators use: vehicle, effects and measurement (SI)."""
    return {**VEHICLE, **design.params, **MEASUREMENT}


def build(design: Design, seed: int = 0, n_cae: int = N_CAE, matrix: str = "table1",
          n_tests: int | None = None) -> tuple[Campaign, dict]:
    """Simulate the campaign in memory.

    Parameters
    ----------
    design : Design
        Resolved preset (:func:`crashfuse.world.multibody.presets.resolve`).
    seed : int
        Seeds the CAE Latin hypercube and the tests' noise and offsets.
    n_cae : int
        Latin-hypercube CAE runs besides the companions.
    matrix : {"table1", "wide"}
        Test matrix.
    n_tests : int, optional
        With ``wide``: that many tests evenly spaced over 10-37 mph (default: the matrix's 11).

    Returns
    -------
    campaign : Campaign
    world : dict
        The answer key written as ``world.json``.
    """
    seed = _check_seed(seed)
    if isinstance(n_cae, bool) or not isinstance(n_cae, (int, np.integer)) or n_cae < 0:
        raise InputError(f"expected a count >= 0, got {n_cae!r}", field="n_cae")
    params = all_params(design)
    tests = matrix_tests(matrix, n_tests)
    companions = tests.assign(run_id=["C" + r for r in tests["run_id"]])
    tests["cae_run_id"] = companions["run_id"]
    cae = pd.concat([companions, cae_design(n_cae, seed)], ignore_index=True)
    # Tests' generators are keyed apart from the Latin hypercube's seed stream.
    rngs = [np.random.default_rng([seed, 2, i]) for i in range(len(tests))]
    test_decel = simulate_tests(runs_of(tests), design.test_effects, params, rngs)
    test_time = np.arange(test_decel.shape[1]) / TEST_RATE
    cae_time, cae_decel = simulate_cae(runs_of(cae), design.cae_effects, params)
    pulses = _pulses(tests, test_time, test_decel, "test", 60) + _pulses(cae, cae_time, cae_decel, "cae", None)
    world = world_key(design, seed, params, matrix, len(tests), len(cae))
    return Campaign.from_pulses(pulses), world


def _pulses(frame: pd.DataFrame, time: np.ndarray, decel: np.ndarray, source: str, cfc) -> list[Pulse]:
    """Pulse objects for the rows of ``frame``; ``cfc`` None marks raw (unfiltered) pulses."""
    out = []
    for row, a in zip(frame.to_dict("records"), decel):
        meta = {"powertrain": row["powertrain"], "drive": row["drive"], "cae_run_id": row.get("cae_run_id"),
                "cfc": cfc}
        out.append(Pulse(time, a, row["v0_mps"], row["front_weight_kg"], row["rear_weight_kg"],
                         run_id=row["run_id"], source=source, meta=meta))
    return out


def world_key(design: Design, seed: int, params: dict, matrix: str, n_tests: int, n_cae: int) -> dict:
    """The answer key: world, version, seed, preset, matrix, withheld effects, every parameter per side."""
    def group(prefix):
        return {k.split(".", 1)[1]: params[k] for k in sorted(params) if k.split(".", 1)[0] == prefix}

    return {
        "world": WORLD_NAME,
        "world_version": WORLD_VERSION,
        "seed": seed,
        "preset": design.preset,
        "strength": design.strength,
        "matrix": matrix,
        "withheld": list(design.withheld),
        "effects": {"test": {e: group(e) for e in design.test_effects},
                    "cae": {e: group(e) for e in design.cae_effects}},
        "vehicle": {name: group(name) for name in ("structure", "front", "engine")},
        "measurement": {**group("measurement"), "applies_to": "test", "raw_rate_hz": RAW_RATE, "cfc": 60},
        "sampling": {"test_rate_hz": TEST_RATE, "test_duration_s": DURATION, "cae_rate_hz": CAE_RATE,
                     "cae_from_s": -CAE_LEAD, "cae_to_s": CAE_DURATION, "cae_cfc": "raw", "t0": "first contact"},
        "runs": {"tests": n_tests, "cae": n_cae},
        "units": "SI (N, m, s, kg); parameter names as in crashfuse.world.multibody",
    }


def generate(out: str | os.PathLike, design: Design, seed: int = 0, n_cae: int = N_CAE,
             matrix: str = "table1", n_tests: int | None = None) -> Path:
    """Write the campaign folder ``out`` (mph, lb, g) with ``world.json``, atomically.

    :func:`crashfuse.io.campaign_write.write_campaign` refuses a non-empty folder and writes the answer
    key in the same temporary folder, so a campaign never appears without it.
    """
    campaign, world = build(design, seed, n_cae, matrix, n_tests)
    key = json.dumps(world, indent=2, sort_keys=True, allow_nan=False) + "\n"
    return write_campaign(campaign, out, extra_files={WORLD_JSON: key})


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"expected an integer seed >= 0, got {seed!r}", field="seed")
    return int(seed)
