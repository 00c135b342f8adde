"""Presets and test matrices of the second world: who carries which effect, at which conditions.

As in the first world, the test side carries every catalogue effect and a *withheld* effect is
absent from the CAE (every other effect is on both sides with the same parameters):

* ``paper``: withheld = [strain_rate, powertrain];
* ``withheld`` with ``withhold=[EFFECT, ...]``: those effects (one, or a pair, ...); ``["none"]``
  withholds nothing (the control: tests differ from CAE only by the measurement chain).

Test matrices: ``table1`` is the paper's Table 1 (shared with the first world); ``wide`` spreads
11 tests over 10-37 mph with Table 1's three configurations, so that the slow tests' rebound falls
inside the 0-60 ms scoring window and the fastest lies beyond the paper's 35.2 mph; ``wide`` with
another number of tests spaces them evenly over the same range (a test library of any size).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.units import LB, MPH
from crashfuse.world.multibody.effects import params_at_strength
from crashfuse.world.presets import TABLE1, Design, table1_tests, withheld_effects

MATRICES = ("table1", "wide")
N_CAE = 400
WIDE_SPEEDS_MPH = (10.0, 11.5, 13.0, 16.0, 19.0, 22.0, 25.0, 28.0, 31.0, 34.0, 37.0)
# Table 1's configurations in turn, each with its mean Table 1 axle masses.
WIDE_CONFIGS = (("Type I", "FWD"), ("Type II", "AWD"), ("Type I", "AWD"))


def resolve(preset: str | None = None, withhold=None, strength: str = "realistic",
            overrides: dict | None = None) -> Design:
    """Resolve the command-line choices into a :class:`Design` (as the first world's
    :func:`crashfuse.world.presets.resolve`, with this world's laws' parameters)."""
    preset, withheld = withheld_effects(preset, withhold)
    params = {**params_at_strength(strength, withheld), **(overrides or {})}
    return Design(preset, withheld, strength, params)


def wide_tests(n_tests: int | None = None) -> pd.DataFrame:
    """The wide matrix: 11 tests over 10-37 mph (or ``n_tests`` evenly spaced there), same columns as
    :func:`matrix_tests`."""
    speeds = WIDE_SPEEDS_MPH if n_tests in (None, len(WIDE_SPEEDS_MPH)) else np.linspace(10.0, 37.0, n_tests)
    rows = []
    for i, mph in enumerate(speeds):
        pt, drive = WIDE_CONFIGS[i % len(WIDE_CONFIGS)]
        same = TABLE1[(TABLE1["powertrain"] == pt) & (TABLE1["drive"] == drive)]
        rows.append((f"T{i + 1:02d}", mph * MPH, same["front_lb"].mean() * LB, same["rear_lb"].mean() * LB, pt, drive))
    return pd.DataFrame(rows, columns=["run_id", "v0_mps", "front_weight_kg", "rear_weight_kg", "powertrain", "drive"])


def matrix_tests(name: str, n_tests: int | None = None) -> pd.DataFrame:
    """Tests of a named matrix in SI: run_id, v0_mps, front_weight_kg, rear_weight_kg, powertrain, drive.

    ``n_tests`` (``wide`` only, at least 2): that many tests evenly spaced over 10-37 mph.
    """
    if n_tests is not None and (name != "wide" or isinstance(n_tests, bool)
                                or not isinstance(n_tests, (int, np.integer)) or n_tests < 2):
        raise InputError(f"expected a number of tests >= 2 with the wide matrix, got {n_tests!r} with {name!r}",
                         field="n_tests")
    if name == "table1":
        return table1_tests()
    if name == "wide":
        return wide_tests(n_tests)
    raise InputError(f"unknown test matrix {name!r}; expected one of {', '.join(MATRICES)}", field="matrix")


def configuration(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Boolean arrays (Type II powertrain, AWD) of a conditions frame."""
    return (frame["powertrain"] == "Type II").to_numpy(), (frame["drive"] == "AWD").to_numpy()
