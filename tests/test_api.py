"""The one-import Python API resolves every name to the function the CLI and the panel use."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest


def test_every_name_resolves_without_bpy():
    code = ("import sys; from unipixie.core import api\n"
            "names = [n for n in api.__all__ if n not in ('bake_object', 'clear_bake', 'scenario_from_scene')]\n"
            "[getattr(api, n) for n in names]\n"
            "print('bpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "False"


def test_same_objects_as_the_modules():
    from unipixie.core import api
    from unipixie.solvers import api as solver_api
    from unipixie.solvers import effects

    assert api.simulate is solver_api.simulate
    assert api.parse_effect is effects.parse
    with pytest.raises(AttributeError):
        api.no_such_thing


def test_simulate_through_the_api():
    import trimesh

    from unipixie.core import api

    body = api.Body.from_mesh(trimesh.creation.box([0.1, 0.1, 0.1]))
    body.mesh.apply_translation([0, 0, 1.0])
    body = api.Body.from_mesh(body.mesh)
    traj = api.simulate("spring_mass", body, api.HomogeneousMaterial(1e5, 0.3, 500), api.Scenario(ground_height=None),
                        np.linspace(0, 0.2, 5), settings={"anchors": 32})
    dz = traj.positions[-1, :, 2].mean() - traj.positions[0, :, 2].mean()
    assert dz == pytest.approx(-0.5 * 9.81 * 0.2 ** 2, rel=0.02)


@pytest.mark.blender
def test_blender_entry_points(blender):
    from unipixie.core import api

    assert callable(api.bake_object) and callable(api.clear_bake) and callable(api.scenario_from_scene)


@pytest.mark.parametrize("solver, settings", [("mpm", {"cells_across": 6}), ("spring_mass", {"anchors": 32}),
                                              ("lbs", {"handles": 4})])
def test_a_run_up_to_a_frame_is_the_start_of_the_full_run(solver, settings):
    """``Simulation.up_to(k)`` shares the prepared simulation and runs only its first k instants: the same positions
    as the full run's first k, bit for bit (CPU), through a bounce on the ground, alone and in a batch; the full
    simulation is untouched and a bad count is refused."""
    import trimesh

    from unipixie.core import api
    from unipixie.solvers import api as solver_api
    from unipixie.solvers import effects

    mesh = trimesh.creation.box([0.1, 0.1, 0.1])
    mesh.apply_translation([0.0, 0.0, 0.06])
    body = api.Body.from_mesh(mesh)
    frames = np.linspace(0.0, 0.24, 13)
    sim = solver_api.prepare(solver, body, api.HomogeneousMaterial(2e5, 0.3, 500),
                                 api.Scenario(ground_height=0.0), frames, settings=settings)
    drag = [effects.make("linear_drag", c=0.5)]
    full = sim.run_batch([[], drag])
    short = sim.up_to(7)
    assert short.frame_times.shape == (7,) and sim.frame_times.shape == (13,)
    part = short.run_batch([[], drag])
    for a, b in zip(full, part):
        assert b.positions.shape[0] == 7
        np.testing.assert_array_equal(b.positions, a.positions[:7])
    alone = sim.run(drag).positions  # a run alone against a run alone (LBS batches round differently)
    np.testing.assert_array_equal(short.run(drag).positions, alone[:7])
    assert np.ptp(full[0].positions[:7].mean(axis=1)[:, 2]) > 0.005  # its centre fell onto the ground
    np.testing.assert_array_equal(sim.run(drag).positions, alone)
    assert sim.up_to(13) is sim
    for bad in (0, 14):
        with pytest.raises(ValueError, match="frames must be"):
            sim.up_to(bad)
