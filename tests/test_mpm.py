"""MPM solver: API, set-up, re-runs, batching, determinism, tracked points, errors (CPU, small problems)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from unipixie.core.errors import CancelledError, SimulationDiverged, UserError
from unipixie.core.progress import Progress
from unipixie.core.types import GridGeometry, MaterialField
from unipixie.solvers import api
from unipixie.solvers import effects as fx
from unipixie.solvers import materials, mpm
from unipixie.solvers.body import Body
from unipixie.solvers.material_sampling import HomogeneousMaterial
from unipixie.solvers.scenario import Scenario

G = 9.81
JELLY = HomogeneousMaterial(1e5, 0.3, 1000.0, "jelly")


def lattice(counts, spacing, origin=(0.0, 0.0, 0.0)):
    """(prod(counts), 3) centres of a counts[0]×counts[1]×counts[2] lattice of pitch ``spacing``, metres."""
    idx = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    return np.asarray(origin, dtype=np.float64) + (idx + 0.5) * spacing


def cube(n=8, spacing=0.005, origin=(0.0, 0.0, 0.0), tracked=None):
    return Body(points=lattice((n, n, n), spacing, origin), point_volume=spacing ** 3, tracked_points=tracked)


def free(**kw):
    kw.setdefault("gravity", [0.0, 0.0, 0.0])
    kw.setdefault("ground_height", None)
    return Scenario(**kw)


# --------------------------------------------------------------------------- set-up and outputs
def test_mesh_body_is_filled_and_tracked_vertices_rotate_rigidly():
    """A spinning box mesh: particles fill its volume (within 1 %); its vertices, carried by the grid
    velocity, turn by ω t about the centre of mass (position error < 1 % of the box size after 1 rad)."""
    mesh = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    omega = 2.0
    frames = np.linspace(0.0, 0.5, 11)
    sim = mpm.prepare(Body.from_mesh(mesh), JELLY, free(initial_angular_velocity=[0, 0, omega]), frames,
                      settings={"cells_across": 8})
    assert sim.dx == pytest.approx(0.1 / 8)
    assert sim.particle_volume.sum() == pytest.approx(mesh.volume, rel=0.01)
    traj = sim.run([])
    assert traj.positions.shape == (11, len(mesh.vertices), 3) and traj.solver == "mpm"
    np.testing.assert_allclose(traj.positions[0], mesh.vertices, atol=1e-6)
    angle = omega * frames[-1]
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    centre = sim.sample_positions.mean(0)
    expected = (mesh.vertices - centre) @ rot.T + centre
    assert np.abs(traj.positions[-1] - expected).max() < 0.01 * 0.1
    meta = traj.meta
    assert meta["substeps_total"] == sum(meta["substeps"]) and len(meta["dt"]) == 10
    assert 0 < meta["dt_min"] <= meta["dt_max"] and meta["dx"] == sim.dx and meta["particles"] == sim.particle_count


def test_particle_states_for_baking():
    """particle_states: positions in the original particle order, velocities, and per-particle attributes."""
    frames = np.linspace(0.0, 0.1, 5)
    sim = mpm.prepare(cube(), JELLY, Scenario(gravity=[0, 0, -G], ground_height=-1.0), frames)
    region = fx.make("stiffness_region", factor=3.0, region={"box": [[-1, -1, -1], [0.02, 1, 1]]})
    traj = sim.run([region], particle_states=True)
    P = sim.particle_count
    assert traj.particle_positions.shape == (5, P, 3)
    np.testing.assert_allclose(traj.particle_positions[0], sim.sample_positions, atol=1e-6)
    attrs = traj.particle_attributes
    assert attrs["velocity"].shape == (5, P, 3) and attrs["volume_ratio"].shape == (5, P)
    assert attrs["material"].tolist() == [materials.get("jelly").id] * P
    inside = sim.sample_positions[:, 0] <= 0.02
    np.testing.assert_allclose(attrs["E"][inside], 3e5, rtol=1e-5)
    np.testing.assert_allclose(attrs["E"][~inside], 1e5, rtol=1e-5)
    # every particle fell g t²/2 (+ first-order stepping error)
    fall = traj.particle_positions[0, :, 2] - traj.particle_positions[-1, :, 2]
    assert np.allclose(fall, 0.5 * G * 0.1 ** 2, rtol=0.02)
    assert sim.run([]).particle_positions is None  # only on request


def test_grid_follows_the_material():
    """A 1 s fall (4.9 m) runs on a grid a few cells larger than the cube, not one spanning the fall."""
    frames = np.linspace(0.0, 1.0, 11)
    sim = mpm.prepare(cube(4, 0.025, origin=(0, 0, 10.0)), JELLY, Scenario(gravity=[0, 0, -G], ground_height=None),
                      frames)
    traj = sim.run([])
    assert traj.positions[-1, :, 2].mean() == pytest.approx(10.05 - 0.5 * G, abs=0.02)
    assert max(traj.meta["grid_dims"]) < 30  # the cube is 2 cells wide; the fall is 98 cells


def test_voxel_field_with_background_and_stationary_parts():
    """A MaterialField whose lower voxels are 'stationary', some 'background' (dropped), the rest jelly:
    background carries no particles, stationary material stays exactly, jelly above it settles on it."""
    geo = GridGeometry(resolution=4, origin=[0.0, 0.0, 0.0], voxel_size=0.025)
    occupancy = np.ones((4, 4, 4), bool)
    idx = np.argwhere(occupancy)
    cls = np.full(len(idx), materials.get("jelly").id)
    cls[idx[:, 2] == 0] = materials.get("stationary").id
    cls[(idx[:, 2] == 3) & (idx[:, 0] == 0)] = materials.get("background").id
    K = len(idx)
    field = MaterialField(geo, occupancy, np.full(K, 1e5), np.full(K, 0.3), np.full(K, 1000.0), cls)
    body = Body(points=lattice((8, 8, 8), 0.0125), point_volume=0.0125 ** 3)
    frames = np.linspace(0.0, 0.2, 5)
    sim = mpm.prepare(body, field, Scenario(gravity=[0, 0, -G], ground_height=None), frames)
    assert sim.particle_count == 512 - 32  # the 4 background voxels × 8 particles are not simulated
    assert not np.any(sim.material.material == materials.get("background").id)
    traj = sim.run([], particle_states=True)
    fixed = sim.material.material == materials.get("stationary").id
    assert sim.held[fixed].all() and not sim.held[~fixed].any()
    np.testing.assert_array_equal(traj.particle_positions[-1][fixed], traj.particle_positions[0][fixed])
    drop = traj.particle_positions[0][~fixed, 2] - traj.particle_positions[-1][~fixed, 2]
    assert drop.max() < 0.01  # held up by the stationary base, not falling 0.2 m
    assert np.all(np.isfinite(traj.positions))


def _jelly_on_stationary_layer(axis: int) -> MaterialField:
    """A 4³ field of 2.5 cm voxels: jelly (E 100 kPa, ν 0.3, 1000 kg/m³) whose first voxel layer along ``axis`` is
    the stationary class."""
    geo = GridGeometry(resolution=4, origin=[0.0, 0.0, 0.0], voxel_size=0.025)
    idx = np.argwhere(np.ones((4, 4, 4), bool))
    cls = np.where(idx[:, axis] == 0, materials.get("stationary").id, materials.get("jelly").id)
    K = len(idx)
    return MaterialField(geo, np.ones((4, 4, 4), bool), np.full(K, 1e5), np.full(K, 0.3), np.full(K, 1000.0), cls)


def test_rigid_mass_scattered_once_matches_every_substep():
    """The held rigid particles' mass goes to the grid once per grid placement (setting ``rigid_mass_once``, the
    default) or in every substep's P2G: the same trajectory up to float summation order, with the jelly swinging
    on a stationary base; the GPU-tuned scatter, which skips them the same way, gives it bitwise."""
    field = _jelly_on_stationary_layer(axis=2)
    points = lattice((8, 8, 8), 0.0125)
    body = Body(points=points, point_volume=0.0125 ** 3, tracked_points=points[::7])
    sc = Scenario(gravity=[0, 0, -G], ground_height=0.0, initial_velocity=[0.5, 0.0, 0.0])
    sim = mpm.prepare(body, field, sc, np.linspace(0.0, 0.1, 5))
    assert sim._rigid_particles == np.count_nonzero(sim.material.material == materials.get("stationary").id) == 128
    assert sim.settings.rigid_mass_once
    once = sim.run([])
    profile = sim.profile([])
    assert profile["rigid_mass"] > 0
    sim.settings = mpm.MPMSettings(rigid_mass_once=False)
    every = sim.run([])
    assert once.meta["substeps"] == every.meta["substeps"]
    moved = np.abs(every.positions[-1] - every.positions[0]).max()
    assert moved > 1e-3  # the jelly swings
    np.testing.assert_allclose(once.positions, every.positions, rtol=0, atol=1e-5 * moved)
    sim.settings = mpm.MPMSettings(p2g_scatter="warp")
    np.testing.assert_array_equal(sim.run([]).positions, once.positions)


def test_rigid_particles_sorted_last_are_left_out_of_the_substep_kernels(monkeypatch):
    """With one environment, ``rigid_mass_once`` and cell sorting, the held rigid particles are sorted after the
    others and P2G and G2P are launched over the others alone (and grid_update a row of nodes per CPU thread): the
    same trajectory, bitwise, as launching them over every particle in the plain cell order."""
    field = _jelly_on_stationary_layer(axis=2)
    points = lattice((8, 8, 8), 0.0125)
    body = Body(points=points, point_volume=0.0125 ** 3, tracked_points=points[::7])
    sc = Scenario(gravity=[0, 0, -G], ground_height=0.0, initial_velocity=[0.5, 0.0, 0.0])
    sim = mpm.prepare(body, field, sc, np.linspace(0.0, 0.1, 5))
    left_out = sim.run([])
    buf = sim._buffer_sets[1]
    rigid = np.asarray(sim._laws.numpy()["held"])[buf.particles["code"].numpy() % 16] != 0
    assert rigid.sum() == sim._rigid_particles == 128 and rigid[-128:].all()  # sorted last
    moving = sim.particle_count - 128
    M = len(body.tracked_points)
    dims = {name: cmd.bounds.size for name, cmd in next(iter(buf.commands.values())).launches}
    assert dims["p2g"] == moving and dims["g2p"] == moving + M
    assert dims["grid_update"] * buf.grid_dims[2] == int(np.prod(buf.grid_dims))
    monkeypatch.setattr(sim, "_moving_count", lambda E, N, tuning: N)
    every = sim.run([])
    buf = sim._buffer_sets[1]
    rigid = np.asarray(sim._laws.numpy()["held"])[buf.particles["code"].numpy() % 16] != 0
    assert not rigid[-128:].all()  # the plain cell order
    assert np.abs(every.positions[-1] - every.positions[0]).max() > 1e-3  # the jelly swings
    np.testing.assert_array_equal(left_out.positions, every.positions)


def test_rerun_with_rigid_parts_after_the_grid_grew_is_the_same():
    """A re-run starts on the grid arrays the first run grew (a jelly block flying away from a stationary one); the
    rigid mass, recorded per grid size, must land in the new arrays, not in the ones the first chunk used."""
    field = _jelly_on_stationary_layer(axis=0)
    points = lattice((8, 8, 8), 0.0125)
    points = points[(points[:, 0] < 0.025) | (points[:, 0] > 0.075)]  # two blocks, 5 cm apart
    sc = Scenario(gravity=[0, 0, -G], ground_height=None, initial_velocity=[2.0, 0.0, 1.0])
    sim = mpm.prepare(Body(points=points, point_volume=0.0125 ** 3), field, sc, np.linspace(0.0, 0.15, 4))
    first = sim.run([])
    start = sim._buffer_sets[1].grid_alloc
    assert sim._rigid_particles == 128
    assert np.abs(first.positions[-1] - first.positions[0]).max() > 0.2  # the jelly flew off; the grid grew
    np.testing.assert_array_equal(sim.run([]).positions, first.positions)
    assert sim._buffer_sets[1].grid_alloc == start


def test_clamped_tracked_points_do_not_move():
    frames = np.linspace(0.0, 0.2, 5)
    tracked = np.array([[0.001, 0.02, 0.02], [0.039, 0.02, 0.02]])
    sc = Scenario(gravity=[0, 0, -G], ground_height=None, pinned_box=[[-1, -1, -1], [0.01, 1, 1]])
    sim = mpm.prepare(cube(tracked=tracked), JELLY, sc, frames)
    assert sim.tracked_held.tolist() == [True, False]
    traj = sim.run([])
    np.testing.assert_array_equal(traj.positions[:, 0], np.repeat(tracked[:1].astype(np.float32), 5, axis=0))
    assert traj.positions[-1, 1, 2] < tracked[1, 2] - 1e-4  # the free end sags


# --------------------------------------------------------------------------- re-runs, batching, determinism
def test_rerun_with_other_effects_is_deterministic_and_independent():
    frames = np.linspace(0.0, 0.2, 6)
    sim = mpm.prepare(cube(origin=(0, 0, 0.05)), JELLY, Scenario(gravity=[0, 0, -G], ground_height=0.0), frames)
    first = sim.run([])
    dragged = sim.run([fx.make("linear_drag", c=5.0)])
    again = sim.run([])
    np.testing.assert_array_equal(first.positions, again.positions)  # bitwise: CPU runs are deterministic
    assert np.abs(dragged.positions - first.positions).max() > 1e-3


def test_elastic_only_kernel_matches_general_kernel(monkeypatch):
    """Runs of pure jelly use a P2G compiled for the elastic law only; the general kernel gives the same."""
    frames = np.linspace(0.0, 0.1, 4)
    sim = mpm.prepare(cube(origin=(0, 0, 0.02)), JELLY, Scenario(gravity=[0, 0, -G], ground_height=0.0,
                                                                 initial_angular_velocity=[1, 2, 0]), frames)
    assert sim._choose_p2g(np.array([np.inf])) is sim._k.p2g_elastic
    assert sim._choose_p2g(np.array([1e4])) is sim._k.p2g_general  # the plasticity effect needs the general law
    fast = sim.run([fx.make("material_damping", eta=1.0)])
    monkeypatch.setattr(sim, "_choose_p2g", lambda yield_stress: sim._k.p2g_general)
    general = sim.run([fx.make("material_damping", eta=1.0)])
    np.testing.assert_array_equal(fast.positions, general.positions)


def test_run_batch_equals_separate_runs():
    """Environments batched into one launch per kernel give the trajectories of separate runs."""
    frames = np.linspace(0.0, 0.15, 6)
    sim = mpm.prepare(cube(), JELLY, Scenario(gravity=[0, 0, -G], ground_height=0.0,
                                              initial_velocity=[0.5, 0, 0]), frames)
    env_effects = [[], [fx.make("linear_drag", c=3.0)], [fx.make("wind", acceleration=[2.0, 0, 0])],
                   [fx.make("ground_friction", mu=0.8), fx.make("material_damping", eta=5.0)],
                   [fx.make("stiffness_region", factor=4.0, region={"box": [[-1, -1, -1], [1, 1, 1]]})]]
    batch = sim.run_batch(env_effects)
    assert len(batch) == 5 and all(t.meta["batched"] and t.meta["environments"] == 5 for t in batch)
    for effects_i, traj in zip(env_effects, batch):
        single = sim.run(effects_i)
        np.testing.assert_allclose(traj.positions, single.positions, atol=1e-6)
        assert traj.meta["substeps"] == single.meta["substeps"]
    assert batch[4].meta["substeps_total"] > batch[0].meta["substeps_total"]  # stiffer: smaller time step


def test_alternating_batch_sizes_reuse_their_buffers_and_stay_bounded(monkeypatch):
    """A diagnosis alternates batch sizes: each size keeps its device arrays (same objects, same results, bitwise
    on the CPU) while they fit the cache budget; past it the least recently used sizes are freed."""
    frames = np.linspace(0.0, 0.1, 4)
    sim = mpm.prepare(cube(), JELLY, Scenario(gravity=[0, 0, -G], ground_height=0.0,
                                              initial_velocity=[0.5, 0, 0]), frames)
    drag = [fx.make("linear_drag", c=3.0)]
    one = sim.run(drag).positions
    pair = sim.run_batch([[], drag])[1].positions
    buffers_of_one = sim._buffer_sets[1]
    assert set(sim._buffer_sets) == {1, 2}
    np.testing.assert_array_equal(sim.run(drag).positions, one)
    assert sim._buffer_sets[1] is buffers_of_one
    np.testing.assert_array_equal(sim.run_batch([[], drag])[1].positions, pair)
    # a budget of about three single-environment sets: sizes 1 and 2 fill it, size 3 evicts the older ones
    per_env = sim.particle_count * mpm._BYTES_PER_PARTICLE
    monkeypatch.setattr(mpm, "BUFFER_CACHE_BYTES", 3 * per_env)
    sim.run_batch([[], drag, []])
    assert list(sim._buffer_sets) == [3]
    sim.run(drag)
    assert list(sim._buffer_sets) == [1]  # 3 + 1 sets exceed the budget: the older size goes


def test_api_dispatch_and_simulate():
    frames = np.linspace(0.0, 0.05, 3)
    sim = api.prepare("mpm", cube(), JELLY, free(), frames)
    assert isinstance(sim, mpm.MPMSimulation) and sim.solver == "mpm"
    traj = api.simulate("mpm", cube(), JELLY, free(initial_velocity=[1, 0, 0]), frames)
    assert traj.positions[-1, :, 0].mean() - traj.positions[0, :, 0].mean() == pytest.approx(0.05, rel=1e-3)


def test_progress_advances_per_frame_and_cancels():
    frames = np.linspace(0.0, 0.05, 6)
    sim = mpm.prepare(cube(), JELLY, free(), frames)
    seen = []
    sim.run([], progress=Progress(total=5, callback=lambda fraction, text: seen.append(fraction)))
    assert seen and seen[-1] == pytest.approx(1.0)
    progress = Progress(total=5, show_bar=False)
    progress.cancel()
    with pytest.raises(CancelledError):
        sim.run([], progress=progress)


# --------------------------------------------------------------------------- errors
def test_divergence_names_frame_count_and_remedy():
    """An explicitly unstable run (viscous time-step bound switched off) stops with SimulationDiverged."""
    frames = np.linspace(0.0, 0.2, 11)
    sim = mpm.prepare(cube(), JELLY, Scenario(gravity=[0, 0, -G], ground_height=0.0), frames,
                      settings={"viscous_cfl": 1e4})
    with pytest.raises(SimulationDiverged, match=r"frame \d+ \(t = .* s\): \d+ of \d+ particles.*(time step|max_dt)"):
        sim.run([fx.make("material_damping", eta=1e4)])
    tight = mpm.prepare(cube(), JELLY, free(), np.linspace(0.0, 1.0, 3), settings={"max_substeps_per_frame": 5})
    with pytest.raises(SimulationDiverged, match=r"frame 1 .* would need \d+ substeps"):
        tight.run([])


@pytest.mark.parametrize("settings, message", [
    ({"grid": 3}, "unknown MPM setting"),
    ({"dx": -0.1}, "'dx' must be positive"),
    ({"cfl": 2.0}, "'cfl' must be at most 1"),
    ({"material_sampling": "cubic"}, "material_sampling"),
    ({"deformation_gradient": "apic"}, "deformation_gradient.*affine.*grid"),
    ({"initial_deformation": np.diag([1.0, 1.0, -1.0])}, "positive determinant"),
    ({"max_particles": 100}, "max_particles"),
])
def test_bad_settings(settings, message):
    with pytest.raises(UserError, match=message):
        mpm.prepare(cube(), JELLY, free(), [0.0, 0.1], settings=settings)


def test_bad_inputs():
    frames = [0.0, 0.1]
    with pytest.raises(UserError, match="below the ground"):
        mpm.prepare(cube(origin=(0, 0, -0.02)), JELLY, Scenario(), frames)
    with pytest.raises(UserError, match="background"):
        mpm.prepare(cube(), HomogeneousMaterial(1e5, 0.3, 1000, "background"), free(), frames)
    with pytest.raises(UserError, match="strictly increasing"):
        mpm.prepare(cube(), JELLY, free(), [0.0, 0.2, 0.1])
    with pytest.raises(UserError, match="needs a Body"):
        mpm.prepare(np.zeros((5, 3)), JELLY, free(), frames)
    with pytest.raises(UserError, match="bad device name"):
        mpm.prepare(cube(), JELLY, free(), frames, device="tpu")
    with pytest.raises(UserError, match="point_volume"):
        mpm.prepare(Body(points=np.zeros((1, 3))), JELLY, free(), frames)
    with pytest.raises(UserError, match="too thin|no sample points"):
        mpm.prepare(Body.from_mesh(trimesh.creation.box(extents=(1.0, 1.0, 1e-4))), JELLY, free(), frames,
                    settings={"cells_across": 8})


def test_cuda_refused_without_a_gpu():
    from unipixie.solvers.warp_runtime import cuda_available

    if cuda_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(UserError, match="no CUDA device"):
        mpm.prepare(cube(), JELLY, free(), [0.0, 0.1], device="cuda")


def test_grid_deformation_gradient_moves_the_material_alike_in_both_g2p_layouts():
    """``deformation_gradient = "grid"`` (the default: F from the gradient of the grid's velocity, updated in G2P)
    changes the motion against ``"affine"`` (APIC's C) — slightly, on a cube tumbling onto the ground, with and without
    plasticity (the general law) — and the split G2P layout of the GPU (``split_g2p``) gives the same bits."""
    scenario = Scenario(gravity=[0, 0, -G], ground_height=0.0, initial_velocity=[0.3, 0, -0.5],
                        initial_angular_velocity=[0, 3.0, 0])
    sim = mpm.prepare(cube(n=6, origin=(0.0, 0.0, 0.002)), JELLY, scenario, np.linspace(0.0, 0.08, 5))
    envs = [[], [fx.make("plasticity", yield_stress=2e3)]]
    grid = sim.run_batch(envs)
    sim.settings = mpm.MPMSettings(deformation_gradient="affine")
    affine = sim.run_batch(envs)
    sim.settings = mpm.MPMSettings(deformation_gradient="grid")
    assert [g.positions.tolist() for g in grid] == [g.positions.tolist() for g in sim.run_batch(envs)]
    sim.settings = mpm.MPMSettings(deformation_gradient="grid", split_g2p=True)
    split = sim.run_batch(envs)
    for a, g, s in zip(affine, grid, split):
        np.testing.assert_array_equal(g.positions, s.positions)
        moved = np.abs(g.positions - a.positions).max()
        assert 1e-6 < moved < 2e-3, moved  # a different discretisation of the same continuum
