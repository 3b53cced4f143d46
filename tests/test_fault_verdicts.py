"""Fault injection, no confident nonsense: contradictory measurements (ground above the object, all pinned,
milliseconds or frame numbers as seconds, gravity in mm/s², sentinels) are refused before fitting, and a model
far above the noise never "explains" a measurement."""

from __future__ import annotations

import numpy as np
import pytest

from unipixie.core import cli
from unipixie.core.errors import UserError
from unipixie.core.measurement import Measurement
from unipixie.solvers.scenario import Scenario

from fault_helpers import _falling_cube


# --------------------------------------------------------------------------- no confident nonsense
@pytest.mark.parametrize("case", ["ground_above", "all_pinned", "times_1e9", "sentinels", "milliseconds"])
def test_contradictory_measurements_are_refused_before_fitting(case):
    from unipixie.core.diagnosis import sanity

    m = _falling_cube()
    if case == "ground_above":
        m = _falling_cube(ground_height=10.0)
    elif case == "all_pinned":
        m = _falling_cube(pinned_box=[[-1, -1, -1], [1, 1, 1]])
    elif case == "times_1e9":
        m = Measurement(positions=m.positions * 1e9, times=m.times, scenario=m.scenario, rest_positions=m.rest * 1e9,
                        faces=m.faces, material=m.material)
    elif case == "sentinels":
        m.positions[5:7, :3] = -999999999.0
    elif case == "milliseconds":
        m = Measurement(positions=m.positions, times=m.times * 1000.0, scenario=m.scenario, rest_positions=m.rest,
                        faces=m.faces, material=m.material)
    with pytest.raises(UserError) as info:
        sanity.check(m, "spring_mass")
    assert len(str(info.value).splitlines()) == 1
    sanity.check(_falling_cube(), "spring_mass")  # the honest measurement passes


def test_milliseconds_can_be_forced_with_allow_long():
    from unipixie.core.diagnosis import sanity

    m = _falling_cube(frames=40, fps=1.0)  # 39 "seconds" of a solid at rest: the times were frame numbers
    still = np.repeat(m.rest[None], 40, axis=0)
    m2 = Measurement(positions=still, times=m.times, scenario=Scenario(ground_height=None, gravity=[0, 0, 0]),
                     rest_positions=m.rest, faces=m.faces, material=m.material)
    with pytest.raises(UserError, match="milliseconds"):
        sanity.check(m2, "lbs")
    warnings = sanity.check(m2, "lbs", allow_long=True)
    assert any("milliseconds" in w for w in warnings)


def test_a_model_far_above_the_noise_never_explains_the_measurement():
    from unipixie.core.diagnosis import verdict

    far = verdict.decide(0.122, 0.0024, None)
    assert far["code"] == "not_explained" and not far["explained"]
    assert "the model explains" not in far["sentence"] and "does NOT explain" in far["sentence"]
    partly = verdict.decide(0.05, 0.002, "linear_drag", added=["linear_drag"])
    assert partly["code"] == "effect_found_partly" and "does not explain" in partly["sentence"]
    near = verdict.decide(0.003, 0.002, None)
    assert near["code"] == "explained" and "explains these measurements" in near["sentence"]
    assert verdict.decide(float("nan"), 0.002, None)["code"] == "not_explained"


def test_five_frame_numbers_as_times_are_refused():
    from unipixie.core.diagnosis import sanity

    m = _falling_cube(frames=5)
    frames = Measurement(positions=m.positions, times=np.arange(5.0), scenario=m.scenario, rest_positions=m.rest,
                         faces=m.faces, material=m.material)  # 0..4 "s": was accepted (the rule wanted 10 s or more)
    with pytest.raises(UserError, match="look like frame numbers"):
        sanity.check(frames, "spring_mass")
    sanity.check(m, "spring_mass")


def test_gravity_in_millimetres_is_refused_and_an_odd_one_warned():
    from unipixie.core.diagnosis import sanity

    with pytest.raises(UserError, match="mm/s²"):  # was accepted: the model fell a thousand times too fast
        sanity.check(_falling_cube(gravity=[0, 0, -9810.0]), "spring_mass")
    assert any("gravity is 50" in w for w in sanity.check(_falling_cube(gravity=[0, 0, -50.0]), "spring_mass"))
    assert not any("gravity" in w for w in sanity.check(_falling_cube(), "spring_mass"))


def test_measure_show_says_what_a_diagnosis_would_refuse(tmp_path, capsys):
    m = _falling_cube()
    Measurement(positions=m.positions, times=m.times * 1000.0, scenario=m.scenario, rest_positions=m.rest,
                faces=m.faces, material=m.material).save(tmp_path / "ms.npz")
    assert cli.main(["measure", "show", str(tmp_path / "ms.npz")]) == 0
    assert "warning: unipixie diagnose would refuse it" in capsys.readouterr().out  # was silent
    m.save(tmp_path / "ok.npz")
    assert cli.main(["measure", "show", str(tmp_path / "ok.npz")]) == 0
    assert "refuse" not in capsys.readouterr().out


# --------------------------------------------------------------------------- no measurement without motion
def test_a_measurement_needs_two_instants_and_an_observed_sample():
    m = _falling_cube()
    with pytest.raises(UserError, match="at least two"):  # was accepted: `measure show` printed "valid"
        Measurement(positions=m.positions[:1], times=m.times[:1], scenario=m.scenario, rest_positions=m.rest)
    with pytest.raises(UserError, match="no observed sample"):  # was accepted: `measure convert` wrote it
        Measurement(positions=m.positions * np.nan, times=m.times, scenario=m.scenario, rest_positions=m.rest)


# --------------------------------------------------------------------------- a scenario that contradicts the motion
def _resting_cube(**scenario) -> Measurement:
    """A cube resting on the ground (its lowest face on z = ground) for 20 instants at 50 fps, noise 0.1 mm."""
    from fault_helpers import CUBE, CUBE_FACES
    from unipixie.core.measurement import MeasuredMaterial

    t = np.arange(20) / 50.0
    pos = np.repeat(CUBE[None], 20, axis=0) + np.random.default_rng(1).normal(0.0, 1e-4, (20,) + CUBE.shape)
    sc = Scenario(**{"ground_height": float(CUBE[:, 2].min()), **scenario})
    return Measurement(positions=pos, times=t, scenario=sc, rest_positions=CUBE.copy(), faces=CUBE_FACES,
                       material=MeasuredMaterial(2e5, 0.3, 1000.0))


@pytest.mark.parametrize("case, words", [
    ("density_1e9", "denser than any solid"),
    ("E_1e15", "stiffer than any solid"),
    ("velocity_3e8", "initial motion"),
    ("spin_1e9", "initial motion"),
    ("gravity_up_on_the_ground", "points up"),
])
def test_a_stated_scenario_the_motion_contradicts_is_refused(case, words):
    """Each of these ran a whole diagnosis before and ended in a verdict: density 1e9 kg/m³ and gravity of the
    wrong sign were 'explained' by a wind (exit 0), a 3e8 m/s throw 'not explained' after many minutes."""
    from unipixie.core.diagnosis import sanity
    from unipixie.core.measurement import MeasuredMaterial

    m = _falling_cube()
    if case == "density_1e9":
        m.material = MeasuredMaterial(2e5, 0.3, 1e9)
    elif case == "E_1e15":
        m.material = MeasuredMaterial(1e15, 0.3, 1000.0)
    elif case == "velocity_3e8":
        m = _falling_cube(initial_velocity=[3e8, 0.0, 0.0])
    elif case == "spin_1e9":
        m = _falling_cube(initial_angular_velocity=[0.0, 0.0, 1e9])
    elif case == "gravity_up_on_the_ground":
        m = _resting_cube(gravity=[0.0, 0.0, 9.81])
    with pytest.raises(UserError, match=words) as info:
        sanity.check(m, "spring_mass")
    assert len(str(info.value).splitlines()) == 1


def test_plausible_scenarios_near_those_refusals_pass():
    from unipixie.core.diagnosis import sanity
    from unipixie.core.measurement import MeasuredMaterial

    sanity.check(_resting_cube(), "spring_mass")                                # resting, gravity down
    sanity.check(_resting_cube(gravity=[0.0, 0.0, 9.81], ground_height=None), "spring_mass")   # no ground to leave
    sanity.check(_falling_cube(gravity=[0.0, 0.0, 9.81]), "spring_mass")        # far above its ground
    sanity.check(_falling_cube(initial_velocity=[20.0, 0.0, 0.0]), "spring_mass")  # could stop in 0.2 m
    m = _falling_cube()
    m.material = MeasuredMaterial(1.2e12, 0.1, 22590.0)                        # diamond's E, osmium's density
    assert sanity.check(m, "spring_mass", estimate_cost=False) == []          # (its cost is another matter)


@pytest.mark.parametrize("field, value, words", [("density", 1.0, "g/cm³"), ("E", 0.2, "pascals")])
def test_a_material_in_the_wrong_unit_is_warned(field, value, words):
    from unipixie.core.diagnosis import sanity
    from unipixie.core.measurement import MeasuredMaterial

    m = _falling_cube()
    values = {"E": 2e5, "nu": 0.3, "density": 1000.0, field: value}
    m.material = MeasuredMaterial(values["E"], values["nu"], values["density"])
    warnings = sanity.check(m, "spring_mass")
    assert any(words in w for w in warnings), warnings


def test_a_misspelt_scenario_key_is_named_and_an_own_key_is_kept_quietly(tmp_path):
    import json

    from unipixie.core import measurement

    m = _falling_cube()
    scenario = {"format": "unipixie.measurement/1", "gravity": [0, 0, -9.81], "ground": {"height": -1.0},
                "initial_velocty": [1.5, 0, 0], "camera_rig": "left", "material": {"E": 2e5, "nu": 0.3,
                                                                                 "density": 1000.0, "densty": 900}}
    path = tmp_path / "m.npz"
    np.savez(path, positions=m.positions, times=m.times, rest_positions=m.rest, scenario=np.array(json.dumps(scenario)))
    loaded = measurement.load(path)
    text = " | ".join(loaded.warnings)
    assert "'initial_velocty'" in text and "did you mean 'initial_velocity'" in text
    assert "did you mean 'material.density'" in text
    assert "camera_rig" not in text
    assert loaded.scenario.extras.get("camera_rig") == "left"          # kept, as the format says


def test_a_sentinel_coordinate_beyond_any_distance_is_refused_when_read():
    m = _falling_cube()
    pos = m.positions.copy()
    pos[3, 2] = 1e308          # overflowed the noise estimate (σ printed as 0 mm) and its squares
    with pytest.raises(UserError, match="sentinel"):
        Measurement(positions=pos, times=m.times, scenario=m.scenario, rest_positions=m.rest, faces=m.faces,
                    material=m.material)
