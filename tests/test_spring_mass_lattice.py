"""The spring-mass lattice layout (solvers/spring_mass_lattice.py): a network that keeps the body's mirror symmetries,
and a cube dropped flat that lands without turning (docs/spring_mass.md, "The lattice layout")."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from unipixie.core.benchmarks import _scenes as scenes
from unipixie.core.errors import UserError
from unipixie.solvers import api
from unipixie.solvers.body import Body
from unipixie.solvers.spring_mass_lattice import lattice_springs
from unipixie.solvers.spring_mass_settings import SpringMassSettings


def _mirror_map(points: np.ndarray, centre: np.ndarray, axis: int) -> np.ndarray:
    """Index of each point's mirror image across the plane through ``centre`` normal to ``axis`` (exact)."""
    mirrored = points.copy()
    mirrored[:, axis] = 2.0 * centre[axis] - mirrored[:, axis]
    dist, index = cKDTree(points).query(mirrored)
    assert dist.max() < 1e-12, f"axis {axis}: a point has no mirror image ({dist.max():.3g} m off)"
    return index


def _drop(layout: str, anchors: int, duration: float = 0.3):
    scene = scenes.scene("drop")
    frames = np.linspace(0.0, duration, int(round(duration / 0.005)) + 1)
    sim = api.prepare("spring_mass", scene.body, scene.material, scene.scenario, frames, device="cpu",
                      settings={"anchors": anchors, "layout": layout})
    return scene, sim, sim.run(scene.effects, particle_states=True)


def _spin_after_first_contact(sim, traj) -> float:
    """|ω| (rad/s) of the anchors about their centre of mass at the run's end (in flight after the first contact):
    mass-weighted angular momentum over the moment of inertia about the axis of ω."""
    x = traj.particle_positions[-1].astype(np.float64)
    v = traj.particle_attributes["velocity"][-1].astype(np.float64)
    m = sim.network.mass
    r = x - (m[:, None] * x).sum(0) / m.sum()
    u = v - (m[:, None] * v).sum(0) / m.sum()
    L = (m[:, None] * np.cross(r, u)).sum(0)
    inertia = (m[:, None, None] * (np.einsum("ij,ij->i", r, r)[:, None, None] * np.eye(3)
                                   - r[:, :, None] * r[:, None, :])).sum(0)
    return float(np.linalg.norm(np.linalg.solve(inertia, L)))


def test_the_lattice_network_of_a_box_is_its_own_mirror_image():
    scene, sim, _ = _drop("lattice", 125, duration=0.01)
    net = sim.network
    centre = np.array([0.0, 0.0, scenes.DROP_HEIGHT + scenes.CUBE_SIZE / 2])
    assert net.count == 125  # 5 × 5 × 5, the count nearest the one asked that a cubic lattice allows
    springs = {tuple(s): r for s, r in zip(np.sort(net.springs, axis=1).tolist(), net.rank.tolist())}
    start, offsets = sim._d_cell_start.numpy(), sim._d_cell_offsets.numpy()
    lowest = np.array([offsets[start[i]:start[i + 1], 2].min() for i in range(net.count)])  # each cell's lowest point
    for axis in range(3):
        image = _mirror_map(net.anchors, centre, axis)
        np.testing.assert_allclose(net.mass[image], net.mass, rtol=1e-12)
        np.testing.assert_allclose(net.volume[image], net.volume, rtol=1e-12)
        np.testing.assert_allclose(sim.stiffness[image], sim.stiffness, rtol=1e-12)
        mirrored = {tuple(sorted((int(image[i]), int(image[j])))): r for (i, j), r in springs.items()}
        assert mirrored == springs, f"axis {axis}: the springs or their ranks are not mirror images"
        if axis < 2:  # the floor's contact cells (a mirror across z swaps lowest and highest points)
            np.testing.assert_allclose(lowest[image], lowest, atol=1e-6)


def test_a_cube_dropped_flat_lands_without_turning_on_the_lattice_and_turns_on_farthest_points():
    """The continuum (and the referee, and MPM on its grid) lands a cube dropped flat without turning; an uneven
    network is pushed off-centre by the floor.  Measured: lattice 0 to four digits, farthest points 0.07-0.5 rad/s
    (192-2048 anchors)."""
    _, sim, traj = _drop("lattice", 125)
    assert _spin_after_first_contact(sim, traj) < 1e-3
    _, sim_fps, traj_fps = _drop("farthest", 192)
    assert _spin_after_first_contact(sim_fps, traj_fps) > 0.03  # the artefact the lattice removes
    low = traj.positions[..., 2].min()
    assert low > -1e-3  # nothing below the floor
    assert traj.positions[-1, :, 2].mean() > scenes.CUBE_SIZE / 2 + 0.02  # it bounced


def test_lattice_springs_join_a_cubic_lattice_s_first_four_shells_with_shared_ranks():
    ijk = np.stack(np.meshgrid(*[np.arange(-3, 4)] * 3, indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
    springs, rank = lattice_springs(0.01 * ijk, 32)
    centre = int(np.flatnonzero(np.all(ijk == 0, axis=1))[0])
    mine = np.any(springs == centre, axis=1)
    other = springs[mine].sum(axis=1) - centre
    shell = np.round(np.sum(ijk[other] ** 2, axis=1)).astype(int)  # squared distance in lattice units
    # its own 32 nearest are the first four shells, whole (6 + 12 + 8 + 6); anchors nearer the lattice's edge have
    # fewer near neighbours, reach farther, and bring it springs from farther shells (one spring per pair)
    assert np.bincount(shell, minlength=5)[1:5].tolist() == [6, 12, 8, 6]
    for sq, first_rank in ((1, 0), (2, 6), (3, 18), (4, 26)):  # a shell shares its rank (or a lower one of the pair)
        assert np.all(rank[mine][shell == sq] <= first_rank)
    assert np.all(rank[mine][shell == 1] == 0)


def test_lattice_layout_refuses_what_it_cannot_do():
    with pytest.raises(UserError, match="farthest"):
        SpringMassSettings(layout="lattice", stiffness=np.ones(10)).check()
    with pytest.raises(UserError):
        SpringMassSettings(layout="hexagonal").check()
    points = np.random.default_rng(0).uniform(0, 0.1, (200, 3))
    body = Body(points=points, point_volume=1e-6)
    scene = scenes.scene("drop")
    with pytest.raises(UserError, match="closed mesh"):
        api.prepare("spring_mass", body, scene.material, scene.scenario, np.linspace(0, 0.01, 3), device="cpu",
                    settings={"anchors": 27, "layout": "lattice"})
