"""Bijective projection (paper Eq. 11-15): bias data from tests and their CAE curves, per branch.

For one test and the CAE curve at its condition, on one branch (loading in ``x = s``,
unloading in ``x = u = s_max - s``, see :mod:`crashfuse.signals.domain`):

* scenario 1 - test points inside the CAE branch's range get the CAE interpolated there:
  ``bias_i = a_test(x_i) - a_cae(x_i)``;
* scenario 2 - CAE points inside the test branch's range get the test interpolated there:
  ``bias_j = a_test(x_j) - a_cae(x_j)``;

and the bias data are the union, sorted by ``x``. Both scenarios stay inside the overlap of the
two branches, so nothing is ever extrapolated: whichever side reaches further, its extra reach
gives no bias data. (The paper's Eq. 13 writes ``x_d`` for the displacement ``s_d``.) Every
point carries the TEST's velocity there (interpolated on the test branch), the extra input of
the ``state`` mode.

The CAE curve of a test is its companion run (``cae_run_id``) or, where there is none or when
asked, the CAE surrogate's curve at the test's condition (:class:`crashfuse.method.surrogate.CAECurve`
either way). After its separation (``u > u_end``) the CAE unloading deceleration is known to be
0, so the CAE unloading branch covers every ``u`` there; a test still in contact there gives bias
data equal to its own deceleration.

Each test's branch is thinned to ``n_grid`` points evenly spaced in ``x`` (bias and velocity
interpolated linearly on the union) so that an exact GP stays affordable; the cost is measured
in ``docs/method-projection-surrogate.md``. Everything is SI (m, m/s, kg, m/s^2).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Protocol, Sequence

import numpy as np

from crashfuse.signals.domain import displacement_branches
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.signals.pulse import Pulse
from crashfuse.method.surrogate import CATEGORIES, CAECurve, CAESurrogate
from crashfuse.units import G0

INPUTS = ("paper", "state")
BRANCHES = ("loading", "unloading")
TARGETS = ("absolute", "relative")
# Relative bias: divided by the CAE deceleration, floored so the near-zero CAE decel at contact
# and after separation does not blow it up (2 g: below the lowest plateau of a frontal pulse).
SCALE_FLOOR = 2.0 * G0
# Input columns (SI units in the names): branch coordinate, velocity, impact condition.
X_COL, V_COL, V0_COL, WF_COL, WR_COL = "x_m", "v_mps", "v0_mps", "front_weight_kg", "rear_weight_kg"
# The state mode's velocity as sign(v) sqrt(|v|) (sqrt(m/s)): a concave rate coordinate, as rate
# hardening laws are (Cowper-Symonds: a power 1/q, q ~ 4-5, of the rate).
SQRT_V_COL = "v_sqrt"
VELOCITY = {"linear": V_COL, "sqrt": SQRT_V_COL}
# The CAE deceleration where the bias is measured (g): the structural stage the crush is in, and the
# force an additive effect (e.g. damping) is a fraction of in a relative bias.
CAE_COL = "cae_decel_g"
CAE_DECEL = ("none", "unloading", "both")  # the branches with the CAE_COL input


class Curve(Protocol):
    """Anything with a strictly increasing coordinate ``x`` (m) and a ``decel`` (m/s^2) on it."""

    x: np.ndarray
    decel: np.ndarray


@dataclasses.dataclass(frozen=True)
class _Samples:
    """A CAE branch as plain arrays: coordinate x (m, strictly increasing), decel (m/s^2)."""

    x: np.ndarray
    decel: np.ndarray


def project_branch(test_branch, cae_branch: Curve) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 11-15 on one branch pair: the union of both scenarios inside their overlap.

    Parameters
    ----------
    test_branch : Branch
        The test's branch (``x``, ``decel``, ``velocity``; ``x`` strictly increasing, m).
    cae_branch : Branch or any object with ``x`` and ``decel``
        The CAE branch on the same coordinate.

    Returns
    -------
    x : ndarray, shape (n,)
        Branch coordinates in m, sorted, unique, within both branches' ranges.
    v : ndarray, shape (n,)
        The test's velocity at ``x`` in m/s.
    bias : ndarray, shape (n,)
        ``a_test(x) - a_cae(x)`` in m/s^2. All three are empty if the branches do not overlap.
    """
    tx, ta, tv = (np.asarray(a, dtype=float) for a in (test_branch.x, test_branch.decel, test_branch.velocity))
    cx, ca = np.asarray(cae_branch.x, dtype=float), np.asarray(cae_branch.decel, dtype=float)
    lo, hi = max(tx[0], cx[0]), min(tx[-1], cx[-1])
    x1 = tx[(tx >= lo) & (tx <= hi)]  # scenario 1: test points inside the CAE range
    x2 = cx[(cx >= lo) & (cx <= hi)]  # scenario 2: CAE points inside the test range
    x = np.unique(np.concatenate([x1, x2]))
    bias = np.interp(x, tx, ta) - np.interp(x, cx, ca)
    return x, np.interp(x, tx, tv), bias


def thin(x: np.ndarray, v: np.ndarray, bias: np.ndarray, n_grid: int | None):
    """Resample projected data to ``n_grid`` points evenly spaced in ``x`` (linear interpolation).

    Parameters
    ----------
    x, v, bias : ndarray, shape (n,)
        From :func:`project_branch` (``x`` sorted).
    n_grid : int or None
        Points to keep; None, or ``n <= n_grid``, keeps the data as they are.

    Returns
    -------
    x, v, bias : ndarray, shape (min(n, n_grid),)
    """
    if n_grid is None or x.size <= n_grid:
        return x, v, bias
    grid = np.linspace(x[0], x[-1], int(n_grid))
    return grid, np.interp(grid, x, v), np.interp(grid, x, bias)


@dataclasses.dataclass(frozen=True)
class BranchData:
    """Bias training data of one branch.

    Attributes
    ----------
    X : ndarray, shape (n, p)
        Inputs in SI, columns named by ``columns``.
    y : ndarray, shape (n,)
        Bias ``a_test - a_cae`` in m/s^2 (target ``absolute``), or that divided by
        :func:`bias_scale` of ``a_cae`` (``relative``, dimensionless).
    groups : ndarray of str, shape (n,)
        The test run_id each row came from.
    columns : tuple of str, length p
        ``x_m`` (s on loading, u on unloading), ``v_mps`` (``state`` mode only), ``v0_mps``,
        ``front_weight_kg``, ``rear_weight_kg``, then one-hot ``powertrain=<level>`` /
        ``drive=<level>`` columns with ``extra_inputs``, then ``cae_decel_g`` with ``cae_decel``.
    scale : ndarray, shape (n,)
        m/s^2 per unit of ``y``: 1 (``absolute``), :func:`bias_scale` of ``a_cae`` (``relative``).
    """

    X: np.ndarray
    y: np.ndarray
    groups: np.ndarray
    columns: tuple[str, ...]
    scale: np.ndarray


@dataclasses.dataclass(frozen=True)
class BiasData:
    """Bias training data per branch, from one fold's training tests.

    Attributes
    ----------
    loading, unloading : BranchData
    inputs : {"paper", "state"}
    target : {"absolute", "relative"}
    categories : dict of str to list of str
        Levels behind the one-hot columns (the first level of each is the dropped baseline).
    missing : dict of str to str
        ``"<test_id>/<branch>"`` -> why that test gave no data on that branch (e.g. it never
        stopped, or its CAE curve has no unloading branch).
    """

    loading: BranchData
    unloading: BranchData
    inputs: str
    categories: dict[str, list[str]]
    missing: dict[str, str]
    target: str = "absolute"

    def branch(self, name: str) -> BranchData:
        """The data of branch ``name`` ('loading' or 'unloading')."""
        if name not in BRANCHES:
            raise InputError(f"expected a branch in {BRANCHES}, got {name!r}", field="branch")
        return getattr(self, name)


def bias_data(campaign: Campaign, test_ids: Sequence[str], inputs: str = "paper", extra_inputs: bool = False,
              n_grid: int | None = 200, surrogate: CAESurrogate | None = None, use_companion: bool = True,
              cae_curves: Mapping[str, CAECurve] | None = None, target: str = "absolute",
              weights: bool = True, velocity: str = "linear", cae_decel: str = "none") -> BiasData:
    """Bias training data from the given tests (a fold's training tests only: no leakage).

    Parameters
    ----------
    campaign : Campaign
    test_ids : sequence of str
        Tests to learn from.
    inputs : {"paper", "state"}
        ``paper``: x = [x_branch, v0, w_f, w_r]; ``state``: x = [x_branch, v, v0, w_f, w_r].
    extra_inputs : bool
        Append one-hot powertrain and drive (levels taken from the whole campaign, first dropped).
    n_grid : int or None
        Points per test per branch after thinning (None: the full projected union).
    surrogate : CAESurrogate, optional
        Fitted surrogate: gives the CAE curve of tests without a companion (or of every test
        with ``use_companion=False``), and the unloading branch of companions that never stop.
    use_companion : bool
        Use the companion CAE run where a test names one.
    cae_curves : mapping of str to CAECurve, optional
        Explicit CAE curves by test run_id; they take precedence over both sources above.
    target : {"absolute", "relative"}
        ``absolute``: y = a_test - a_cae (m/s^2); ``relative``: y = (a_test - a_cae) /
        :func:`bias_scale` (a_cae), a fractional force error, which a rate effect makes nearly
        independent of speed (docs/method-projection-surrogate.md).
    weights : bool
        Include the axle masses as inputs (within a campaign of a few tests they are confounded
        with v0 and the powertrain).
    velocity : {"linear", "sqrt"}
        The state mode's velocity column: ``v_mps``, or ``v_sqrt`` = sign(v) sqrt(|v|).
    cae_decel : {"none", "unloading", "both"}
        The branches whose inputs include the CAE curve's deceleration at each point (``cae_decel_g``, in g).

    Returns
    -------
    BiasData

    Raises
    ------
    InputError
        Unknown ``inputs``, a run that is not a test, or a test with no CAE curve (no companion
        and no surrogate).
    """
    if inputs not in INPUTS:
        raise InputError(f"expected one of {INPUTS}, got {inputs!r}", field="inputs")
    if target not in TARGETS:
        raise InputError(f"expected one of {TARGETS}, got {target!r}", field="target")
    if cae_decel not in CAE_DECEL:
        raise InputError(f"expected one of {CAE_DECEL}, got {cae_decel!r}", field="cae_decel")
    if len(test_ids) == 0:
        raise InputError("expected at least one training test, got none", campaign.root, "test_ids")
    if n_grid is not None and not (isinstance(n_grid, (int, np.integer)) and n_grid >= 2):
        raise InputError(f"expected None or an integer >= 2 points per branch, got {n_grid!r}", field="n_grid")
    categories = _categories(campaign) if extra_inputs else {}
    columns = {b: bias_columns(inputs, categories, weights, velocity, cae_decel in (b, "both")) for b in BRANCHES}
    parts = {b: [] for b in BRANCHES}
    missing = {}
    for test_id in test_ids:
        test = training_test(campaign, test_id)
        curve = cae_curve(campaign, test, surrogate, use_companion, cae_curves or {})
        for name, rows in _test_rows(test, curve, n_grid, missing, target).items():
            x, v, bias, scale, a_cae = rows
            X = bias_inputs(columns[name], x, v, test.v0, test.front_weight, test.rear_weight,
                            test.meta.get("powertrain"), test.meta.get("drive"), a_cae)
            parts[name].append((X, bias, np.full(x.size, test_id, dtype=object), scale))
    data = {b: _stack(parts[b], columns[b]) for b in BRANCHES}
    return BiasData(data["loading"], data["unloading"], inputs, categories, missing, target)


def column_velocity(column: str, values) -> np.ndarray:
    """Velocity in m/s from a state velocity column's values (``v_mps`` or ``v_sqrt``)."""
    values = np.asarray(values, dtype=float)
    return values if column == V_COL else np.sign(values) * values**2


def nominal_time(columns: Sequence[str], X) -> np.ndarray:
    """Time since contact (s) of loading-branch ``state`` inputs, ``2 s / (v0 + v)``.

    Exact at constant deceleration; it follows the slowing car where ``s / v0`` would not.

    Parameters
    ----------
    columns : sequence of str
        The inputs' column names: ``x_m``, a velocity column and ``v0_mps`` among them.
    X : array_like, shape (m, len(columns))

    Returns
    -------
    ndarray, shape (m,)
    """
    X = np.asarray(X, dtype=float)
    vcol = next((c for c in columns if c in VELOCITY.values()), None)
    if vcol is None or X_COL not in columns or V0_COL not in columns:
        raise InputError(f"the time since contact needs {X_COL}, a velocity and {V0_COL} among the bias inputs, "
                         f"got {tuple(columns)}", field="inputs")
    col = list(columns).index
    speed = X[:, col(V0_COL)] + column_velocity(vcol, X[:, col(vcol)])
    return 2.0 * X[:, col(X_COL)] / np.maximum(speed, np.finfo(float).tiny)


def bias_scale(a_cae) -> np.ndarray:
    """What a relative bias multiplies: the CAE deceleration floored at ``SCALE_FLOOR`` (m/s^2).

    Parameters
    ----------
    a_cae : array_like, shape (n,)
        CAE deceleration in m/s^2.

    Returns
    -------
    ndarray, shape (n,)
    """
    return np.maximum(np.asarray(a_cae, dtype=float), SCALE_FLOOR)


def bias_columns(inputs: str, categories: Mapping[str, Sequence[str]] | None = None,
                 weights: bool = True, velocity: str = "linear", cae_decel: bool = False) -> tuple[str, ...]:
    """Input column names for ``inputs`` ('paper' | 'state'), one-hot ``categories``, the axle
    masses, the state mode's ``velocity`` coordinate ('linear' | 'sqrt') and the CAE deceleration."""
    if inputs not in INPUTS:
        raise InputError(f"expected one of {INPUTS}, got {inputs!r}", field="inputs")
    if velocity not in VELOCITY:
        raise InputError(f"expected one of {tuple(VELOCITY)}, got {velocity!r}", field="velocity")
    base = (X_COL, VELOCITY[velocity]) if inputs == "state" else (X_COL,)
    one_hot = tuple(f"{c}={lv}" for c, levels in (categories or {}).items() for lv in levels[1:])
    return (*base, V0_COL, *((WF_COL, WR_COL) if weights else ()), *one_hot,
            *((CAE_COL,) if cae_decel else ()))


def is_label(column: str) -> bool:
    """Whether a :func:`bias_columns` name is a one-hot label (``powertrain=<level>``, ``drive=<level>``)."""
    name, sep, _ = column.partition("=")
    return bool(sep) and name in CATEGORIES


def bias_inputs(columns: Sequence[str], x, v, v0: float, front_weight: float, rear_weight: float,
                powertrain: str | None = None, drive: str | None = None, a_cae=None) -> np.ndarray:
    """Bias-model inputs in ``columns`` order, for training rows or a rollout state.

    Parameters
    ----------
    columns : sequence of str
        From :func:`bias_columns` (or ``BranchData.columns``).
    x : array_like, shape (m,)
        Branch coordinate in m (s on loading, u on unloading).
    v : array_like, shape (m,) or None
        Velocity in m/s (needed for a ``v_mps`` column).
    v0, front_weight, rear_weight : float
        Condition in m/s and kg.
    powertrain, drive : str, optional
        Needed for one-hot columns.
    a_cae : array_like, shape (m,), optional
        The CAE deceleration at ``x`` in m/s^2, needed for a ``cae_decel_g`` column.

    Returns
    -------
    ndarray, shape (m, len(columns))
    """
    x = np.asarray(x, dtype=float)
    labels = {"powertrain": powertrain, "drive": drive}
    out = np.empty((x.size, len(columns)))
    for j, col in enumerate(columns):
        if col == X_COL:
            out[:, j] = x
        elif col in (V_COL, SQRT_V_COL):
            if v is None:
                raise InputError("the state inputs need the velocity", field=col)
            vv = np.broadcast_to(np.asarray(v, dtype=float), x.shape)
            out[:, j] = vv if col == V_COL else np.sign(vv) * np.sqrt(np.abs(vv))
        elif col == CAE_COL:
            if a_cae is None:
                raise InputError("the bias inputs include the CAE deceleration; expected it", field=col)
            out[:, j] = np.broadcast_to(np.asarray(a_cae, dtype=float), x.shape) / G0
        elif col in (V0_COL, WF_COL, WR_COL):
            out[:, j] = {V0_COL: v0, WF_COL: front_weight, WR_COL: rear_weight}[col]
        else:
            name, _, level = col.partition("=")
            if name not in labels or labels[name] is None:
                raise InputError(f"the bias inputs include one-hot {name}; expected a {name} label", field=name)
            out[:, j] = float(str(labels[name]) == level)
    return out


# ------------------------------------------------------------------------------- helpers
def _categories(campaign: Campaign) -> dict[str, list[str]]:
    """Levels of powertrain and drive over the whole campaign (inputs, not outcomes: no leakage)."""
    return {c: sorted({str(v) for v in campaign.conditions[c]}) for c in CATEGORIES}


def training_test(campaign: Campaign, test_id: str) -> Pulse:
    """The pulse of test ``test_id``; InputError if the campaign has no such run or it is not a test."""
    pulse = campaign.pulses.get(test_id)
    if pulse is None:
        raise InputError(f"no run {test_id!r} in the campaign", campaign.root, "test_ids")
    if pulse.source != "test":
        raise InputError(f"run {test_id!r} is a {pulse.source} run; bias data come from tests", campaign.root,
                         "test_ids")
    return pulse


def cae_curve(campaign: Campaign, test: Pulse, surrogate, use_companion: bool = True, explicit=()) -> CAECurve:
    """The CAE curve a test is compared with: explicit, companion (if allowed), or surrogate.

    A companion that does not reach separation in its record borrows the surrogate's unloading
    branch when a surrogate is given (:meth:`CAECurve.from_pulse`).
    """
    if test.run_id in explicit:
        return explicit[test.run_id]
    companion = campaign.companion(test.run_id) if use_companion else None
    stand_in = None
    if surrogate is not None:
        stand_in = surrogate.curve(test.v0, test.front_weight, test.rear_weight, test.meta.get("powertrain"),
                                   test.meta.get("drive"))
    if companion is not None:
        return CAECurve.from_pulse(companion, unloading_from=stand_in)
    if stand_in is None:
        why = "names no companion CAE run (cae_run_id)" if use_companion else "use_companion is off"
        raise InputError(f"test {test.run_id} {why} and no CAE surrogate was given; fit a CAESurrogate on the "
                         f"campaign's CAE runs and pass it as surrogate=", campaign.root, "cae_run_id")
    return stand_in


def _test_rows(test: Pulse, curve: CAECurve, n_grid, missing: dict, target: str = "absolute") -> dict[str, tuple]:
    """Projected and thinned (x, v, y, scale, a_cae) per branch for one test; records branches with no data."""
    br = displacement_branches(test)
    cae = {"loading": _Samples(curve.s, curve.a_loading)}
    if br.unloading is None:
        missing[f"{test.run_id}/unloading"] = "the test never reaches zero velocity in its record"
    elif curve.u is None:
        missing[f"{test.run_id}/unloading"] = f"its CAE curve ({curve.run_id}) has no unloading branch"
    else:
        cae["unloading"] = _cae_unloading(curve, br.unloading.x[-1])
    out = {}
    for name, side in cae.items():
        rows = project_branch(getattr(br, name), side)
        if rows[0].size < 2:
            missing[f"{test.run_id}/{name}"] = "the test and CAE branches do not overlap"
            continue
        x, v, bias = thin(*rows, n_grid)
        a_cae = np.interp(x, side.x, side.decel)
        scale = bias_scale(a_cae) if target == "relative" else np.ones(x.size)
        out[name] = (x, v, bias / scale, scale, a_cae)
    return out


def _cae_unloading(curve: CAECurve, reach: float) -> _Samples:
    """The CAE unloading branch, extended with decel 0 up to ``reach`` (m) after its separation."""
    if reach <= curve.u_end:
        return _Samples(curve.u, curve.a_unloading)
    return _Samples(np.append(curve.u, reach), np.append(curve.unloading(curve.u), 0.0))


def _stack(parts: list, columns: tuple[str, ...]) -> BranchData:
    if not parts:
        return BranchData(np.empty((0, len(columns))), np.empty(0), np.empty(0, dtype=object), columns, np.empty(0))
    X, y, g, scale = (np.concatenate(p) for p in zip(*parts))
    return BranchData(X, y, g, columns, scale)
