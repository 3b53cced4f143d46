"""Material-class registry, effect registry and scenario parsing."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.solvers import effects as fx
from unipixie.solvers import materials
from unipixie.solvers.scenario import Scenario


def test_material_classes_complete_and_ordered():
    assert materials.names() == ["jelly", "metal", "sand", "plasticine", "fluid", "snow", "stationary", "background"]
    assert [c.id for c in materials.MATERIAL_CLASSES] == list(range(materials.NUM_CLASSES))
    for c in materials.MATERIAL_CLASSES:
        assert c.elasticity in materials.ELASTICITY_MODELS
        assert c.plasticity in materials.PLASTICITY_MODELS
        assert c.typical_E[0] <= c.typical_E[1]
    assert materials.get("snow").plasticity == "snow" and materials.get("snow").elasticity == "fixed_corotated"
    assert materials.get(1).name == "metal" and materials.get("2").name == "sand"
    assert materials.get("stationary").held_fixed and not materials.get("background").simulated
    with pytest.raises(UserError, match="unknown material class"):
        materials.get("unobtainium")


def test_effect_vocabulary_matches_spec():
    assert set(fx.EFFECTS) >= {"linear_drag", "quadratic_drag", "material_damping", "ground_friction",
                               "plasticity", "wind", "stiffness_region"}
    for cls in fx.EFFECTS.values():
        assert cls.law and cls.params and cls.signature


def test_effect_parse_and_roundtrip():
    e = fx.parse("wind:acceleration=0,0.8,-0.1")
    assert np.allclose(e.values["acceleration"], [0, 0.8, -0.1])
    assert fx.from_dict(json.loads(json.dumps(e.to_dict()))) == e
    e2 = fx.parse("linear_drag:c=1.5")
    assert e2.values["c"] == 1.5 and e2.fit_vector().tolist() == [1.5]
    assert e2.with_fit_vector([99.0]).values["c"] == 50.0  # clipped into bounds
    r = fx.parse("stiffness_region:factor=3,points=0-2+5")
    assert r.values["region"]["points"].tolist() == [0, 1, 2, 5]


@pytest.mark.parametrize("spec", [
    "linear_drag:c=0.333333", "quadratic_drag:k=0.3", "wind:acceleration=0,0.8,-0.1", "ground_friction:mu=0.4",
    "stiffness_region:factor=3,box=0,0,0,0.1,0.1,0.05", "stiffness_region:factor=0.3,points=0+1+2+5",
])
def test_effect_to_spec_is_the_inverse_of_parse(spec):
    e = fx.parse(spec)
    assert e.to_spec() == spec and fx.parse(e.to_spec()) == e
    # the panel writes its fields' values through the same formatter
    assert type(e).spec_of({k: v for k, v in e.values.items()}) == spec


def test_every_effect_default_round_trips_through_its_spec():
    for name, cls in fx.EFFECTS.items():
        if all(p.fittable for p in cls.params):
            e = fx.make(name)
            assert fx.parse(e.to_spec()) == e, name


def test_solver_registry_names_every_solver_once():
    from dataclasses import fields

    from unipixie.solvers import api, registry

    assert registry.SOLVER_NAMES == ("mpm", "lbs", "spring_mass")  # the model's head order
    for name, solver in registry.SOLVERS.items():
        assert solver.name == name and solver.label and solver.description
        assert isinstance(solver.defaults(), solver.settings)
        assert solver.settings.from_any(None) == solver.defaults()
        first = fields(solver.settings)[0].name
        assert solver.settings.from_any({first: getattr(solver.defaults(), first)}) == solver.defaults()
        with pytest.raises(UserError, match=f"unknown {solver.settings.solver_words} setting"):
            solver.settings.from_any({"no_such_setting": 1})
        with pytest.raises(UserError, match="must be a dict"):
            solver.settings.from_any(3)
    assert api.canonical_solver(" Spring-Mass ") == "spring_mass"
    for effect in fx.EFFECTS.values():
        assert set(effect.solvers) <= set(registry.SOLVERS)
    with pytest.raises(UserError, match="unknown solver"):
        api.canonical_solver("fem")


@pytest.mark.parametrize("spec, message", [
    ("gravityy:x=1", "unknown effect"),
    ("linear_drag:c=-1", "outside"),
    ("linear_drag:q=1", "no parameter"),
    ("linear_drag:c=abc", "not a number"),
    ("stiffness_region:factor=2", "needs a region"),
    ("wind:acceleration=1,2", "3 finite numbers"),
])
def test_effect_parse_errors(spec, message):
    with pytest.raises(UserError, match=message):
        fx.parse(spec)


def test_combine_terms_and_regions():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    ctx = fx.EffectContext(sample_positions=pts, tracked_rest_positions=pts[[0, 3]])
    terms = fx.combine([fx.make("linear_drag", c=0.3), fx.make("linear_drag", c=0.2),
                        fx.make("wind", acceleration=[1, 0, 0]), fx.make("plasticity", yield_stress=5e3),
                        fx.parse("stiffness_region:factor=4,box=0.5,-1,-1,2,2,2")], ctx)
    assert terms.linear_drag == pytest.approx(0.5)
    assert terms.extra_acceleration.tolist() == [1, 0, 0]
    assert terms.yield_stress == 5e3 and not terms.is_base()
    assert terms.E_scale.tolist() == [1, 4, 1, 4]
    # a point region: samples whose nearest tracked point is in the list
    t2 = fx.combine([fx.parse("stiffness_region:factor=0.5,points=1")], ctx)
    assert t2.E_scale.tolist() == [1, 0.5, 0.5, 0.5] or t2.E_scale.tolist() == [1, 0.5, 1, 0.5] or t2.E_scale[3] == 0.5
    assert fx.combine([], ctx).is_base()
    assert math.isinf(fx.PhysicsTerms().yield_stress)


def test_scenario_roundtrip_and_errors():
    s = Scenario.from_dict({"format": "unipixie.measurement/1", "gravity": [0, 0, -9.8], "ground": None,
                            "initial_velocity": [1, 0, 0], "pinned_box": [[0, 0, 0], [1, 1, 0.1]],
                            "material": {"E": 1e5}, "my_key": 3})
    assert s.ground_height is None and s.extras == {"my_key": 3}
    again = Scenario.from_json(s.to_json())
    assert again.pinned_box.tolist() == [[0, 0, 0], [1, 1, 0.1]]
    assert again.pinned_mask(np.array([[0.5, 0.5, 0.05], [0.5, 0.5, 0.5]])).tolist() == [True, False]
    v = Scenario(initial_angular_velocity=[0, 0, 1]).initial_velocities(np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert np.allclose(v, [[0, 1, 0], [0, -1, 0]])
    with pytest.raises(UserError, match="'format'"):
        Scenario.from_dict({"format": "x"})
    with pytest.raises(UserError, match="'gravity'"):
        Scenario.from_dict({"format": "unipixie.measurement/1", "gravity": [0, 0]})
    with pytest.raises(UserError, match="'pinned_box'"):
        Scenario.from_dict({"format": "unipixie.measurement/1", "pinned_box": [[1, 1, 1], [0, 0, 0]]})
    with pytest.raises(UserError, match="'ground'"):
        Scenario.from_dict({"format": "unipixie.measurement/1", "ground": 3})
