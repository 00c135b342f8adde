"""The physics-first hybrid: effect laws fitted to the training tests, the GMM-GP bias on what is left.

With ``effects`` (:class:`crashfuse.method.config.MethodConfig`), a fit first adds catalogue
effects (:mod:`crashfuse.method.laws`) to the CAE model, their parameters fitted to the fold's
training tests only (:mod:`crashfuse.method.effect_fit`). The CAE curve of any condition then
becomes the rollout of CAE + effects (:meth:`PhysicsFirst.curve`): the bias data pair each training
test with that curve, so the GMM-GP bias learns only what the laws leave, and a prediction rolls out
the same curve plus the predicted bias. Without effects the fit is the GMM-GPR model unchanged.

``effects="auto"`` chooses the effects by forward selection on the training tests alone: an effect
joins when it cuts their inner leave-one-test-out squared error (each training test predicted by
the laws fitted on the others) by at least :data:`MIN_GAIN`, and an earlier pick leaves when the
later ones make it unneeded (without it the error rises by less than that). A law of no powertrain
label must gain so on the tests of more than one label. Rate laws (``strain_rate``,
``damping``) need CAE runs at :data:`~crashfuse.method.effect_fit.MIN_CAE_SPEEDS` impact speeds,
which separate the CAE model's own rate sensitivity from the missing one: naming one without them
is an error, and ``auto`` leaves them out and says so (:attr:`PhysicsFirst.notes`).

A law acts only where the training tests saw it act: the powertrain arrest of a label whose fitted
gap no training test of that label crushed to (or of a label no training test had) is switched off,
so a faster condition of that label does not meet an engine fitted to nothing.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from crashfuse.catalogue import CATALOGUE, EFFECTS
from crashfuse.errors import InputError
from crashfuse.io.campaign import Campaign
from crashfuse.method.effect_fit import (DT, MIN_CAE_SPEEDS, FoldFits, fit_folds, parameters_to_fit,
                                         predict, test_case, warm_start)
from crashfuse.method.laws import N_S, curve_plant, simulate
from crashfuse.method.surrogate import CAECurve, CAESurrogate
from crashfuse.signals.pulse import Pulse

AUTO = "auto"
RATE_EFFECTS = ("strain_rate", "damping")  # laws that act through the crush speed
UNREACHED_GAP = 1.0e3  # m: a powertrain gap no crush reaches - the law is off for that label
MIN_GAIN = 0.10  # fraction of the inner held-out squared error an effect must remove to join `auto`
DURATION = 0.3  # s, rollout of a CAE + effects curve: past separation for any frontal pulse


@dataclasses.dataclass
class PhysicsFirst:
    """Effect laws fitted to training tests, added to the CAE model.

    Attributes
    ----------
    effects : tuple of str
        Catalogue effects, possibly empty (then :meth:`curve` returns the CAE curve unchanged).
    tests : list of str
        The training tests the laws were fitted (and chosen) on, sorted.
    theta : dict of str to float
        Every law parameter (``effect.param``, SI), fitted on the training tests.
    labels : tuple of str
        Powertrain labels of the training tests (``all`` where unlabelled).
    s_hi : float
        Crush (m) up to which the laws tabulate the CAE curve.
    rate : ndarray, shape (2, N_S)
        The CAE force's sensitivity to crush speed on ``linspace(0, s_hi, N_S)``
        (:func:`crashfuse.method.laws.crush_force_rate`, N s/m and N s^2/m^2); zeros when
        not ``rate_aware``.
    rate_aware : bool
        Whether the CAE runs span enough impact speeds to estimate that sensitivity.
    training_mse : float
        Mean squared residual of CAE + effects over the training tests, (m/s^2)^2.
    inner_mse : dict of str to float
        ``auto`` only: the inner leave-one-test-out squared error of every effect set tried
        (keys as :func:`choose_effects` returns them), (m/s^2)^2.
    notes : list of str
        Fallbacks taken (rate laws left out of ``auto``, powertrain laws switched off).
    """

    effects: tuple
    tests: list
    theta: dict
    labels: tuple
    s_hi: float
    rate: np.ndarray
    rate_aware: bool
    training_mse: float
    inner_mse: dict
    notes: list

    def curve(self, base: CAECurve, mass: float, label: str | None, faster: CAECurve | None,
              front_weight: float, rear_weight: float) -> CAECurve:
        """The CAE + effects curve of one condition.

        Parameters
        ----------
        base : CAECurve
            The CAE model's curve there (companion run or surrogate).
        mass : float
            Nominal vehicle mass in kg.
        label : str or None
            Powertrain label (None: ``all``).
        faster : CAECurve or None
            The surrogate's curve at :data:`~crashfuse.method.effect_fit.FASTER` x the impact
            speed, the structure met beyond ``base``'s crush (rate-aware fits only).
        front_weight, rear_weight : float
            Axle masses in kg (recorded on the rolled-out pulse).

        A label no training test had meets no powertrain arrest (nothing informed one).
        """
        if not self.effects:
            return base
        label = "all" if label is None else str(label)
        theta = dict(self.theta)
        if "powertrain" in self.effects and label not in self.labels:
            theta.update({f"powertrain.mass[{label}]": 0.0, f"powertrain.gap[{label}]": UNREACHED_GAP})
        grid = np.linspace(0.0, self.s_hi, N_S)
        rate = None if not self.rate_aware else (lambda s: np.array([np.interp(s, grid, b) for b in self.rate]))
        plant = curve_plant([base], [mass], [label], self.s_hi, [faster] if self.rate_aware else None, rate)
        theta = {name: np.array([value]) for name, value in theta.items()}
        traj = simulate(plant, self.effects, theta, DT, int(round(DURATION / DT)))
        pulse = Pulse(traj.time, traj.decel[0], base.v0, front_weight, rear_weight,
                      run_id=f"{base.run_id}+{'+'.join(self.effects)}", source="cae")
        return CAECurve.from_pulse(pulse, unloading_from=base)


def check_effects(value, field: str = "effects"):
    """``auto``, or a tuple of distinct catalogue effects (``none`` and empty: no effect).

    Raises
    ------
    InputError
        An unknown effect, a repeat, or another type, naming ``field``.
    """
    if isinstance(value, str):
        value = () if value == "none" else value if value == AUTO else (value,)
    if value == AUTO:
        return AUTO
    if not isinstance(value, (tuple, list)) or not all(isinstance(e, str) for e in value):
        raise InputError(f"expected {AUTO!r}, 'none' or a sequence of effects among {list(EFFECTS)}, got {value!r}",
                         field=field)
    unknown = [e for e in value if e not in EFFECTS]
    if unknown or len(set(value)) != len(value):
        what = f"unknown effect(s) {unknown}" if unknown else "an effect named twice"
        raise InputError(f"{what}: expected distinct effects among {list(EFFECTS)}, {AUTO!r} or 'none', "
                         f"got {list(value)}", field=field)
    return tuple(value)


def fit_physics(campaign: Campaign, train, effects, surrogate: CAESurrogate, min_gain: float = MIN_GAIN,
                candidates=EFFECTS) -> PhysicsFirst:
    """Fit (and with ``auto`` choose) effect laws on the tests ``train`` only.

    Parameters
    ----------
    campaign : Campaign
    train : sequence of str
        The training tests; no other test enters any fit or choice.
    effects : "auto" or tuple of str
        As :func:`check_effects` returns.
    surrogate : CAESurrogate
        Fitted on the campaign's CAE runs.
    min_gain : float
        ``auto``: the fraction of inner held-out squared error an effect must remove.
    candidates : sequence of str
        ``auto``: the effects it may choose among.

    Returns
    -------
    PhysicsFirst

    Raises
    ------
    InputError
        A rate law named while the CAE runs span fewer than ``MIN_CAE_SPEEDS`` impact speeds.
    """
    case = test_case(campaign.subset([*train, *campaign.cae]), surrogate)
    rows = list(range(len(case.test_ids)))
    notes, inner = [], {}
    if effects == AUTO:
        if not case.rate_aware:
            candidates = tuple(e for e in candidates if e not in RATE_EFFECTS)
            notes.append(f"rate laws {list(RATE_EFFECTS)} left out: the CAE runs span fewer than {MIN_CAE_SPEEDS} "
                         f"impact speeds")
        effects, inner, fits, refused = choose_effects(case, rows, candidates, min_gain)
        notes += refused
    elif not case.rate_aware and set(effects) & set(RATE_EFFECTS):
        raise InputError(f"{sorted(set(effects) & set(RATE_EFFECTS))} need CAE runs at {MIN_CAE_SPEEDS} or more "
                         f"impact speeds (the CAE model's own rate sensitivity), the campaign has fewer",
                         campaign.root, "effects")
    else:
        fits = fit_folds(case, effects, [rows])
    theta = {p.name: float(v) for p, v in zip(fits.params, fits.theta[-1])}
    notes += _switch_off_unreached(theta, _reach(case, rows))
    plant = case.plant  # its rate sensitivity as tabulated for the fit (force per crush speed = dadv x mass)
    rate = np.array([plant.dadv[0], plant.dadv2[0]]) * plant.mass[0]
    return PhysicsFirst(tuple(effects), sorted(train), theta, plant.labels, plant.s_hi, rate, case.rate_aware,
                        float(fits.cost[-1]), inner, notes)


def _reach(case, rows) -> dict:
    """Largest measured crush (m) per powertrain label of ``case`` among the tests ``rows`` (0 for a
    label none of them has)."""
    group = case.plant.group
    return {label: max((case.crush[r] for r in rows if group[r] == g), default=0.0)
            for g, label in enumerate(case.plant.labels)}


def _switch_off_unreached(theta: dict, reach: dict) -> list:
    """Switch off, in ``theta``, the powertrain law of every label whose fitted gap no training test of
    that label crushed to (``reach``: label to largest crush, m): its mass and gap were never observed
    acting, so a faster condition of that label must not meet an arrest fitted to nothing (the bias
    model then corrects it as without the law). The training tests' rollouts never reached the gap,
    so their fit is unchanged. Returns notes."""
    notes = []
    for label, largest in reach.items():
        name = f"powertrain.gap[{label}]"
        if name in theta and theta[name] >= largest:
            notes.append(f"powertrain law off for {label}: no training test of it crushed to its fitted gap "
                         f"{theta[name]:.3f} m (largest crush {largest:.3f} m)")
            theta[name] = UNREACHED_GAP
    return notes


def choose_effects(case, rows, candidates=EFFECTS, min_gain: float = MIN_GAIN) -> tuple[tuple, dict, FoldFits, list]:
    """Forward selection of effects by inner leave-one-test-out squared error over ``rows``.

    Each round fits every remaining candidate with the chosen ones (from their fits and from the
    listed starts) on every inner training set and on all of ``rows`` at once; the best joins if it
    removes ``min_gain`` of the error, and an earlier pick it makes unneeded leaves
    (:func:`_drop_unneeded`). Each inner held-out test is predicted as the model fitted without it
    would predict it (:func:`_inner_errors`). A law that acts alike on every powertrain label may join
    only where it gains on more than one label (:func:`_gains_on_labels`).

    Parameters
    ----------
    case : TestCase
    rows : list of int
        The tests of ``case`` to choose on.
    candidates : sequence of str
    min_gain : float

    Returns
    -------
    effects : tuple of str
        The chosen effects, in the order they joined (empty: the CAE alone predicts best).
    tried : dict of str to float
        Inner held-out mean squared error, (m/s^2)^2, of every effect set tried (``+``-joined,
        ``none`` for the CAE alone; ``... (refitted without e)`` for a set checked without an
        earlier pick ``e``).
    fits : FoldFits
        The chosen set's fits: the inner sets, then all of ``rows`` (the last row).
    notes : list of str
        Candidates refused because their gain was one label's alone.
    """
    sets = [[r for r in rows if r != j] for j in rows] + [list(rows)]
    current = fit_folds(case, (), sets)
    chosen, error, dropped, notes = (), _inner_errors(case, current, rows), set(), []
    tried = {"none": float(error.mean())}
    while remaining := [e for e in candidates if e not in chosen and e not in dropped]:
        trials = {e: fit_folds(case, chosen + (e,), sets, start=warm_start(case, current, (e,)),
                                 listed_too=True) for e in remaining}
        errors = {e: _inner_errors(case, fits, rows) for e, fits in trials.items()}
        tried.update({"+".join(chosen + (e,)): float(err.mean()) for e, err in errors.items()})
        gaining = [e for e in remaining if errors[e].mean() <= (1.0 - min_gain) * error.mean()]
        spread = [e for e in gaining if _per_label(e) or _gains_on_labels(case, rows, error, errors[e], min_gain)]
        notes += [f"{e} refused after {'+'.join(chosen) or 'none'}: its gain is on one powertrain label's tests only"
                  for e in gaining if e not in spread]
        if not spread:
            break
        best = min(spread, key=lambda e: errors[e].mean())
        chosen, current, error = _drop_unneeded(case, rows, sets, chosen + (best,), trials[best],
                                                errors[best], tried, dropped, min_gain)
    return chosen, tried, current, notes


def _per_label(effect: str) -> bool:
    """Whether the catalogue gives ``effect`` a quantity per powertrain label (it may act on one alone)."""
    return any(q.per_label for q in CATALOGUE[effect].quantities)


def _gains_on_labels(case, rows, before, after, min_gain: float) -> bool:
    """Whether the inner squared errors ``after`` (per test of ``rows``) are ``min_gain`` below ``before``
    on the tests of more than one powertrain label (labels with two or more tests among ``rows``;
    True where fewer than two labels have that many). A law of no label acts on every test; a gain on
    one label's tests alone is that label's own unmodelled physics taken up by the wrong law - rate
    hardening fitted to one powertrain's engine impact (docs/decisions.md, section 49)."""
    group = case.plant.group[np.asarray(rows)]
    labels = [g for g in np.unique(group) if (group == g).sum() >= 2]
    gains = [after[group == g].sum() <= (1.0 - min_gain) * before[group == g].sum() for g in labels]
    return len(labels) < 2 or sum(gains) >= 2


def _drop_unneeded(case, rows, sets, chosen, fits: FoldFits, error: np.ndarray, tried: dict, dropped: set,
                   min_gain: float):
    """``chosen`` (its ``fits`` and inner ``error`` per test of ``rows``) without each earlier pick the
    later ones make unneeded: refitted without it from ``fits``' values, the mean inner error must rise
    by ``min_gain`` of the mean with it, as it had to fall when it joined. Two laws can take up one gap
    in turn - a force growing with crush speed read first as rate hardening, then as damping - and the
    first must not stay by its order alone (the diagnosis' rule, docs/decisions.md, section 43). A
    dropped effect joins ``dropped`` and is not tried again; each check is recorded in ``tried``.
    Returns the effects, fits and inner errors kept."""
    for e in chosen[:-1]:
        rest = tuple(x for x in chosen if x != e)
        names = {p.name for p in parameters_to_fit(case, rest)}
        refit = fit_folds(case, rest, sets, start=fits.theta[:, [p.name in names for p in fits.params]],
                          listed_too=True)
        without = _inner_errors(case, refit, rows)
        tried[f"{'+'.join(rest)} (refitted without {e})"] = float(without.mean())
        if error.mean() > (1.0 - min_gain) * without.mean():
            dropped.add(e)
            chosen, fits, error = rest, refit, without
    return chosen, fits, error


def _inner_errors(case, fits: FoldFits, rows) -> np.ndarray:
    """Each test of ``rows``' mean squared error, (m/s^2)^2, predicted by the fit of the inner set without it
    as :func:`fit_physics` would predict it: with the powertrain law of a label off where none of the
    inner set's tests of that label crushed to its fitted gap. Unguarded, a test that alone reached
    its label's engine met one fitted to nothing, and that error - noise of the starting point -
    outweighed the rest (docs/decisions.md, section 47)."""
    theta = fits.theta.copy()
    if "powertrain" in fits.effects:
        names = [p.name for p in fits.params]
        for j, held in enumerate(rows):
            values = dict(zip(names, theta[j]))
            _switch_off_unreached(values, _reach(case, [r for r in rows if r != held]))
            theta[j] = [values[n] for n in names]
    return predict(case, dataclasses.replace(fits, theta=theta), range(len(rows)), rows)[1]
