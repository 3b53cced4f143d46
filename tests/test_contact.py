"""The one contact law (solvers/contact.py), honoured by all three solvers, against closed forms.

Fast versions of docs/fidelity.md's drop and slide at coarse resolutions: nothing goes below the ground
(≤ PENETRATION_TOLERANCE), free fall until the first contact matches √(2h/g), the ``contact_damping``
effect takes energy in every solver (a lower rebound), and Coulomb friction
stops a slide at v²/(2μg).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from unipixie.core.benchmarks import _scenes
from unipixie.solvers import api
from unipixie.solvers import effects as fx
from unipixie.solvers.contact import PENETRATION_TOLERANCE, clamp_to_ground

COARSE = {"mpm": {"cells_across": 10}, "spring_mass": {"anchors": 192}, "lbs": {"cubature_points": 120}}
SOLVERS = tuple(COARSE)


def _drop_run(solver, effects=(), duration=0.26):
    sc = _scenes.scene("drop")
    times = sc.frame_times[sc.frame_times <= duration + 1e-9][::4]  # 4 ms frames
    traj = api.simulate(solver, sc.body, sc.material, sc.scenario, times, list(effects), settings=COARSE[solver])
    return sc, traj


@pytest.fixture(scope="module")
def drops():
    return {s: _drop_run(s) for s in SOLVERS}


def test_clamp_to_ground_copies_and_lifts():
    p = np.array([[0.0, 0.0, -0.2], [0.0, 0.0, 0.3]])
    q = clamp_to_ground(p, 0.0)
    assert q[0, 2] == 0.0 and q[1, 2] == 0.3 and p[0, 2] == -0.2
    assert np.array_equal(clamp_to_ground(p, None), p)


@pytest.mark.parametrize("solver", SOLVERS)
def test_drop_never_below_the_ground_and_falls_freely_until_contact(drops, solver):
    sc, traj = drops[solver]
    z = traj.positions[..., 2]
    assert z.min() >= -PENETRATION_TOLERANCE, f"{solver}: a tracked point {1e3 * -z.min():.2f} mm below the ground"
    m = sc.measure(traj)
    # the first contact at √(2h/g) = 0.1428 s, to a frame (4 ms)
    assert m["first_contact"] == pytest.approx(math.sqrt(2 * _scenes.DROP_HEIGHT / _scenes.G), abs=0.0045)
    assert np.isfinite(m["rebound_peak"]) and m["rebound_peak"] > _scenes.CUBE_SIZE / 2  # it leaves the floor again


@pytest.mark.parametrize("solver", SOLVERS)
def test_contact_damping_takes_energy_in_every_solver(drops, solver):
    sc, base = drops[solver]
    rise = []
    # both dampers below the rigid cube's critical contact damping 2√(k ρ h) = 2.8e4 Pa·s/m (0.2 m, 1000 kg/m³).
    # The rebound is not monotonic in c: the solid's waves reflect at the damped floor many times during a
    # contact, and a damper near the solid's impedance ρ c_p (1.6e4 Pa·s/m) absorbs a wave best, one far
    # above it is as stiff as a wall (measured: MPM's centre rises 0 mm above rest at c = 3e3, 2 mm at 1e4).
    for c in (3e3, 1e4):
        _, traj = _drop_run(solver, [fx.make("contact_damping", c=c, k=1e6)])
        assert traj.positions[..., 2].min() >= -PENETRATION_TOLERANCE
        rise.append(traj.positions[:, :, 2].mean(1)[-20:].max())
    base_rise = base.positions[:, :, 2].mean(1)[-20:].max()
    rest = _scenes.CUBE_SIZE / 2
    # a lower rebound with either damper (heights of the centre above rest, late in the run)
    for r in rise:
        assert r - rest < 0.8 * (base_rise - rest), (solver, base_rise, rise)


@pytest.mark.parametrize("solver", SOLVERS)
def test_coulomb_slide_stops_at_the_closed_form(solver):
    sc = _scenes.scene("slide")
    traj = api.simulate(solver, sc.body, sc.material, sc.scenario, sc.frame_times[::2], sc.effects,
                        settings=COARSE[solver])
    got = sc.measure(traj)["stopping_distance"]
    ref = sc.reference["stopping_distance"][0]
    assert got == pytest.approx(ref, rel=0.05), (solver, got, ref)
    assert traj.positions[..., 2].min() >= -PENETRATION_TOLERANCE


def test_lbs_stiff_contact_at_the_default_step_gains_no_energy(monkeypatch):
    """A stiff block (35 MPa, ν 0.45) dropped at LBS's default 5 ms step: the contact spring is capped at
    ω Δt ≤ IMPLICIT_MAX_CONTACT_RATE (uncapped, ω Δt ~ 10², the demo's duck flew off); its centre never rises
    above where it started."""
    import trimesh

    from unipixie.solvers import lbs
    from unipixie.solvers.body import Body
    from unipixie.solvers.material_sampling import HomogeneousMaterial
    from unipixie.solvers.scenario import Scenario

    mesh = trimesh.creation.box(extents=(0.1, 0.08, 0.06))
    mesh.apply_translation((0, 0, 0.15))
    times = np.linspace(0.0, 0.8, 21)
    traj = api.simulate("lbs", Body.from_mesh(mesh), HomogeneousMaterial(3.5e7, 0.45, 300.0),
                        Scenario(ground_height=0.0, initial_velocity=[0.8, 0.0, 0.0]), times, [],
                        settings={"cubature_points": 120, "collision_points": 64})
    com = traj.positions[:, :, 2].mean(1)
    assert np.all(np.isfinite(com)) and com.max() <= com[0] + 1e-3, com
    assert traj.positions[..., 2].min() >= -PENETRATION_TOLERANCE
