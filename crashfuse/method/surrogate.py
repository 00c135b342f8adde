"""CAE surrogate G_a: the CAE deceleration vs displacement at a new impact condition.

A CAE run is represented by its two branches in the displacement domain
(:func:`crashfuse.signals.domain.displacement_branches`):

* loading, ``a(s)`` on a fixed ABSOLUTE displacement grid ``0 .. s_top`` (the furthest any
  training run reached). Absolute, not ``xi = s / s_max``: a frontal structure's deceleration is a
  force-crush characteristic, so features (the plateau, the stiff rise when the engine bay stacks
  up) stay at the same ``s`` across speeds and a few principal components describe all runs;
  and a run that never stops inside the record (on the ``paper`` campaign, 164 of 1020 CAE runs
  between about 8 and 10 m/s) has an unknown ``s_max``, so it could not be normalised at all.
  Each run is observed up to its own furthest displacement; the rest of the grid is missing and
  filled by iterative low-rank (truncated SVD) imputation before the PCA.
* unloading, ``a(u)`` with ``u = s_max - s`` on a normalised grid ``w = u / u_end``, where
  ``u_end`` is the elastic spring-back up to separation (the deceleration first falls to
  ``SEPARATION`` of its value at maximum crush). Only runs whose unloading reaches separation
  inside the record enter this part of the fit; the others are missing there.

Curves are reduced by PCA and the component scores (plus ``log u_end``) are regressed on the
standardised conditions (v0, front and rear axle mass, and one-hot powertrain / drive where they
vary) with :class:`crashfuse.gp.kriging.KrigingGP` (linear GLS trend, anisotropic Gaussian correlation,
MLE). A predicted curve's maximum crush follows from the energy balance
``int_0^s_max a(s) ds = v0^2 / 2`` on the predicted curve itself, so it is consistent with any
rollout along it. Everything is SI: s, u in m, speeds in m/s, masses in kg, decel in m/s^2.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from typing import Iterable

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils import check_random_state
from sklearn.utils.validation import check_is_fitted

from crashfuse.gp.kriging import SEED_MAX, KrigingGP
from crashfuse.gp.threads import one_blas_thread
from crashfuse.signals.domain import Branches, displacement_branches
from crashfuse.signals.dynamics import Trajectory, rollout
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.signals.pulse import Pulse

SEPARATION = 0.02  # unloading ends where the decel first falls to 2 % of its value at maximum crush
CATEGORIES = ("powertrain", "drive")


@dataclasses.dataclass(frozen=True, eq=False)
class CAECurve:
    """CAE deceleration along the loading and unloading branches at one condition.

    Attributes
    ----------
    s : ndarray, shape (k,)
        Loading-branch displacements in m, strictly increasing from 0.
    a_loading : ndarray, shape (k,)
        Deceleration at ``s`` in m/s^2.
    u : ndarray, shape (j,) or None
        Unloading coordinates ``u = s_max - s`` in m, strictly increasing from 0 to ``u_end``
        (where the decel is 0); None if unknown (a run that never stops, no stand-in given).
    a_unloading : ndarray, shape (j,) or None
        Deceleration at ``u`` in m/s^2.
    s_max : float
        Maximum crush in m at this condition (from the run, or the energy balance).
    u_end : float or None
        Elastic spring-back in m: beyond it the vehicle has separated and the decel is 0.
    v0 : float
        Impact speed in m/s.
    run_id : str
        The CAE run (``from_pulse``) or ``"surrogate"``.
    unloading_origin : str
        ``run`` (the run's own, to separation), ``continued`` (the run's own to the record's end,
        then its last stiffness down to 0), ``joined`` (the run's own to the record's end, then
        ``unloading_from``'s), ``stand-in`` (from ``unloading_from``), ``surrogate`` or ``none``.
    """

    s: np.ndarray
    a_loading: np.ndarray
    u: np.ndarray | None
    a_unloading: np.ndarray | None
    s_max: float
    u_end: float | None
    v0: float
    run_id: str = "surrogate"
    unloading_origin: str = "surrogate"

    @classmethod
    def from_pulse(cls, pulse: Pulse, unloading_from: "CAECurve | None" = None) -> "CAECurve":
        """The curve of one CAE run, taken directly from its branches (``use_companion=True``).

        The unloading branch is, in order of preference: the run's own, if it reaches separation
        inside the record; else, if the run stopped, its own as far as its record goes, continued beyond
        by ``unloading_from``'s scaled to meet it (:func:`_joined_unloading`) or - without one, or where
        it separates first - with its last stiffness down to 0 (:func:`_continued_unloading`); else
        ``unloading_from``'s whole (a run that never stops); else none (``unloading_origin`` says which).
        A stopped run's own spring-back is never replaced: the surrogate's, taken whole, carried its bias
        against the run into the tests' bias (docs/decisions.md, section 85).

        Parameters
        ----------
        pulse : Pulse
            A CAE run (decel in m/s^2).
        unloading_from : CAECurve, optional
            Stand-in unloading branch, e.g. the surrogate's curve at the same condition.

        Returns
        -------
        CAECurve

        Raises
        ------
        InputError
            If the run never stops and its loading branch, continued with its last stiffness,
            cannot absorb ``v0^2 / 2`` (no maximum crush; names the run and its file).
        """
        br = displacement_branches(pulse)
        load = br.loading
        s_max = br.s_max if br.stopped else _energy_stop(load.x, load.decel, pulse.v0, f"CAE run {pulse.run_id}",
                                                             pulse.where)
        unload = (*_unloading_to_separation(br), "run") if br.stopped and _separation(br) is not None else None
        stand_in = unloading_from if unloading_from is not None and unloading_from.u is not None else None
        if unload is None and br.stopped:
            own = br.unloading.x, br.unloading.decel
            joined = _joined_unloading(*own, stand_in) if stand_in is not None else None
            unload = joined or _continued_unloading(*own)
        if unload is None and stand_in is not None:
            unload = stand_in.u, stand_in.a_unloading, "stand-in"
        u, a_u, origin = unload if unload is not None else (None, None, "none")
        return cls(load.x, load.decel, u, a_u, s_max, None if u is None else float(u[-1]), pulse.v0,
                   pulse.run_id, origin)

    def loading(self, s) -> np.ndarray:
        """Loading-branch deceleration (m/s^2) at displacements ``s`` (m), any shape.

        Beyond the last known displacement the curve continues with its last stiffness
        (slope of the final 5 % of the branch), clipped at 0; :meth:`extrapolated` flags it.
        """
        s = np.asarray(s, dtype=float)
        inside = np.interp(s, self.s, self.a_loading)
        beyond = np.maximum(self.a_loading[-1] + self.end_stiffness * (s - self.s[-1]), 0.0)
        return np.where(s > self.s[-1], beyond, inside)

    def extrapolated(self, s) -> np.ndarray:
        """True where ``s`` (m) lies beyond the loading data (the last-stiffness continuation)."""
        return np.asarray(s, dtype=float) > self.s[-1]

    def unloading(self, u) -> np.ndarray:
        """Unloading-branch deceleration (m/s^2) at ``u = s_max - s`` (m), any shape.

        0 beyond ``u_end`` (separated: the barrier cannot pull).

        Raises
        ------
        InputError
            If this curve has no unloading branch (a CAE run that never stopped, no stand-in).
        """
        if self.u is None:
            raise InputError("this CAE run never reaches zero velocity in its record, so it has no unloading "
                             "branch; pass unloading_from= (e.g. the surrogate's curve) to CAECurve.from_pulse",
                             field=self.run_id)
        u = np.asarray(u, dtype=float)
        return np.where(u > self.u_end, 0.0, np.interp(u, self.u, self.a_unloading))

    def decel(self, x, loading) -> np.ndarray:
        """Deceleration (m/s^2) at branch coordinates ``x`` (m): ``s`` where ``loading``, else ``u``.

        Parameters
        ----------
        x : ndarray, shape (m,)
        loading : ndarray of bool, shape (m,)
        """
        x = np.asarray(x, dtype=float)
        a = self.loading(np.where(loading, x, 0.0))
        if np.all(loading):
            return a
        return np.where(loading, a, self.unloading(np.where(loading, 0.0, x)))

    def rollout(self, dt: float, n_steps: int) -> Trajectory:
        """The zero-bias pulse of this curve (:func:`crashfuse.signals.dynamics.rollout` from ``v0``)."""
        return rollout(lambda st: self.decel(st.x, st.loading), self.v0, dt, n_steps)

    @functools.cached_property
    def end_stiffness(self) -> float:
        """Slope (m/s^2 per m) of the loading branch's last 5 %: its continuation beyond the data."""
        return _end_slope(self.s, self.a_loading)


class CAESurrogate(BaseEstimator):
    """PCA + kriging surrogate of CAE loading and unloading curves over impact conditions.

    Parameters
    ----------
    n_grid : int
        Points of the absolute loading grid ``0 .. s_top``.
    n_unload_grid : int
        Points of the normalised unloading grid ``w = u / u_end`` in [0, 1].
    n_components : int
        Principal components kept for the loading curves (at most; fewer if the data have fewer).
    n_unload_components : int
        Principal components kept for the unloading curves.
    categorical : {"auto", True, False}
        One-hot powertrain and drive as further inputs: "auto" uses those that vary in the data.
    impute_iter : int
        Iterations of the low-rank imputation of the loading grid beyond each run's reach.
    n_restarts : int
        Likelihood restarts of each KrigingGP beyond its fixed start. 0: on the ``paper``
        campaign one restart gives the same held-out ISO (mean 0.9915, min 0.9666) at about
        twice the fit time (docs/decisions.md, section 13).
    max_fit_points : int or None
        Runs (a seeded subset) in each KrigingGP's likelihood search; all runs are conditioned on.
    random_state : int, RandomState or None
        Seeds the GP restarts and fit subsets.

    Attributes
    ----------
    s_grid_ : ndarray, shape (n_grid,)
        Loading grid in m.
    w_grid_ : ndarray, shape (n_unload_grid,)
        Normalised unloading grid.
    load_mean_, load_components_ : ndarray, shape (n_grid,) and (r, n_grid)
        PCA of the (imputed) loading curves, m/s^2.
    unload_mean_, unload_components_ : ndarray, shape (n_unload_grid,) and (q, n_unload_grid)
        PCA of the complete unloading curves, m/s^2.
    load_gps_, unload_gps_ : list of KrigingGP
        One per component score; ``unload_gps_[-1]`` predicts ``log u_end``.
    categories_ : dict of str to list of str
        Levels one-hot encoded per categorical column used.
    run_ids_ : list of str
        The CAE runs fitted; ``n_unloading_`` of them had an unloading branch reaching separation.
    campaign_hash_ : str or None
        :meth:`Campaign.content_hash` of the campaign fitted on; None if fitted from pulses.
    campaign_source_ : str or None
        :attr:`Campaign.source` of the campaign fitted on (the digest of its folder's bytes); None if
        it was built in memory.
    fit_time_ : float
        Wall time of ``fit`` in s.
    """

    def __init__(self, n_grid=200, n_unload_grid=50, n_components=10, n_unload_components=6,
                 categorical="auto", impute_iter=30, n_restarts=0, max_fit_points=300, random_state=None):
        self.n_grid = n_grid
        self.n_unload_grid = n_unload_grid
        self.n_components = n_components
        self.n_unload_components = n_unload_components
        self.categorical = categorical
        self.impute_iter = impute_iter
        self.n_restarts = n_restarts
        self.max_fit_points = max_fit_points
        self.random_state = random_state

    @one_blas_thread  # the imputation's products: the same bits on any thread count
    def fit(self, runs: Campaign | Iterable[Pulse]) -> "CAESurrogate":
        """Learn the surrogate from CAE runs.

        Parameters
        ----------
        runs : Campaign or iterable of Pulse
            A campaign (its CAE runs are used) or CAE pulses with ``meta['powertrain']`` and
            ``meta['drive']``.

        Returns
        -------
        self

        Raises
        ------
        InputError
            Fewer CAE runs than the model needs, or no run with a complete unloading branch.
        """
        t0 = time.perf_counter()
        pulses = _cae_pulses(runs)
        rng = check_random_state(self.random_state)
        self.categories_ = self._choose_categories(pulses)
        X = self._features(pulses)
        branches = [displacement_branches(p) for p in pulses]
        self._fit_loading(X, branches, rng)
        self._fit_unloading(X, branches, rng)
        self.run_ids_ = [p.run_id for p in pulses]
        self.campaign_hash_ = runs.content_hash() if isinstance(runs, Campaign) else None
        self.campaign_source_ = runs.source if isinstance(runs, Campaign) else None
        self.fit_time_ = time.perf_counter() - t0
        return self

    def curve(self, v0: float, front_weight: float, rear_weight: float, powertrain: str | None = None,
              drive: str | None = None) -> CAECurve:
        """Predicted CAE curve at one condition.

        Parameters
        ----------
        v0 : float
            Impact speed in m/s.
        front_weight, rear_weight : float
            Axle masses in kg.
        powertrain, drive : str, optional
            Needed when the surrogate was fitted with them as inputs (``categories_``).

        Returns
        -------
        CAECurve
            Loading on ``s_grid_`` (continued by the last stiffness beyond ``s_grid_[-1]``),
            unloading on ``w_grid_ * u_end``, ``s_max`` from the energy balance.

        Raises
        ------
        InputError
            On a bad condition, or a predicted curve that cannot absorb ``v0^2 / 2`` (field ``v0``).
        """
        check_is_fitted(self)
        x = self._features_one(v0, front_weight, rear_weight, {"powertrain": powertrain, "drive": drive})
        scores = np.array([gp.predict(x)[0] for gp in self.load_gps_])
        a_load = self.load_mean_ + scores @ self.load_components_
        u_scores = np.array([gp.predict(x)[0] for gp in self.unload_gps_])
        a_unload = np.maximum(self.unload_mean_ + u_scores[:-1] @ self.unload_components_, 0.0)
        u_end = float(np.exp(u_scores[-1]))
        s_max = _energy_stop(self.s_grid_, a_load, v0, f"surrogate curve at v0 = {v0:.4g} m/s")
        return CAECurve(self.s_grid_, a_load, self.w_grid_ * u_end, a_unload, s_max, u_end, float(v0))

    def campaign_identity(self) -> tuple[str | None, str | None]:
        """``(source, content_hash)`` of the campaign fitted on, for ``read_campaign(known=...)``
        (``source`` None in files written before it was recorded)."""
        check_is_fitted(self)
        return getattr(self, "campaign_source_", None), getattr(self, "campaign_hash_", None)

    def check_campaign(self, campaign: Campaign, file: str | os.PathLike | None = None) -> None:
        """Refuse to serve ``campaign`` unless this surrogate was fitted on exactly that campaign.

        Parameters
        ----------
        campaign : Campaign
            The campaign about to be evaluated or fitted with this surrogate.
        file : path-like, optional
            Where the surrogate was read from, for the error message.

        Raises
        ------
        InputError
            If the recorded ``campaign_hash_`` is missing (fitted from pulses, or an older file) or
            differs from ``campaign.content_hash()`` (field ``campaign_hash``).
        """
        check_is_fitted(self)
        recorded, actual = getattr(self, "campaign_hash_", None), campaign.content_hash()
        if recorded != actual:
            got = "records no campaign" if recorded is None else f"was fitted on campaign {recorded[:12]}"
            raise InputError(f"this CAE surrogate {got}, expected campaign {actual[:12]} "
                             f"({campaign.root or 'in memory'}): re-run `crashfuse prepare` on it", file,
                             "campaign_hash")

    # --------------------------------------------------------------------------- features
    def _choose_categories(self, pulses: list[Pulse]) -> dict[str, list[str]]:
        if self.categorical not in ("auto", True, False):
            raise InputError(f"expected 'auto', True or False, got {self.categorical!r}", field="categorical")
        if self.categorical is False:
            return {}
        levels = {c: sorted({str(p.meta.get(c)) for p in pulses}) for c in CATEGORIES}
        return {c: lv for c, lv in levels.items() if len(lv) > 1 or self.categorical is True}

    def _features(self, pulses: list[Pulse]) -> np.ndarray:
        """Conditions matrix, shape (n, 3 + one-hot columns): v0 m/s, w_f kg, w_r kg, one-hots."""
        return np.vstack([self._features_one(p.v0, p.front_weight, p.rear_weight, p.meta, p.run_id)
                          for p in pulses])

    def _features_one(self, v0, wf, wr, labels: dict, run_id: str | None = None) -> np.ndarray:
        """One conditions row, shape (1, p); ``run_id`` (fit data) names the run in errors."""
        of = f" (run {run_id})" if run_id else ""
        for name, val in (("v0", v0), ("front_weight", wf), ("rear_weight", wr)):
            if not (np.isfinite(val) and val > 0):
                raise InputError(f"expected a positive finite number (SI), got {val!r}{of}", field=name)
        row = [float(v0), float(wf), float(wr)]
        for col, levels in self.categories_.items():
            val = labels.get(col)
            if str(val) not in levels:
                raise InputError(f"expected one of {levels} (the levels the surrogate was fitted on), got "
                                 f"{val!r}{of}", field=col)
            row += [float(str(val) == lv) for lv in levels[1:]]
        return np.array([row])

    def _gp(self, rng) -> KrigingGP:
        return KrigingGP(trend="linear", n_restarts=self.n_restarts, max_fit_points=self.max_fit_points,
                         random_state=rng.randint(SEED_MAX))

    # --------------------------------------------------------------------------- loading
    def _fit_loading(self, X, branches: list[Branches], rng) -> None:
        reach = np.array([b.loading.x[-1] for b in branches])
        self.s_grid_ = np.linspace(0.0, reach.max(), self.n_grid)
        A = np.full((len(branches), self.n_grid), np.nan)
        for row, b in zip(A, branches):
            seen = self.s_grid_ <= b.loading.x[-1]
            row[seen] = np.interp(self.s_grid_[seen], b.loading.x, b.loading.decel)
        r = min(self.n_components, len(branches) - 1, self.n_grid)
        A = _impute_low_rank(A, r, self.impute_iter)
        self.load_mean_, self.load_components_, scores = _pca(A, r)
        self.load_gps_ = [self._gp(rng).fit(X, z) for z in scores.T]

    # --------------------------------------------------------------------------- unloading
    def _fit_unloading(self, X, branches: list[Branches], rng) -> None:
        self.w_grid_ = np.linspace(0.0, 1.0, self.n_unload_grid)
        rows, curves, log_u = [], [], []
        for i, b in enumerate(branches):
            if b.stopped and _separation(b) is not None:
                u, a = _unloading_to_separation(b)
                rows.append(i)
                curves.append(np.interp(self.w_grid_ * u[-1], u, a))
                log_u.append(np.log(u[-1]))
        if len(rows) < 5:
            raise InputError(f"expected at least 5 CAE runs whose unloading reaches separation within the record, "
                             f"found {len(rows)}", field="cae")
        q = min(self.n_unload_components, len(rows) - 1, self.n_unload_grid)
        self.unload_mean_, self.unload_components_, scores = _pca(np.array(curves), q)
        targets = [*scores.T, np.array(log_u)]
        self.unload_gps_ = [self._gp(rng).fit(X[rows], z) for z in targets]
        self.n_unloading_ = len(rows)


# ------------------------------------------------------------------------------- helpers
def _cae_pulses(runs) -> list[Pulse]:
    if isinstance(runs, Campaign):
        pulses = [runs.pulses[r] for r in runs.cae]
    else:
        pulses = list(runs)
    not_cae = [p.run_id for p in pulses if p.source != "cae"]
    if not_cae:
        raise InputError(f"the CAE surrogate learns from CAE runs only, got tests {not_cae[:5]}", field="source")
    if len(pulses) < 10:
        raise InputError(f"expected at least 10 CAE runs to learn a surrogate from, got {len(pulses)}",
                         field="cae")
    return pulses


def _separation(br: Branches) -> int | None:
    """Index on the unloading branch where the decel first falls to SEPARATION of its start, or None."""
    a = br.unloading.decel
    below = np.flatnonzero(a <= SEPARATION * a[0])
    return int(below[0]) if below.size and below[0] >= 2 else None


def _unloading_to_separation(br: Branches) -> tuple[np.ndarray, np.ndarray]:
    """Unloading coordinate u (m) and decel (m/s^2) from maximum crush to separation (decel set to 0 there)."""
    k = _separation(br)
    u, a = br.unloading.x[: k + 1].copy(), br.unloading.decel[: k + 1].copy()
    a[-1] = 0.0
    return u, a


def _joined_unloading(u: np.ndarray, a: np.ndarray, stand_in: "CAECurve"):
    """A run's unloading ``(u, a)`` cut by its record's end, continued by ``stand_in``'s beyond it:
    ``(u, a, 'joined')``, or None where the stand-in ends first or the two do not push there.

    The stand-in (the surrogate's curve at the run's condition) is scaled to the run's force over the
    last 5 % of the run's spring-back: taken whole, it met the run's turnaround with the surrogate's
    force, a jump of up to 2.5 g in a companion rollout that the run itself does not show
    (docs/decisions.md, section 70).
    """
    beyond = stand_in.u > u[-1]
    if u.size < 2 or not beyond.any():
        return None
    tail = u >= u[-1] - 0.05 * (u[-1] - u[0])
    own, theirs = float(np.mean(a[tail])), float(np.mean(np.interp(u[tail], stand_in.u, stand_in.a_unloading)))
    if own <= 0 or theirs <= 0:
        return None
    return np.append(u, stand_in.u[beyond]), np.append(a, stand_in.a_unloading[beyond] * own / theirs), "joined"


def _end_slope(x: np.ndarray, a: np.ndarray) -> float:
    """Least-squares slope (m/s^2 per m) of ``a`` over the last 5 % of ``x`` (0 if < 2 points)."""
    tail = x >= x[-1] - 0.05 * (x[-1] - x[0])
    return float(np.polyfit(x[tail], a[tail], 1)[0]) if tail.sum() >= 2 else 0.0


def _continued_unloading(u: np.ndarray, a: np.ndarray):
    """An unloading cut by the record's end, continued with its last slope to 0: (u, a, 'continued').

    Where the last slope does not fall (a run pushing harder again as its record ends: the second world's
    engine on its mounts), the branch's mean slope from maximum crush to the record's end. None if that
    does not fall either (no honest way to say where the spring-back ends).
    """
    k = _end_slope(u, a)
    if k >= 0 and u[-1] > u[0]:
        k = (a[-1] - a[0]) / (u[-1] - u[0])
    if k >= 0 or a[-1] <= 0:
        return None
    return np.append(u, u[-1] + a[-1] / -k), np.append(a, 0.0), "continued"


def _energy_stop(s: np.ndarray, a: np.ndarray, v0: float, what: str, file: str | None = None) -> float:
    """Displacement (m) where the work ``int a ds`` (trapezoid) reaches ``v0^2 / 2``.

    Beyond ``s[-1]`` the curve is continued with its last stiffness (as :meth:`CAECurve.loading`),
    clipped at 0: a falling tail absorbs at most ``a_end^2 / (2 |k|)`` before the decel reaches 0.

    Parameters
    ----------
    s, a : ndarray, shape (k,)
        Displacements (m, increasing) and decelerations (m/s^2) of the loading branch.
    v0 : float
        Impact speed in m/s.
    what : str
        The curve, for the error message (e.g. ``"CAE run C012"``).
    file : str, optional
        The file it came from, for the error message.

    Raises
    ------
    InputError
        If the curve (with its continued tail) cannot absorb the impact energy.
    """
    need = 0.5 * v0 * v0
    work = np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * np.diff(s))])
    if work[-1] >= need:
        i = int(np.searchsorted(work, need))
        return float(s[i - 1] + (s[i] - s[i - 1]) * (need - work[i - 1]) / (work[i] - work[i - 1]))
    k, a_end, rest = _end_slope(s, a), max(float(a[-1]), 0.0), need - work[-1]
    # rest = a_end d + k d^2 / 2 for the extra travel d. A falling tail reaches 0 (and stays there) after
    # absorbing a_end^2 / (2 |k|); a flat tail at 0 absorbs nothing.
    if k < 0:
        tail_work = a_end**2 / (-2 * k)
    else:
        tail_work = np.inf if k > 0 or a_end > 0 else 0.0
    if rest > tail_work:
        raise InputError(f"{what}: the CAE curve stops decelerating beyond {s[-1]:.3g} m before absorbing the "
                         f"impact energy (v0 = {v0:.3g} m/s needs {need:.4g} J/kg, the curve and its continued "
                         f"tail give {work[-1] + tail_work:.4g}); expected a curve that brings the vehicle to "
                         "rest: outside the CAE data", file=file, field="v0")
    d = rest / a_end if abs(k) < 1e-12 else (-a_end + np.sqrt(a_end**2 + 2 * k * rest)) / k
    return float(s[-1] + d)


def _impute_low_rank(A: np.ndarray, rank: int, n_iter: int) -> np.ndarray:
    """Fill NaNs of ``A`` (n, k) by iterated rank-``rank`` SVD reconstruction (hard impute).

    Starts from the column means of the observed entries; observed entries are never changed.
    """
    missing = np.isnan(A)
    col_mean = np.nanmean(A, axis=0)
    filled = np.where(missing, col_mean, A)
    for _ in range(n_iter if missing.any() else 0):
        mean, comps, scores = _pca(filled, rank)
        filled[missing] = (mean + scores @ comps)[missing]
    return filled


def _pca(A: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (k,), leading ``rank`` components (rank, k) and scores (n, rank) of rows of ``A`` (n, k).

    From the eigenvectors of the k x k scatter matrix rather than an SVD of the n x k data: with
    n ~ 1000 runs and k ~ 200 grid points it is ~20x cheaper, and the leading components of these
    smooth curves are far above the precision lost by squaring the condition number.
    """
    mean = A.mean(axis=0)
    centred = A - mean
    _, vecs = np.linalg.eigh(centred.T @ centred)
    # Contiguous, as a pickled copy is: a strided array takes another BLAS path, whose last-bit
    # differences the hybrid's least-squares fit amplifies (--jobs 1 and 2 gave ISO 0.934 / 0.927).
    comps = np.ascontiguousarray(vecs[:, ::-1][:, :rank].T)
    return mean, comps, centred @ comps.T
