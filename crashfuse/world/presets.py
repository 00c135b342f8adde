"""Campaign designs and presets: the paper's Table 1 tests, the CAE Latin hypercube, who carries what.

Every catalogue effect is present on the test side. A *withheld* effect is absent on the CAE side;
every other effect is on both sides with the same parameters. So

* ``paper``: withheld = [strain_rate, powertrain] (the paper's situation: a CAE model with a rigid
  powertrain and rate-independent material);
* ``withheld`` with ``withhold=[EFFECT, ...]``: those effects (one, or a pair, ...); with
  ``withhold="none"`` nothing is withheld (the control: tests differ from CAE only by measurement
  realism).

``strength`` ("realistic" or "subtle") sets the magnitude of the withheld effects; shared effects
are always realistic, so a campaign differs from the control only in what it withholds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
from scipy.stats import qmc

from crashfuse.catalogue import EFFECTS, check_effect
from crashfuse.errors import InputError
from crashfuse.units import LB, MPH
from crashfuse.world.effects import params_at_strength

PRESETS = ("paper", "withheld")
PAPER_WITHHELD = ("strain_rate", "powertrain")
N_CAE = 1009

# Table 1 of the paper, exactly as tabulated: speed mph, front and rear weight lb, P/T, drive.
TABLE1 = pd.DataFrame(
    [
        (8.1, 1994.7, 1400.0, "Type I", "AWD"),
        (12.1, 2163.7, 1592.9, "Type II", "AWD"),
        (16.7, 2120.1, 1600.2, "Type I", "FWD"),
        (22.0, 2237.4, 1765.3, "Type II", "AWD"),
        (24.9, 2100.4, 1554.6, "Type I", "FWD"),
        (25.2, 2155.4, 1707.1, "Type II", "AWD"),
        (25.2, 2058.9, 1507.9, "Type I", "FWD"),
        (35.2, 2179.3, 1745.5, "Type II", "AWD"),
        (35.1, 2107.7, 1556.6, "Type I", "FWD"),
        (35.2, 2166.9, 1737.2, "Type II", "AWD"),
        (35.2, 2168.9, 1694.7, "Type II", "AWD"),
    ],
    columns=["speed_mph", "front_lb", "rear_lb", "powertrain", "drive"],
)

# CAE design space: ~5-40 mph and Table 1's weight ranges widened by about 5 %.
CAE_SPEED_MPH = (5.0, 40.0)
CAE_FRONT_LB = (1890.0, 2350.0)
CAE_REAR_LB = (1330.0, 1860.0)
# Powertrain/drive configurations of the CAE runs and the share of the design each gets
# (Table 1 has Type I FWD, Type I AWD and Type II AWD).
CAE_CONFIGS = (("Type I", "FWD", 0.4), ("Type I", "AWD", 0.1), ("Type II", "AWD", 0.5))


@dataclasses.dataclass(frozen=True)
class Design:
    """A preset resolved into who carries which effect with which parameters.

    Attributes
    ----------
    preset : str
    withheld : tuple of str
        Effects the tests carry and the CAE does not.
    strength : str
    params : dict
        Every parameter ``effect.param`` of the world's effect laws in SI (the generator adds ``vehicle.*`` and
        ``measurement.*``).
    """

    preset: str
    withheld: tuple
    strength: str
    params: dict

    @property
    def test_effects(self) -> tuple:
        """Effects present in the physical tests (all of the catalogue)."""
        return EFFECTS

    @property
    def cae_effects(self) -> tuple:
        """Effects present in the CAE runs."""
        return tuple(e for e in EFFECTS if e not in self.withheld)


def resolve(preset: str | None = None, withhold=None, strength: str = "realistic",
            overrides: dict | None = None) -> Design:
    """Resolve the command-line choices into a :class:`Design`.

    Parameters
    ----------
    preset : {"paper", "withheld"} or None
        None means ``withheld`` if ``withhold`` is given, else ``paper``.
    withhold : str or sequence of str, optional
        Catalogue effects withheld from the CAE (distinct: one, a pair, ...), or ``"none"`` alone
        (``withheld`` preset only).
    strength : {"realistic", "subtle"}
        Magnitude of the withheld effects (shared effects stay realistic).
    overrides : dict, optional
        ``effect.param`` values replacing the named strength's (see
        :func:`crashfuse.world.effects.parse_overrides`).

    Raises
    ------
    InputError
        Unknown preset, effect or strength, or a combination that does not fit.
    """
    preset, withheld = withheld_effects(preset, withhold)
    params = {**params_at_strength(strength, withheld), **(overrides or {})}
    return Design(preset, withheld, strength, params)


def withheld_effects(preset: str | None, withhold) -> tuple[str, tuple]:
    """The preset and the effects it withholds from the CAE, checked (both worlds' presets).

    ``withhold`` is a catalogue effect, a sequence of distinct ones, ``"none"`` alone or None (the
    ``paper`` preset's :data:`PAPER_WITHHELD`). Raises :class:`InputError` naming ``preset`` or
    ``withhold``."""
    names = [withhold] if isinstance(withhold, str) else list(withhold or [])
    if preset is None:
        preset = "withheld" if names else "paper"
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}", field="preset")
    if preset == "paper":
        if names:
            raise InputError("the paper preset withholds strain_rate and powertrain; use the withheld preset "
                             "to withhold other effects", field="withhold")
        return preset, PAPER_WITHHELD
    if not names:
        raise InputError(f"the withheld preset needs effects to withhold ({'|'.join(EFFECTS)}|none)", field="withhold")
    if "none" in names:
        if len(names) > 1:
            raise InputError(f"'none' withholds nothing and stands alone, got {' '.join(names)}", field="withhold")
        return preset, ()
    withheld = tuple(check_effect(n, field="withhold") for n in names)
    if len(set(withheld)) < len(withheld):
        raise InputError(f"expected distinct effects, got {' '.join(names)}", field="withhold")
    return preset, withheld


def table1_tests() -> pd.DataFrame:
    """The 11 tests in SI: run_id T01..T11, v0_mps, front_weight_kg, rear_weight_kg, powertrain, drive."""
    return pd.DataFrame({
        "run_id": [f"T{i + 1:02d}" for i in range(len(TABLE1))],
        "v0_mps": TABLE1["speed_mph"] * MPH,
        "front_weight_kg": TABLE1["front_lb"] * LB,
        "rear_weight_kg": TABLE1["rear_lb"] * LB,
        "powertrain": TABLE1["powertrain"],
        "drive": TABLE1["drive"],
    })


def cae_design(n: int = N_CAE, seed: int = 0) -> pd.DataFrame:
    """A seeded Latin hypercube of CAE conditions, run ids C0001.., same columns as :func:`table1_tests`.

    The fourth LHS dimension picks the powertrain/drive configuration (shares ``CAE_CONFIGS``).
    """
    u = qmc.LatinHypercube(d=4, rng=np.random.default_rng(seed)).random(n)
    lo, hi = np.array([CAE_SPEED_MPH, CAE_FRONT_LB, CAE_REAR_LB]).T
    x = lo + u[:, :3] * (hi - lo)
    edges = np.cumsum([c[2] for c in CAE_CONFIGS])
    config = np.searchsorted(edges, u[:, 3], side="right").clip(max=len(CAE_CONFIGS) - 1)
    return pd.DataFrame({
        "run_id": [f"C{i + 1:04d}" for i in range(n)],
        "v0_mps": x[:, 0] * MPH,
        "front_weight_kg": x[:, 1] * LB,
        "rear_weight_kg": x[:, 2] * LB,
        "powertrain": [CAE_CONFIGS[c][0] for c in config],
        "drive": [CAE_CONFIGS[c][1] for c in config],
    })
