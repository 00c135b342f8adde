"""The catalogue of physical effects a real crash test has and a CAE model may miss.

One catalogue serves two independent sets of laws: the synthetic world's (:mod:`crashfuse.world.effects`,
how the physical tests are made) and the diagnosis' (:mod:`crashfuse.method.laws`, fitted to a
campaign to explain its gap). Neither imports the other's physics; they share only what is here:
the effect names, what each effect is physically, and the quantities that describe it, each by
meaning with a unit. The entries describe the physics, not one law's equation, so laws of other
forms (another rate-hardening or unloading law) plug in by declaring which of these quantities
their parameters are.

Every law declares its parameters as ``{"effect.param": quantity name}`` (:func:`check_declaration`).
The *headline* quantities of an effect are what every law of it can report and what the
validation compares between the world's answer key and the diagnosis' fit; they are reported as
``effect.quantity`` (``effect.quantity[label]`` for a quantity per powertrain label, :func:`key`).
All quantities are SI.
"""

from __future__ import annotations

import dataclasses
import math

from crashfuse.errors import InputError

V_REF = 15.0  # m/s: reference crush speed of the strain-rate headline (about 34 mph)
F_REF = 5e5  # N: reference peak force of the unloading headline (about 30 g on a 1700 kg car)
STRENGTHS = ("realistic", "subtle")  # named magnitudes of a world's effect laws


@dataclasses.dataclass(frozen=True)
class Quantity:
    """One physical quantity of an effect.

    Attributes
    ----------
    name : str
        Short name, unique within the effect (reported as ``effect.name``).
    unit : str
        SI unit (``-`` for dimensionless).
    meaning : str
        What it quantifies, independent of any law's equation.
    headline : bool
        Every law of the effect reports it; the validation compares it.
    per_label : bool
        One value per powertrain label (reported as ``effect.name[label]``).
    """

    name: str
    unit: str
    meaning: str
    headline: bool = False
    per_label: bool = False


@dataclasses.dataclass(frozen=True)
class Effect:
    """One catalogue effect: its physical meaning and the quantities that describe it."""

    name: str
    meaning: str
    quantities: tuple

    def quantity(self, name: str) -> Quantity:
        """The quantity ``name`` of this effect, else ValueError (a law declared an unknown quantity)."""
        for q in self.quantities:
            if q.name == name:
                return q
        known = ", ".join(q.name for q in self.quantities)
        raise ValueError(f"the catalogue's {self.name} has no quantity {name!r}; expected one of {known}")

    @property
    def headlines(self) -> tuple:
        """The headline quantities, in catalogue order."""
        return tuple(q for q in self.quantities if q.headline)


CATALOGUE = {e.name: e for e in (
    Effect("damping", "crush damping: a crush force growing with the crush speed (viscous: in proportion), on "
           "loading and unloading", (
               Quantity("c", "N s/m", f"damping force per unit crush speed at the reference crush speed "
                        f"{V_REF:g} m/s (the coefficient of a linear law)", headline=True),
               Quantity("quadratic_coefficient", "N s^2/m^2", "damping force per squared crush speed (a "
                        "quadratic law: fluids and foam squeezed out)"),
               Quantity("speed_exponent", "-", "the damping force grows as the crush speed to this power (1: "
                        "linear, 2: quadratic)"))),
    Effect("strain_rate", "rate hardening of the crush strength on loading: the structure is stronger the faster "
           "it is crushed, so the gap grows with impact speed", (
               Quantity("gain_at_15mps", "-", f"fractional increase of the crush strength over the static one at "
                        f"the reference crush speed {V_REF:g} m/s", headline=True),
               Quantity("doubling_speed", "m/s", "crush speed at which the strength is twice the static one"),
               Quantity("inverse_rate_exponent", "-", "how slowly the increase grows with crush speed: it grows "
                        "as the crush speed to the power 1/this"),
               Quantity("rate_exponent", "-", "the increase grows as the crush speed to this power"),
               Quantity("gain_at_reference_speed", "-", "fractional increase of the crush strength at a law's own "
                        "reference crush speed"),
               Quantity("reference_speed", "m/s", "a law's own reference crush speed"))),
    Effect("powertrain", "a powertrain mass riding in the body is stopped by the barrier once the crush closes "
           "its gap; the body then drives into it through its mounts: a secondary pulse", (
               Quantity("mass", "kg", "arrested mass: the powertrain mass the barrier stops", headline=True,
                        per_label=True),
               Quantity("gap", "m", "crush at which the powertrain reaches the barrier", per_label=True),
               Quantity("mount_yield_force", "N", "force at which the powertrain mounts yield"),
               Quantity("mount_stiffness", "N/m", "elastic stiffness of the powertrain mounts"),
               Quantity("mount_damping", "N s/m", "viscous damping of the powertrain mounts"),
               Quantity("contact_stiffness", "N/m", "stiffness of the powertrain-barrier contact"),
               Quantity("contact_damping", "N s/m", "viscous damping of the powertrain-barrier contact"))),
    Effect("unloading", "hysteretic unloading after maximum crush: the force falls over an elastic spring-back "
           "that grows with the peak force, larger in proportion at low speed", (
               Quantity("springback_at_500kN", "m", f"elastic spring-back (crush recovered until the force is "
                        f"zero) after a peak force of {F_REF / 1e3:g} kN", headline=True),
               Quantity("springback_floor", "m", "spring-back after a vanishing peak force (bumper foam, elastic "
                        "beams)"),
               Quantity("springback_stiffness", "N/m", "peak force per unit of the spring-back that grows with it"),
               Quantity("initial_decay_floor", "m", "after a vanishing peak force, the crush recovered over which "
                        "the force would reach zero at the rate it starts to fall"),
               Quantity("initial_unloading_stiffness", "N/m", "how steeply the force falls as unloading starts, "
                        "at a large peak force (force per metre of recovered crush)"),
               Quantity("unloading_exponent", "-", "shape of the force's fall over the spring-back (1: linear; "
                        "larger: falls faster at first; without bound: exponential)"),
               Quantity("zero_force_travel_ratio", "-", "travel from maximum crush to zero force, as a multiple "
                        "of the spring-back scale (an exponential law's residual set)"))),
    Effect("mass", "the decelerating mass exceeds the nominal test weight (ballast, instrumentation, cables), "
           "carried rigidly or on a compliant link that loads the body late", (
        Quantity("extra", "kg", "mass decelerated beyond the nominal test weight", headline=True),
        Quantity("link_stiffness", "N/m", "stiffness of a compliant link carrying the extra mass"),
        Quantity("link_damping", "N s/m", "viscous damping of that link"))),
)}

EFFECTS = tuple(CATALOGUE)


def check_effect(name: str, field: str = "effect") -> str:
    """``name`` if it is a catalogue effect, else InputError naming ``field``."""
    if name not in CATALOGUE:
        raise InputError(f"unknown effect {name!r}; expected one of {', '.join(EFFECTS)}", field=field)
    return name


def params_at_strength(strength, realistic: dict, subtle: dict, effects) -> dict:
    """One set of laws' parameters ``{"effect.param": value}`` (SI) at a named strength.

    Parameters
    ----------
    strength : {"realistic", "subtle"}
    realistic : dict
        Every parameter at its realistic magnitude.
    subtle : dict of str to dict
        Per effect, the parameters that change when it is made subtle.
    effects : iterable of str
        Effects made subtle (only with ``strength="subtle"``).

    Raises
    ------
    InputError
        Field ``strength`` or ``withhold``: an unknown strength or effect.
    """
    if strength not in STRENGTHS:
        raise InputError(f"unknown strength {strength!r}; expected one of {STRENGTHS}", field="strength")
    params = dict(realistic)
    if strength == "subtle":
        for name in effects:
            params.update(subtle[check_effect(name, field="withhold")])
    return params


def parse_params(items, known, positive=()) -> dict:
    """Parse ``["effect.param=value", ...]`` into ``{"effect.param": float}`` (SI) for one set of laws.

    Parameters
    ----------
    items : iterable of str or None
    known : collection of str
        The laws' parameter names ``effect.param``.
    positive : collection of str
        Parameters that divide or set a scale: zero is as invalid as negative.

    Raises
    ------
    InputError
        Field ``overrides``: a malformed item, an unknown effect or parameter, a value that is not a
        finite number >= 0 (> 0 for ``positive``).
    """
    out = {}
    for item in items or ():
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep:
            raise InputError(f"expected name=value, got {item!r}", field="overrides")
        effect = check_effect(name.split(".")[0], field="overrides")
        if name not in known:
            names = ", ".join(k for k in known if k.startswith(effect + "."))
            raise InputError(f"unknown parameter {name!r}; expected one of {names}", field="overrides")
        try:
            value = float(text)
        except ValueError:
            raise InputError(f"{name}: expected a number, got {text!r}", field="overrides") from None
        if not math.isfinite(value) or value < 0 or (value == 0 and name in positive):
            need = "> 0" if name in positive else ">= 0"
            raise InputError(f"{name}: expected a finite value {need} (SI units), got {text}", field="overrides")
        out[name] = value
    return out


def quantity(param: str, declaration: dict) -> Quantity:
    """The catalogue quantity a law's parameter ``effect.param`` is, by the law's ``declaration``.

    Raises
    ------
    ValueError
        ``param`` is undeclared, or declared as an unknown effect or quantity.
    """
    effect = param.split(".", 1)[0]
    if param not in declaration or effect not in CATALOGUE:
        raise ValueError(f"{param!r} is not declared as a quantity of a catalogue effect")
    return CATALOGUE[effect].quantity(declaration[param])


def key(effect: str, name: str, label: str | None = None) -> str:
    """The reported name of quantity ``name`` of ``effect``: ``effect.name`` or ``effect.name[label]``."""
    q = CATALOGUE[check_effect(effect)].quantity(name)
    if q.per_label != (label is not None):
        raise ValueError(f"{effect}.{name} is {'' if q.per_label else 'not '}given per powertrain label")
    return f"{effect}.{name}" + ("" if label is None else f"[{label}]")


def check_declaration(declaration: dict, side: str) -> None:
    """Check a set of laws' parameter declaration against the catalogue.

    Parameters
    ----------
    declaration : dict of str to str
        ``{"effect.param": quantity name}`` for every parameter of the laws.
    side : str
        Who declares (for the message), e.g. ``"crashfuse.world.effects"``.

    Raises
    ------
    ValueError
        A parameter of an unknown effect or quantity, or a catalogue effect without a parameter.
    """
    for param in declaration:
        quantity(param, declaration)
    covered = {p.split(".", 1)[0] for p in declaration}
    if covered != set(EFFECTS):
        raise ValueError(f"{side} has laws for {sorted(covered)}; the catalogue lists {list(EFFECTS)}")
