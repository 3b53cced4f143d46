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
