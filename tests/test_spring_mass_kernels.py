"""The spring-mass substep's two passes: each spring computed once, at an end that moves, the same forces."""

from __future__ import annotations

import numpy as np
import trimesh

from unipixie.solvers import spring_mass as sm
from unipixie.solvers.body import Body
from unipixie.solvers.material_sampling import HomogeneousMaterial
from unipixie.solvers.scenario import Scenario


def clamped_bar():
    """A bar of 80 anchors, its left third in the clamp (held anchors next to free ones)."""
    mesh = trimesh.creation.box(extents=(0.3, 0.06, 0.06))
    return sm.prepare(Body.from_mesh(mesh), HomogeneousMaterial(1e5, 0.3, 1000.0),
                      Scenario(pinned_box=[[-1, -1, -1], [-0.05, 1, 1]], gravity=[0, 0, 0], ground_height=None),
                      [0.0, 0.01], settings={"anchors": 80, "volumetric": False})


def test_every_spring_with_a_moving_end_has_one_owner_that_moves():
    sim = clamped_bar()
    slots = sim._slots
    src, dst, sid = sim._he_src, sim._he_dst, sim._he_spring
    free = sim.inv_mass > 0
    assert 0 < free.sum() < sim.network.count  # both kinds of anchor
    he = slots["slot_he"]
    # the two half-edges of each slot are the two ends of its spring, the owner's first
    assert np.array_equal(sid[he[:, 0]], slots["slot_spring"]) and np.array_equal(sid[he[:, 1]], slots["slot_spring"])
    assert np.array_equal(src[he[:, 0]], dst[he[:, 1]]) and np.array_equal(slots["slot_nbr"], dst[he[:, 0]])
    assert sorted(slots["slot_spring"]) == list(range(len(sim.network.springs)))
    # anchor i's slots are the range slot_start[i] .. slot_start[i + 1], owned by i
    owner = np.repeat(np.arange(sim.network.count), np.diff(slots["slot_start"]))
    k = len(owner)
    assert np.array_equal(src[he[:k, 0]], owner)
    # every spring with an end that moves is owned, by an end that moves (the lower one where both do)
    a, b = src[he[:, 0]], dst[he[:, 0]]
    moving = free[a] | free[b]
    assert k == moving.sum() and np.all(moving[:k]) and not np.any(moving[k:])
    assert np.all(free[a[:k]]) and np.all(~free[b[:k]] | (a[:k] < b[:k]))


def pass_and_kick(sim, x, v, rest, kappa, dashpot, yield_strain, damped, plastic):
    """Forces (N, 3) N from the first pass and the kick (unit inverse mass, τ = 1 s, no body force: v_out − v = f),
    and the per-slot rest lengths after the pass."""
    from unipixie.solvers import spring_mass_kernels as K
    from unipixie.solvers.warp_runtime import init_warp

    wp = init_warp()
    n = sim.network.count
    arr = lambda a, dtype=float: wp.array(np.asarray(a, np.float32), dtype=dtype, device="cpu")  # noqa: E731
    d_x, d_v, d_rest = arr(x[None], wp.vec3), arr(v[None], wp.vec3), arr(rest[None])
    force = wp.zeros((1, len(sim._he_src)), dtype=wp.vec3, device="cpu")
    stress = wp.zeros((1, n), dtype=wp.mat33, device="cpu")
    wp.launch_tiled(K.spring_star_pass, dim=(1, n), device="cpu", block_dim=1,
                    inputs=[d_x, d_v, sim._d_start, sim._d_nbr, sim._d_rest_vec, sim._d_slot_start, sim._d_slot_nbr,
                            sim._d_slot_he, d_rest, arr(kappa[None]), arr(dashpot[None]), arr(yield_strain[None]),
                            sim._d_gram_inv, arr(np.zeros((1, n))), force, stress, damped, plastic])
    v_out = wp.zeros((1, n), dtype=wp.vec3, device="cpu")
    wp.launch(K.velocity_kick, dim=(1, n), device="cpu",
              inputs=[d_v, v_out, sim._d_start, sim._d_nbr, force, sim._d_rest_vec, arr(sim.inv_mass > 0),
                      arr(np.zeros((1, 3)), wp.vec3), arr([0.0]), arr([0.0]), stress, 0, 1.0])
    return (v_out.numpy()[0] - d_v.numpy()[0]).astype(np.float64), d_rest.numpy()[0].astype(np.float64)


def test_pass_forces_match_every_end_computing_its_own():
    """Against a float64 reference in which every anchor sums its own half-edges (Hooke + dashpot along the spring,
    rest lengths yielding past ±ε_y): the forces on the moving anchors and the yielded rest lengths, with dashpots
    and plasticity on; without them, the kernels' shortcuts (damped = plastic = 0) give the same forces bit for bit."""
    sim = clamped_bar()
    rng = np.random.default_rng(3)
    X = sim.network.anchors
    x = (X * np.array([1.05, 0.97, 0.98]) + rng.normal(0, 1e-3, X.shape)).astype(np.float32).astype(np.float64)
    v = rng.normal(0, 0.2, X.shape).astype(np.float32).astype(np.float64)
    slot_spring = sim._slots["slot_spring"]
    L0 = sim.network.rest_length.copy()
    kappa = sim.spring_kappa
    c = np.full(len(L0), 0.3)
    ey = np.full(len(L0), 0.02)
    f, rest = pass_and_kick(sim, x, v, L0[slot_spring], kappa[slot_spring], c[slot_spring], ey[slot_spring], 1, 1)
    # reference: per half-edge, every anchor computing its own
    s = sim._he_spring
    d = x[sim._he_dst] - x[sim._he_src]
    length = np.linalg.norm(d, axis=1)
    n = d / length[:, None]
    L = np.clip(L0[s], length / (1 + ey[s]), length / (1 - ey[s]))
    fh = (kappa[s] * (length - L) + c[s] * np.einsum("hi,hi->h", v[sim._he_dst] - v[sim._he_src], n))[:, None] * n
    ref = np.zeros_like(x)
    np.add.at(ref, sim._he_src, fh)
    free = sim.inv_mass > 0
    scale = np.abs(ref[free]).max()
    assert scale > 0 and np.abs(f[~free]).max() == 0.0
    np.testing.assert_allclose(f[free], ref[free], atol=2e-5 * scale)
    yielded = np.abs(L - L0[s]) > 1e-6 * L0[s]
    assert yielded.any() and not yielded.all()
    moving = np.zeros(len(L0), bool)
    moving[s[free[sim._he_src]]] = True  # the springs with an end that moves (the others are never computed)
    spring_rest = np.empty(len(L0))
    spring_rest[slot_spring] = rest
    he_moving = moving[s]
    np.testing.assert_allclose(spring_rest[s[he_moving]], L[he_moving], rtol=1e-5)
    # no dashpots, no yield: the shortcuts change nothing
    zero, big = np.zeros(len(L0)), np.full(len(L0), 1e30)
    args = (L0[slot_spring], kappa[slot_spring], zero, big)
    f_on, _ = pass_and_kick(sim, x, v, *args, 1, 1)
    f_off, _ = pass_and_kick(sim, x, v, *args, 0, 0)
    assert np.array_equal(f_on, f_off) and np.abs(f_on).max() > 0
