"""The effect catalogue: the world's laws and the diagnosis' laws describe exactly its effects, with
parameters that are its quantities and headlines under its names."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import yaml

from crashfuse import catalogue
from crashfuse.catalogue import CATALOGUE, EFFECTS, check_declaration, check_effect, key
from crashfuse.method import laws
from crashfuse.errors import InputError
from crashfuse.world import effects as world
from crashfuse.world.multibody import effects as multibody

REPO = Path(__file__).resolve().parents[1]
LABELS = ("Type I", "Type II")
SIDES = {"world": world.QUANTITIES, "multibody world": multibody.QUANTITIES, "diagnosis": laws.QUANTITIES}


def _effects_of(declaration) -> set:
    return {name.split(".", 1)[0] for name in declaration}


def _headline_keys(effect: str) -> set:
    """The catalogue's reported names of the headline quantities of ``effect`` for :data:`LABELS`."""
    return {key(effect, q.name, lab) for q in CATALOGUE[effect].headlines
            for lab in (LABELS if q.per_label else (None,))}


@pytest.mark.parametrize("side", SIDES)
def test_each_side_has_laws_for_exactly_the_catalogue(side):
    check_declaration(SIDES[side], side)
    assert _effects_of(SIDES[side]) == set(EFFECTS)


def test_a_law_on_one_side_only_fails():
    for side, declaration in SIDES.items():
        with pytest.raises(ValueError, match="catalogue"):
            check_declaration({**declaration, "engine_contact.speed": "gap"}, side)
        with pytest.raises(ValueError, match="laws for"):
            check_declaration({k: v for k, v in declaration.items() if not k.startswith("mass.")}, side)
        with pytest.raises(ValueError, match="no quantity"):
            check_declaration({**declaration, "damping.c": "damping_ratio"}, side)


@pytest.mark.parametrize("laws_of", [world, multibody], ids=["world", "multibody world"])
def test_world_declares_every_parameter_it_uses(laws_of):
    assert set(laws_of.REALISTIC) == set(laws_of.QUANTITIES)
    assert set(laws_of.params_at_strength("subtle", EFFECTS)) == set(laws_of.QUANTITIES)
    assert set(laws_of.POSITIVE) <= set(laws_of.QUANTITIES)


@pytest.mark.parametrize("effect", EFFECTS)
def test_diagnosis_declares_every_parameter_it_fits(effect):
    params = laws.parameters(effect, LABELS)
    assert {p.name.split("[", 1)[0] for p in params} == {n for n in laws.QUANTITIES if n.startswith(effect + ".")}
    for p in params:
        q = catalogue.quantity(p.name.split("[", 1)[0], laws.QUANTITIES)
        assert p.unit == q.unit
        assert ("[" in p.name) == q.per_label


@pytest.mark.parametrize("effect", EFFECTS)
def test_both_sides_report_the_catalogue_headlines(effect):
    tests = pd.DataFrame({"powertrain": ["Type I", "Type II", "Type II"], "drive": ["FWD", "AWD", "AWD"]})
    true = world.headline(effect, world.REALISTIC, tests)
    second = multibody.headline(effect, multibody.REALISTIC, {"Type I": 170.0, "Type II": 245.0})
    fitted = laws.headline(effect, {p.name: p.start[0] for p in laws.parameters(effect, LABELS)})
    assert set(true) == set(second) == set(fitted) == _headline_keys(effect)


def test_second_world_headlines_follow_its_own_laws():
    """Law-neutral headlines from the power-law rate hardening and the quadratic damping."""
    p = {**multibody.REALISTIC, "strain_rate.a": 0.2, "strain_rate.v_ref": 10.0, "strain_rate.p": 0.5,
         "damping.c2": 300.0}
    gain = multibody.headline("strain_rate", p, {})["strain_rate.gain_at_15mps"]
    assert gain == pytest.approx(0.2 * 1.5**0.5)
    assert multibody.headline("damping", p, {})["damping.c"] == pytest.approx(300.0 * catalogue.V_REF)


def test_catalogue_entries():
    for effect in CATALOGUE.values():
        names = [q.name for q in effect.quantities]
        assert len(names) == len(set(names)) and effect.headlines and effect.meaning
        assert all(q.unit and q.meaning for q in effect.quantities)
    with pytest.raises(ValueError, match="per powertrain label"):
        key("powertrain", "mass")
    with pytest.raises(InputError, match="unknown effect 'spring'") as err:
        check_effect("spring", field="--effects")
    assert err.value.field == "--effects"


def test_workflow_offers_the_catalogue():
    schema = yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())
    effects = schema["properties"]["diagnosis"]["properties"]["effects"]
    assert tuple(effects["items"]["enum"]) == tuple(effects["default"]) == EFFECTS
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    assert tuple(config["diagnosis"]["effects"]) == EFFECTS
