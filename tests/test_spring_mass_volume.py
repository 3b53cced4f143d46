"""The spring-mass network's volumetric term: the material's Poisson ratio (solvers/spring_mass*.py, issue 17).

Springs scaled to the material's shear modulus plus ½ V λ_extra (J − 1)² per anchor star give the network the
material's (E, ν) instead of a central-force network's ν = 1/4.  CPU, small networks.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import trimesh

from unipixie.core.benchmarks import _scenes
from unipixie.core.errors import UserError
from unipixie.solvers import spring_mass as sm
from unipixie.solvers import spring_mass_linear as linear
from unipixie.solvers import spring_mass_network as network
from unipixie.solvers.body import Body
from unipixie.solvers.material_sampling import HomogeneousMaterial
from unipixie.solvers.scenario import Scenario

CUBE = 0.2


def cube_sim(nu: float, anchors: int, volumetric: bool = True, E: float = 2e5):
    body = Body.from_mesh(trimesh.creation.box(extents=(CUBE, CUBE, CUBE)))
    return sm.prepare(body, HomogeneousMaterial(E, nu, 1000.0), Scenario(gravity=[0, 0, 0], ground_height=None),
                      [0.0, 0.01], settings={"anchors": anchors, "volumetric": volumetric})


def kernel_forces(sim, positions: np.ndarray) -> np.ndarray:
    """(N, 3) N: the solver's elastic forces on every anchor at ``positions`` (N, 3) m, from its own kernels (the
    first pass, then the velocity kick with unit inverse mass, τ = 1 s, no body force, no dashpots: v_out = f)."""
    from unipixie.solvers import spring_mass_kernels as K
    from unipixie.solvers.warp_runtime import init_warp

    wp = init_warp()
    n = sim.network.count
    slots = sim._slots["slot_spring"]
    kappa = sim._kappa(sim.stiffness)[slots]
    vol = sim.volume_unit * sim.youngs_modulus
    s = len(kappa)
    arr = lambda a, dtype=float: wp.array(np.asarray(a), dtype=dtype, device="cpu")  # noqa: E731
    x = arr(np.asarray(positions, np.float64)[None].astype(np.float32), wp.vec3)
    v = wp.zeros((1, n), dtype=wp.vec3, device="cpu")
    stress = wp.zeros((1, n), dtype=wp.mat33, device="cpu")
    force = wp.zeros((1, len(sim._he_src)), dtype=wp.vec3, device="cpu")
    wp.launch_tiled(K.spring_star_pass, dim=(1, n), device="cpu", block_dim=1,
                    inputs=[x, v, sim._d_start, sim._d_nbr, sim._d_rest_vec, sim._d_slot_start, sim._d_slot_nbr,
                            sim._d_slot_he, arr(sim.network.rest_length[slots][None]), arr(kappa[None]),
                            arr(np.zeros((1, s))), arr(np.full((1, s), K.BIG)), sim._d_gram_inv, arr(vol[None]), force,
                            stress, 0, 0])
    v_out = wp.zeros((1, n), dtype=wp.vec3, device="cpu")
    wp.launch(K.velocity_kick, dim=(1, n), device="cpu",
              inputs=[v, v_out, sim._d_start, sim._d_nbr, force, sim._d_rest_vec, arr(np.ones(n)),
                      arr(np.zeros((1, 3)), wp.vec3), arr([0.0]), arr([0.0]), stress, int(np.any(vol > 0)), 1.0])
    return v_out.numpy()[0].astype(np.float64)


def test_poisson_split_gives_the_material_moduli():
    """Springs scaled by 1.25 / (1 + ν) carry μ(E, ν) and their own λ = μ; λ_extra brings λ to λ(E, ν); ν below
    1/4 runs as the springs-only network, ν above the cap at the cap."""
    E = 1.0
    nu = np.array([0.1, 0.25, 0.3, 0.4, 0.49])
    factor, lam_x = network.poisson_split(nu)
    mu_springs = factor * E / (2 * 1.25)  # the springs alone: E_net = E · factor at ν 1/4, μ = E_net / 2.5
    v = np.clip(nu, 0.25, network.MAX_NETWORK_POISSON_RATIO)
    np.testing.assert_allclose(mu_springs, E / (2 * (1 + v)), rtol=1e-12)
    np.testing.assert_allclose(mu_springs + lam_x, E * v / ((1 + v) * (1 - 2 * v)), rtol=1e-12)
    assert factor[0] == 1.0 and lam_x[0] == 0.0 and lam_x[1] == 0.0
    assert lam_x[-1] == network.poisson_split(network.MAX_NETWORK_POISSON_RATIO)[1]
    with pytest.raises(UserError):
        sm.SpringMassSettings(volumetric="yes")
    capped = cube_sim(0.49, 60)
    np.testing.assert_allclose(capped.poisson_ratio, network.MAX_NETWORK_POISSON_RATIO)
    assert any("runs as 0.45" in w for w in capped.warnings)


def test_forces_are_the_energy_gradient_and_conserve_momentum():
    """At a random deformation the kernels' forces are −∂(spring + volumetric energy)/∂x (central differences of
    :meth:`energy`), sum to zero and exert no torque; the volumetric term carries a good part of them."""
    sim = cube_sim(0.4, 120)
    x0 = sim.network.anchors
    rng = np.random.default_rng(1)
    x = x0 * np.array([1.04, 0.97, 0.93]) + rng.normal(0, 2e-3, x0.shape)
    f = kernel_forces(sim, x)
    zero_v = np.zeros_like(x)
    h = 1e-6
    for i in rng.choice(sim.network.count, 6, replace=False):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, c] += h
            xm[i, c] -= h
            grad = (sim.energy(xp, zero_v)["elastic"] - sim.energy(xm, zero_v)["elastic"]) / (2 * h)
            assert abs(f[i, c] + grad) < 2e-3 * np.abs(f).max(), (i, c, f[i, c], -grad)
    scale = np.abs(f).max()
    np.testing.assert_allclose(f.sum(0), 0.0, atol=1e-4 * scale * len(f) ** 0.5)
    np.testing.assert_allclose(np.cross(x, f).sum(0), 0.0, atol=1e-4 * scale * len(f) ** 0.5 * CUBE)
    springs_only = kernel_forces(cube_sim(0.4, 120, volumetric=False), x)
    assert np.abs(f - springs_only).max() > 0.2 * scale


def test_rigid_rotation_stores_no_energy():
    """A rigidly rotated (and moved) network: every star's J is 1, no elastic energy, no force; the same stars
    compressed by 1 % do store volumetric energy."""
    sim = cube_sim(0.4, 120)
    x0 = sim.network.anchors
    a = 1.1
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ \
        np.array([[1, 0, 0], [0, np.cos(0.7), -np.sin(0.7)], [0, np.sin(0.7), np.cos(0.7)]])
    x = x0 @ R.T + np.array([0.3, -0.1, 0.5])
    np.testing.assert_allclose(sim.star_volume_ratio(x), 1.0, atol=1e-9)
    assert sim.energy(x, np.zeros_like(x))["elastic"] < 1e-15
    squeezed = x0 * 0.99
    e_sq = sim.energy(squeezed, np.zeros_like(x))["elastic"]
    e_sq_springs = cube_sim(0.4, 120, volumetric=False).energy(squeezed, np.zeros_like(x))["elastic"]
    assert e_sq > 1.5 * e_sq_springs * sim.spring_factor.mean()  # the volumetric energy is there
    f_rot = kernel_forces(sim, x)
    f_sq = kernel_forces(sim, squeezed)
    assert np.abs(f_rot).max() < 1e-3 * np.abs(f_sq).max()


@pytest.mark.parametrize("nu", [0.3, 0.4])
def test_lateral_contraction_is_the_materials_poisson_ratio(nu):
    """A 512-anchor cube stretched along z between frictionless grips (its top and bottom tenth held in z only,
    linear statics with :mod:`.spring_mass_linear`): the middle's lateral strain over its axial strain is the
    material's ν (measured 0.297 at ν 0.3, 0.381 at ν 0.4), not the central-force network's 1/4 (0.248 without
    the term), and the axial stiffness stays the material's E (within 2 % of the springs-only network's)."""
    out = {}
    for volumetric in (True, False):
        sim = cube_sim(nu, 512, volumetric)
        K = linear.stiffness_matrix(sim)
        X = sim.network.anchors
        z = X[:, 2]
        h = np.ptp(z)
        grip = (z > z.max() - 0.1 * h) | (z < z.min() + 0.1 * h)
        held = np.zeros(3 * len(X), bool)
        held[3 * np.flatnonzero(grip) + 2] = True
        u = np.zeros(3 * len(X))
        u[held] = 1e-3 * (z[grip] - z.mean())
        free = ~held
        Kff = K[free][:, free] + sp.identity(int(free.sum())) * 1e-9 * K.diagonal().mean()  # x, y, spin: rigid
        u[free] = sla.spsolve(Kff.tocsc(), -(K[free][:, held] @ u[held]))
        U = u.reshape(-1, 3)
        mid = np.abs(z - z.mean()) < 0.3 * h
        A = np.c_[X[mid] - X[mid].mean(0), np.ones(mid.sum())]
        grad = np.stack([np.linalg.lstsq(A, U[mid, c], rcond=None)[0][:3] for c in range(3)])
        nu_measured = -0.5 * (grad[0, 0] + grad[1, 1]) / grad[2, 2]
        axial = (K @ u).reshape(-1, 3)[z > z.max() - 0.1 * h, 2].sum()
        out[volumetric] = nu_measured, axial
    print(f"ν {nu}: measured {out[True][0]:.4f} (springs only {out[False][0]:.4f}), axial ratio "
          f"{out[True][1] / out[False][1]:.4f}")
    assert abs(out[False][0] - 0.25) < 0.01
    assert abs(out[True][0] - nu) < 0.01 + 0.15 * (nu - 0.3)
    assert abs(out[True][1] / out[False][1] - 1) < 0.02


def test_drop_rebound_falls_with_poisson_ratio_as_the_referees_does():
    """The canonical drop at 512 anchors: at ν 0.3 the network rebounds lower than at ν 1/4, as the referee's
    continuum does (penalty floor, 12 cells: 0.1689 → 0.1638 m, −5.1 mm; hard floor −3.9 mm); measured
    0.1709 → 0.1665 m (−4.4 mm).  At ν 1/4 the term is absent: the springs-only network's rebound."""
    scene = _scenes.scene("drop")
    peaks = {}
    for nu, volumetric in ((0.25, True), (0.3, True), (0.3, False)):
        traj = sm.prepare(scene.body, HomogeneousMaterial(_scenes.CUBE_E, nu, _scenes.CUBE_DENSITY), scene.scenario,
                          scene.frame_times, settings={"anchors": 512, "volumetric": volumetric}).run(scene.effects)
        peaks[nu, volumetric] = scene.measure(traj)["rebound_peak"]
    print("rebound peaks", peaks)
    assert abs(peaks[0.25, True] - peaks[0.3, False]) < 2e-4  # ν 1/4: springs only, whatever the setting
    assert 0.003 < peaks[0.25, True] - peaks[0.3, True] < 0.007


def test_flat_stars_run_with_springs_only():
    """A plate one or two anchors thick (96 anchors in 0.3 × 0.3 × 0.05 m): its stars cannot measure a volume
    change, so those anchors run springs-only (ν = 1/4, the springs-only network's spring constants), with a
    warning; a cube of the same material gets the term at every anchor."""
    plate = Body.from_mesh(trimesh.creation.box(extents=(0.3, 0.3, 0.05)))
    mat = HomogeneousMaterial(5e5, 0.3, 1000.0)
    on = sm.prepare(plate, mat, Scenario(), [0.0, 0.01], settings={"anchors": 96})
    off = sm.prepare(plate, mat, Scenario(), [0.0, 0.01], settings={"anchors": 96, "volumetric": False})
    assert np.all(on.network.star_isotropy() < network.MIN_STAR_ISOTROPY)
    np.testing.assert_array_equal(on.poisson_ratio, 0.25)
    np.testing.assert_array_equal(on.volume_unit, 0.0)
    np.testing.assert_allclose(on.spring_kappa, off.spring_kappa, rtol=1e-12)
    assert any("too flat" in w for w in on.warnings)
    cube = cube_sim(0.3, 96)
    np.testing.assert_allclose(cube.poisson_ratio, 0.3)
    assert np.all(cube.volume_unit > 0) and not any("too flat" in w for w in cube.warnings)


def test_substep_bound_covers_the_volumetric_stiffness():
    """The volumetric term's per-anchor bound (stable_substep) is at least the largest eigenvalue of M⁻¹ K_vol
    (K_vol = Bᵀ diag(V λ_extra) B, linearised at rest) and not far above it (measured 6.4× at ν 0.45, 120 anchors;
    the springs' Gershgorin bound is 4–6× above their largest eigenvalue), and it
    shortens the substep of a ν 0.45 network."""
    sim = cube_sim(0.45, 120)
    s = sim.volume_unit * sim.youngs_modulus
    B = linear.volume_gradient_matrix(sim)
    m = np.repeat(sim.network.mass, 3)
    Kv = sp.diags(m ** -0.5) @ (B.T @ sp.diags(s) @ B) @ sp.diags(m ** -0.5)
    top = sla.eigsh(Kv, k=1, which="LA")[0][0]
    bound = float(np.max(sim.volume_rows(s) / sim.network.mass))
    print(f"volumetric ω² bound / largest eigenvalue: {bound / top:.2f}")
    assert top <= bound < 10 * top
    zero = np.zeros_like(sim.spring_kappa)
    assert sim.stable_substep(sim.spring_kappa, zero, s) < 0.95 * sim.stable_substep(sim.spring_kappa, zero)
