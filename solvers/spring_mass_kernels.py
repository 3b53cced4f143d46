"""Warp kernels of the spring-mass solver (imported only after :func:`~.warp_runtime.init_warp`).

Arrays are indexed ``[env, item]``: every simulated environment (one effect list of a
batch) runs in the same launch.  Springs are stored as half-edges in CSR order
(``start[i] .. start[i + 1]`` are the springs of anchor ``i``), so each thread *gathers*
the forces on its own anchor (a block of lanes per anchor on a GPU): no atomics.  A substep is
two launches: :func:`spring_star_pass` computes each spring's force once, at the end that owns it
(its one copy of the rest length, so plastic rest-length updates stay symmetric), and each
anchor star's volumetric stress; :func:`spring_substep` gathers them (the other end takes the
negative, which is exactly the force it would compute itself) and integrates.  On the CPU the same two passes
run per anchor without tile operations (:func:`star_pass_anchor`, :func:`substep_anchor`), all the substeps of a
frame in one launch (:func:`substep_pairs_serial`), so that runs in several threads may go on at once.
"""

from __future__ import annotations

import warp as wp

from .contact import RIGID_SAMPLE_DAMPING_RATIO, SAMPLE_CONTACT_IMPLICIT
from .contact_kernels import ground_contact_impulse

# forward kernels only: nothing differentiates through them (no wp.Tape); the adjoints cost most of the
# module's compile time on an empty kernel cache (LBS 20 s -> 8 s CPU, spring-mass 6.7 s -> 4.5 s)
wp.set_module_options({"enable_backward": False})

BIG = 1.0e30
"""Yield strain meaning "never yields"."""
SAMPLE_IMPLICIT = wp.constant(SAMPLE_CONTACT_IMPLICIT["spring_mass"])
"""Whether an anchor takes the ground's impulse implicitly (:data:`.contact.SAMPLE_CONTACT_IMPLICIT`)."""
SAMPLE_ZETA = wp.constant(RIGID_SAMPLE_DAMPING_RATIO["spring_mass"])
"""Damping ratio of an anchor's own contact spring on the rigid floor (:data:`.contact.RIGID_SAMPLE_DAMPING_RATIO`)."""


@wp.func
def spring_force(e: int, k: int, d: wp.vec3, dv: wp.vec3, rest: wp.array2d(dtype=float),
                 kappa: wp.array2d(dtype=float), dashpot: wp.array2d(dtype=float),
                 yield_strain: wp.array2d(dtype=float), damped: int, plastic: int):
    """Force (N) of spring slot ``k`` of environment ``e`` on the anchor it joins to a neighbour d = x_j − x_i away
    (m) moving at dv = v_j − v_i (m/s) relative to it: Hooke spring along the current direction plus (damped != 0)
    the dashpot on the relative velocity along it; (plastic != 0) past the yield strain the rest length (stored in
    ``rest[e, k]``) follows the spring.  damped = 0 / plastic = 0 only where no spring of the launch has a dashpot /
    a yield strain below BIG (adding 0 · dv·n or testing BIG changes nothing).  The force on the other end is
    exactly its negative (d, dv and n change sign, l and the scalar do not)."""
    l = wp.length(d)
    f = wp.vec3(0.0, 0.0, 0.0)
    if l > 1.0e-12:
        n = d / l
        L = rest[e, k]
        if plastic != 0:
            ey = yield_strain[e, k]
            if ey < BIG:
                s = (l - L) / L
                if s > ey:
                    L = l / (1.0 + ey)
                    rest[e, k] = L
                elif s < -ey:
                    L = l / (1.0 - ey)
                    rest[e, k] = L
        fn = kappa[e, k] * (l - L)
        if damped != 0:
            fn = fn + dashpot[e, k] * wp.dot(dv, n)
        f = fn * n
    return f


@wp.func
def gathered_force(e: int, i: int, first: int, stride: int, start: wp.array(dtype=int), nbr: wp.array(dtype=int),
                   force: wp.array2d(dtype=wp.vec3), rest_vec: wp.array(dtype=wp.vec3),
                   stress: wp.array2d(dtype=wp.mat33), has_volume: int):
    """Sum (N) of the spring forces on anchor ``i`` over its half-edges start[i] + first, + stride, ... (all of them
    with first 0, stride 1; one lane's share in a block of lanes): force[e, h], which :func:`spring_star_pass`
    computed at the end that owns the spring (from the other end: the exact negative of what this end would
    compute); plus, when has_volume != 0, the volumetric term's force Σ_h (A_i + A_j) d0_h
    (A = :func:`spring_star_pass`'s stress[e, ·], N/m; d0_h = rest_vec[h] = X_j − X_i, m): the gradient of the
    anchor's own star energy and of every star it belongs to (the half-edges are symmetric: j is in i's star
    exactly when i is in j's)."""
    f = wp.vec3(0.0, 0.0, 0.0)
    d0_sum = wp.vec3(0.0, 0.0, 0.0)
    h = start[i] + first
    stop = start[i + 1]
    while h < stop:
        f = f + force[e, h]
        if has_volume != 0:
            d0 = rest_vec[h]
            f = f + stress[e, nbr[h]] * d0
            d0_sum = d0_sum + d0
        h += stride
    if has_volume != 0:
        f = f + stress[e, i] * d0_sum
    return f


@wp.func
def star_deformation(e: int, i: int, x: wp.array2d(dtype=wp.vec3), x_rest: wp.array(dtype=wp.vec3),
                     start: wp.array(dtype=int), nbr: wp.array(dtype=int), gram_inv: wp.array(dtype=wp.mat33)):
    """F_i = (Σ_h d_h d0_hᵀ) (Σ_h d0_h d0_hᵀ)⁻¹, the least-squares deformation gradient of anchor ``i``'s spring
    star (d = x_j − x_i now, d0 at rest; gram_inv[i] the inverse of the rest Gram matrix, 1/m²)."""
    xi = x[e, i]
    x0 = x_rest[i]
    B = wp.mat33(0.0)
    for h in range(start[i], start[i + 1]):
        j = nbr[h]
        B = B + wp.outer(x[e, j] - xi, x_rest[j] - x0)
    return B * gram_inv[i]


@wp.func
def star_springs(e: int, i: int, first: int, stride: int, x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                 slot_start: wp.array(dtype=int), slot_nbr: wp.array(dtype=int), slot_he: wp.array2d(dtype=int),
                 rest: wp.array2d(dtype=float), kappa: wp.array2d(dtype=float), dashpot: wp.array2d(dtype=float),
                 yield_strain: wp.array2d(dtype=float), force: wp.array2d(dtype=wp.vec3), damped: int, plastic: int):
    """The springs anchor ``i`` owns, slots slot_start[i] + first, + stride, ... (one lane's share; all of them with
    first 0, stride 1): each spring's force to both its half-edges (:func:`spring_star_pass`)."""
    xi = x[e, i]
    vi = v[e, i]
    k = slot_start[i] + first
    stop = slot_start[i + 1]
    while k < stop:
        j = slot_nbr[k]
        dv = wp.vec3(0.0, 0.0, 0.0)
        if damped != 0:
            dv = v[e, j] - vi
        f = spring_force(e, k, x[e, j] - xi, dv, rest, kappa, dashpot, yield_strain, damped, plastic)
        force[e, slot_he[k, 0]] = f
        force[e, slot_he[k, 1]] = -f
        k += stride


@wp.func
def star_stretch(e: int, i: int, first: int, stride: int, x: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=int),
                 nbr: wp.array(dtype=int), rest_vec: wp.array(dtype=wp.vec3)):
    """Σ_h d_h d0_hᵀ (m²) over anchor ``i``'s half-edges start[i] + first, + stride, ... (one lane's share)."""
    xi = x[e, i]
    B = wp.mat33(0.0)
    h = start[i] + first
    stop = start[i + 1]
    while h < stop:
        B = B + wp.outer(x[e, nbr[h]] - xi, rest_vec[h])
        h += stride
    return B


@wp.func
def star_stress(stretch: wp.mat33, gram_inv: wp.mat33, s: float):
    """A_i = s (J − 1) cof(F) G⁻¹ (N/m) of a star with F = stretch · G⁻¹ and stiffness s = V λ_extra (J)."""
    F = stretch * gram_inv
    Ft = wp.transpose(F)
    cof = wp.matrix_from_cols(wp.cross(Ft[1], Ft[2]), wp.cross(Ft[2], Ft[0]), wp.cross(Ft[0], Ft[1]))
    J = wp.dot(Ft[0], wp.cross(Ft[1], Ft[2]))
    return (s * (J - 1.0)) * (cof * gram_inv)


@wp.kernel
def spring_star_pass(x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=int),
                     nbr: wp.array(dtype=int), rest_vec: wp.array(dtype=wp.vec3), slot_start: wp.array(dtype=int),
                     slot_nbr: wp.array(dtype=int), slot_he: wp.array2d(dtype=int), rest: wp.array2d(dtype=float),
                     kappa: wp.array2d(dtype=float), dashpot: wp.array2d(dtype=float), yield_strain: wp.array2d(dtype=float),
                     gram_inv: wp.array(dtype=wp.mat33), vol_stiffness: wp.array2d(dtype=float),
                     force: wp.array2d(dtype=wp.vec3), stress: wp.array2d(dtype=wp.mat33), damped: int,
                     plastic: int):
    """First pass of a substep, by a block of lanes per anchor as :func:`spring_substep` (lane ``l`` takes every
    block_dim-th item from the l-th; a tile reduction joins the star's sums).  For anchor ``i``:

    * **its springs, each computed once**: the springs anchor ``i`` owns (it moves, and the other end is held or has
      the higher index; :meth:`.spring_mass.SpringMassSimulation._spring_slots`) are the slots
      k = slot_start[i] .. slot_start[i + 1] − 1, to j = slot_nbr[k]: f = :func:`spring_force` (N), the force on
      ``i``, goes to its half-edge force[e, slot_he[k, 0]] and −f, the force on ``j``, to j's
      force[e, slot_he[k, 1]] — half the square roots and divisions of every end computing its own, the same numbers;
    * **the volumetric term** (s_i = vol_stiffness[e, i] = V_i λ_extra,i, J; 0: none): over its half-edges
      h = start[i] .. start[i + 1] − 1 (to j = nbr[h]), per anchor star energy W_i = ½ s_i (J_i − 1)², J_i = det F_i,
      F_i = (Σ_h d_h d0_hᵀ) G_i⁻¹ (d = x_j − x_i, d0_h = rest_vec[h] = X_j − X_i, m; G_i⁻¹ = gram_inv[i], 1/m²);
      writes A_i = s_i (J_i − 1) cof(F_i) G_i⁻¹ (N/m), so ∂W_i/∂x_j = A_i d0_h for a neighbour j and
      −Σ_h A_i d0_h for the anchor itself.  cof(F) = ∂J/∂F (columns c1×c2, c2×c0, c0×c1 of F's columns c): J is
      rotation invariant, so the forces store no energy under rigid rotation, and they sum to zero over the star
      (momentum).

    rest, kappa, dashpot, yield_strain: (E, S) per slot (m, N/m, N·s/m, ≥ BIG: elastic); damped, plastic: whether
    any spring has a dashpot, a yield strain (:func:`spring_force`); force: (E, H) N per half-edge (the force on its
    anchor); stress: (E, N) N/m."""
    e, i, lane = wp.tid()
    star_springs(e, i, lane, wp.block_dim(), x, v, slot_start, slot_nbr, slot_he, rest, kappa, dashpot, yield_strain,
                 force, damped, plastic)
    s = vol_stiffness[e, i]
    if s == 0.0:  # the same for every lane of the block
        if lane == 0:
            stress[e, i] = wp.mat33(0.0)
        return
    B = star_stretch(e, i, lane, wp.block_dim(), x, start, nbr, rest_vec)
    total = wp.tile_sum(wp.tile(B, preserve_type=True))
    if lane == 0:
        stress[e, i] = star_stress(total[0], gram_inv[i], s)


@wp.func
def star_pass_anchor(e: int, i: int, x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                     start: wp.array(dtype=int), nbr: wp.array(dtype=int), rest_vec: wp.array(dtype=wp.vec3),
                     slot_start: wp.array(dtype=int), slot_nbr: wp.array(dtype=int), slot_he: wp.array2d(dtype=int),
                     rest: wp.array2d(dtype=float), kappa: wp.array2d(dtype=float), dashpot: wp.array2d(dtype=float),
                     yield_strain: wp.array2d(dtype=float), gram_inv: wp.array(dtype=wp.mat33),
                     vol_stiffness: wp.array2d(dtype=float), force: wp.array2d(dtype=wp.vec3),
                     stress: wp.array2d(dtype=wp.mat33), damped: int, plastic: int):
    """:func:`spring_star_pass` of anchor ``i`` by one thread (no tile operations): the same arithmetic in the same
    order as the tiled kernel with one lane."""
    star_springs(e, i, 0, 1, x, v, slot_start, slot_nbr, slot_he, rest, kappa, dashpot, yield_strain, force, damped,
                 plastic)
    s = vol_stiffness[e, i]
    if s == 0.0:
        stress[e, i] = wp.mat33(0.0)
    else:
        stress[e, i] = star_stress(star_stretch(e, i, 0, 1, x, start, nbr, rest_vec), gram_inv[i], s)


@wp.kernel
def spring_star_pass_serial(x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=int),
                            nbr: wp.array(dtype=int), rest_vec: wp.array(dtype=wp.vec3),
                            slot_start: wp.array(dtype=int), slot_nbr: wp.array(dtype=int),
                            slot_he: wp.array2d(dtype=int), rest: wp.array2d(dtype=float),
                            kappa: wp.array2d(dtype=float), dashpot: wp.array2d(dtype=float),
                            yield_strain: wp.array2d(dtype=float), gram_inv: wp.array(dtype=wp.mat33),
                            vol_stiffness: wp.array2d(dtype=float), force: wp.array2d(dtype=wp.vec3),
                            stress: wp.array2d(dtype=wp.mat33), damped: int, plastic: int):
    """:func:`spring_star_pass` by one thread per anchor (dim (E, N), a plain launch: the CPU, where the
    leapfrog's kicks use it; :func:`star_pass_anchor`)."""
    e, i = wp.tid()
    star_pass_anchor(e, i, x, v, start, nbr, rest_vec, slot_start, slot_nbr, slot_he, rest, kappa, dashpot,
                     yield_strain, gram_inv, vol_stiffness, force, stress, damped, plastic)


@wp.func
def drag_kick(vi: wp.vec3, a: wp.vec3, rate: float, tau: float):
    """Velocity (m/s) after τ s of dv/dt = a − rate · v with a (m/s²) and rate (1/s) held: exact,
    vi e^{−rate τ} + a (1 − e^{−rate τ}) / rate (the exponentials in float64; a series where rate τ is small)."""
    x = wp.float64(rate) * wp.float64(tau)
    decay = wp.exp(-x)
    if wp.abs(x) < wp.float64(1.0e-3):
        phi = wp.float64(tau) * (wp.float64(1.0) - x * (wp.float64(0.5) - x / wp.float64(6.0)))
    else:
        phi = (wp.float64(1.0) - decay) / wp.float64(rate)
    return vi * float(decay) + a * float(phi)


@wp.func
def kicked_velocity(e: int, vi: wp.vec3, f: wp.vec3, im: float, accel: wp.array(dtype=wp.vec3),
                    lin_drag: wp.array(dtype=float), quad_drag: wp.array(dtype=float), tau: float):
    """Velocity (m/s) after a kick of τ s: body acceleration + im f held over the kick, the drags integrated exactly
    (:func:`drag_kick`; a quadratic drag's rate k |v| from the speed of the mean of the velocities before and after
    a first pass).  Second order in the leapfrog and stable for any drag.  The drag on the velocity after alone
    (backward Euler, as before) was first order: a thrown cube with c = 0.4 s⁻¹ at 192 anchors fell 0.94 mm short of
    the closed form in 0.8 s, one under quadratic drag k = 1 m⁻¹ 4 mm; now 7 µm and 11 µm
    (`tests/test_spring_mass.py::test_drags_follow_their_closed_forms_to_a_few_micrometres`)."""
    a = accel[e] + im * f
    if lin_drag[e] == 0.0 and quad_drag[e] == 0.0:
        return vi + tau * a
    if quad_drag[e] == 0.0:
        return drag_kick(vi, a, lin_drag[e], tau)
    first = drag_kick(vi, a, lin_drag[e] + quad_drag[e] * wp.length(vi + tau * a), tau)
    return drag_kick(vi, a, lin_drag[e] + quad_drag[e] * wp.length(0.5 * (vi + first)), tau)


@wp.func
def integrate_anchor(e: int, i: int, xi: wp.vec3, vi: wp.vec3, f: wp.vec3, im: float,
                     x_out: wp.array2d(dtype=wp.vec3), v_out: wp.array2d(dtype=wp.vec3),
                     accel: wp.array(dtype=wp.vec3), lin_drag: wp.array(dtype=float),
                     quad_drag: wp.array(dtype=float), ground_law: wp.array(dtype=wp.vec3),
                     contact_low: wp.array2d(dtype=float), contact_area: wp.array(dtype=float),
                     rigid_k: wp.array2d(dtype=float), rigid_c: wp.array2d(dtype=float), ground: float,
                     has_ground: int, dt: float):
    """Semi-implicit Euler update of anchor ``i`` (inverse mass ``im``, 1/kg) under the spring force ``f`` (N),
    body acceleration, drags and the ground's contact impulse (:func:`.contact_kernels.ground_contact_impulse` on
    the anchor's cell, whose lowest point lies contact_low[e, i] m below the anchor); writes x_out[e, i],
    v_out[e, i]."""
    vn = kicked_velocity(e, vi, f, im, accel, lin_drag, quad_drag, dt)
    if has_ground != 0:
        g = ground_law[e]
        size = wp.sqrt(contact_area[i])  # an anchor's cell is a cube of its volume: area ℓ², thickness ℓ
        vn = vn + im * ground_contact_impulse(xi[2] - contact_low[e, i], vn, 1.0 / im, contact_area[i], size,
                                              rigid_k[e, i], rigid_c[e, i], SAMPLE_ZETA, dt, ground, g[0], g[1],
                                              g[2], SAMPLE_IMPLICIT)
    x_out[e, i] = xi + dt * vn
    v_out[e, i] = vn


@wp.kernel
def spring_substep(x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                   x_out: wp.array2d(dtype=wp.vec3), v_out: wp.array2d(dtype=wp.vec3),
                   start: wp.array(dtype=int), nbr: wp.array(dtype=int), force: wp.array2d(dtype=wp.vec3),
                   rest_vec: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), x_rest: wp.array(dtype=wp.vec3),
                   accel: wp.array(dtype=wp.vec3), lin_drag: wp.array(dtype=float),
                   quad_drag: wp.array(dtype=float), ground_law: wp.array(dtype=wp.vec3),
                   contact_low: wp.array2d(dtype=float), contact_area: wp.array(dtype=float),
                   rigid_k: wp.array2d(dtype=float), rigid_c: wp.array2d(dtype=float), ground: float,
                   has_ground: int, stress: wp.array2d(dtype=wp.mat33), has_volume: int, dt: float):
    """Second pass of one semi-implicit Euler substep of anchor ``i`` in environment ``e``, by a block of lanes
    (``wp.launch_tiled``, dim (E, N), block_dim lanes: 1 on the CPU, 32 on a GPU).  Lane ``l`` gathers the
    half-edges start[i] + l, + block_dim, ... (:func:`gathered_force`); a tile reduction adds the lanes' forces and
    lane 0 integrates.  On a GPU the loads of an anchor are so issued together instead of one after another (one
    thread per anchor is latency-bound there).

    x, v: (E, N) m, m/s at the start of the substep; x_out, v_out: (E, N) at its end.
    force: (E, H) N per half-edge and stress: (E, N) N/m, :func:`spring_star_pass` of x, v; start, nbr, rest_vec: the
    half-edges (CSR), as :func:`gathered_force`.  inv_mass: (N,) 1/kg, 0 for anchors held by the clamp (they stay at x_rest).
    accel: (E,) m/s² gravity + extra acceleration; lin_drag (E,) 1/s; quad_drag (E,) 1/m;
    ground_law: (E,) (k_g Pa/m, c_g Pa·s/m, μ) of the contact law at the plane z = ground (when has_ground != 0);
    contact_low: (E, N) m, depth of each anchor cell's lowest point below the anchor (:func:`contact_depths`);
    contact_area: (N,) m²; rigid_k: (E, N) N/m, each anchor's rigid-floor spring; rigid_c: (E, N) N·s/m, its
    material's Kelvin–Voigt damper (:mod:`.contact`).
    """
    e, i, lane = wp.tid()
    im = inv_mass[i]
    if im == 0.0:  # the same for every lane of the block: the whole block leaves
        if lane == 0:
            x_out[e, i] = x_rest[i]
            v_out[e, i] = wp.vec3(0.0, 0.0, 0.0)
        return
    f = gathered_force(e, i, lane, wp.block_dim(), start, nbr, force, rest_vec, stress, has_volume)
    total = wp.tile_sum(wp.tile(f, preserve_type=True))
    if lane == 0:
        integrate_anchor(e, i, x[e, i], v[e, i], total[0], im, x_out, v_out, accel, lin_drag, quad_drag, ground_law,
                         contact_low, contact_area, rigid_k, rigid_c, ground, has_ground, dt)


@wp.func
def substep_anchor(e: int, i: int, x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                   x_out: wp.array2d(dtype=wp.vec3), v_out: wp.array2d(dtype=wp.vec3),
                   start: wp.array(dtype=int), nbr: wp.array(dtype=int), force: wp.array2d(dtype=wp.vec3),
                   rest_vec: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), x_rest: wp.array(dtype=wp.vec3),
                   accel: wp.array(dtype=wp.vec3), lin_drag: wp.array(dtype=float), quad_drag: wp.array(dtype=float),
                   ground_law: wp.array(dtype=wp.vec3), contact_low: wp.array2d(dtype=float),
                   contact_area: wp.array(dtype=float), rigid_k: wp.array2d(dtype=float),
                   rigid_c: wp.array2d(dtype=float), ground: float, has_ground: int,
                   stress: wp.array2d(dtype=wp.mat33), has_volume: int, dt: float):
    """:func:`spring_substep` of anchor ``i`` by one thread (no tile operations; the same arithmetic)."""
    im = inv_mass[i]
    if im == 0.0:
        x_out[e, i] = x_rest[i]
        v_out[e, i] = wp.vec3(0.0, 0.0, 0.0)
    else:
        f = gathered_force(e, i, 0, 1, start, nbr, force, rest_vec, stress, has_volume)
        integrate_anchor(e, i, x[e, i], v[e, i], f, im, x_out, v_out, accel, lin_drag, quad_drag, ground_law,
                         contact_low, contact_area, rigid_k, rigid_c, ground, has_ground, dt)


@wp.kernel
def substep_pairs_serial(x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                         x_b: wp.array2d(dtype=wp.vec3), v_b: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=int),
                         nbr: wp.array(dtype=int), rest_vec: wp.array(dtype=wp.vec3),
                         slot_start: wp.array(dtype=int), slot_nbr: wp.array(dtype=int),
                         slot_he: wp.array2d(dtype=int), rest: wp.array2d(dtype=float),
                         kappa: wp.array2d(dtype=float), dashpot: wp.array2d(dtype=float),
                         yield_strain: wp.array2d(dtype=float), gram_inv: wp.array(dtype=wp.mat33),
                         vol_stiffness: wp.array2d(dtype=float), force: wp.array2d(dtype=wp.vec3),
                         stress: wp.array2d(dtype=wp.mat33), damped: int, plastic: int,
                         inv_mass: wp.array(dtype=float), x_rest: wp.array(dtype=wp.vec3),
                         accel: wp.array(dtype=wp.vec3), lin_drag: wp.array(dtype=float),
                         quad_drag: wp.array(dtype=float), ground_law: wp.array(dtype=wp.vec3),
                         contact_low: wp.array2d(dtype=float), contact_area: wp.array(dtype=float),
                         rigid_k: wp.array2d(dtype=float), rigid_c: wp.array2d(dtype=float), ground: float,
                         has_ground: int, has_volume: int, dt: float, pairs: int):
    """``2 · pairs`` substeps of environment ``e`` (dim (E,): one thread per environment, the CPU only) in one launch:
    each substep is :func:`star_pass_anchor` over every anchor, then :func:`substep_anchor` over every anchor (a
    substep's two passes, as the two launches :func:`spring_star_pass` and :func:`spring_substep` do), from (x, v)
    to (x_b, v_b) and back, so the state ends in (x, v).  A launch per substep pair costs nothing in the interpreter
    (on the CPU the launches' Python was a fifth of a diagnosis-size substep) and leaves Python's lock free for other
    runs (:attr:`.spring_mass.SpringMassSimulation.concurrent_runs`).  Same arrays and units as the two kernels; dt in
    s; the same arithmetic in the same order: bit for bit their result."""
    e = wp.tid()
    n = x.shape[1]
    for p in range(pairs):
        for i in range(n):
            star_pass_anchor(e, i, x, v, start, nbr, rest_vec, slot_start, slot_nbr, slot_he, rest, kappa, dashpot,
                             yield_strain, gram_inv, vol_stiffness, force, stress, damped, plastic)
        for i in range(n):
            substep_anchor(e, i, x, v, x_b, v_b, start, nbr, force, rest_vec, inv_mass, x_rest, accel, lin_drag,
                           quad_drag, ground_law, contact_low, contact_area, rigid_k, rigid_c, ground, has_ground,
                           stress, has_volume, dt)
        for i in range(n):
            star_pass_anchor(e, i, x_b, v_b, start, nbr, rest_vec, slot_start, slot_nbr, slot_he, rest, kappa,
                             dashpot, yield_strain, gram_inv, vol_stiffness, force, stress, damped, plastic)
        for i in range(n):
            substep_anchor(e, i, x_b, v_b, x, v, start, nbr, force, rest_vec, inv_mass, x_rest, accel, lin_drag,
                           quad_drag, ground_law, contact_low, contact_area, rigid_k, rigid_c, ground, has_ground,
                           stress, has_volume, dt)


@wp.kernel
def velocity_kick(v: wp.array2d(dtype=wp.vec3), v_out: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=int),
                  nbr: wp.array(dtype=int), force: wp.array2d(dtype=wp.vec3), rest_vec: wp.array(dtype=wp.vec3),
                  inv_mass: wp.array(dtype=float), accel: wp.array(dtype=wp.vec3), lin_drag: wp.array(dtype=float),
                  quad_drag: wp.array(dtype=float), stress: wp.array2d(dtype=wp.mat33), has_volume: int, tau: float):
    """Velocity kick v += τ a(x, v) of anchor ``i`` in environment ``e`` (positions unchanged), with the forces of
    :func:`spring_substep` (``force`` and ``stress`` from :func:`spring_star_pass` of the same state; drags
    implicit): the leapfrog start (τ = −Δt/2: the velocities become those half a substep earlier) and its correction
    when the substep changes from Δt to Δt' (τ = (Δt − Δt')/2).  Same arrays and units as :func:`spring_substep`;
    the kicked velocities go to ``v_out`` (may be ``v``: an anchor reads only its own); τ in s (may be
    negative)."""
    e, i = wp.tid()
    im = inv_mass[i]
    vi = v[e, i]
    if im == 0.0:
        v_out[e, i] = vi
        return
    f = gathered_force(e, i, 0, 1, start, nbr, force, rest_vec, stress, has_volume)
    v_out[e, i] = kicked_velocity(e, vi, f, im, accel, lin_drag, quad_drag, tau)


@wp.kernel
def anchor_rotations(x: wp.array2d(dtype=wp.vec3), x_rest: wp.array(dtype=wp.vec3),
                     start: wp.array(dtype=int), nbr: wp.array(dtype=int),
                     gram_inv: wp.array(dtype=wp.mat33), rot: wp.array2d(dtype=wp.mat33)):
    """Per-anchor rotation: polar part of the least-squares deformation of its spring star.

    F_i = (Σ_h d_h d0_hᵀ) (Σ_h d0_h d0_hᵀ)⁻¹ with d = x_j − x_i now and d0 at rest; R_i = U Vᵀ.
    """
    e, i = wp.tid()
    F = star_deformation(e, i, x, x_rest, start, nbr, gram_inv)
    U = wp.mat33()
    S = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, S, V)
    R = U * wp.transpose(V)
    if wp.determinant(R) < 0.0:
        U = wp.mat33(U[0, 0], U[0, 1], -U[0, 2], U[1, 0], U[1, 1], -U[1, 2], U[2, 0], U[2, 1], -U[2, 2])
        R = U * wp.transpose(V)
    rot[e, i] = R


@wp.kernel
def contact_depths(rot: wp.array2d(dtype=wp.mat33), start: wp.array(dtype=int), offsets: wp.array(dtype=wp.vec3),
                   margin: float, depth: wp.array2d(dtype=float)):
    """depth[e, i] = margin + max over anchor i's cell points q of −(R_i (X_q − X_i))_z (m): how far the lowest
    point of the anchor's cell (rotated with the anchor) lies below it; offsets[start[i]:start[i+1]] = X_q − X_i
    at rest; margin (m): how far the solid reaches beyond its points (half their spacing for a point body)."""
    e, i = wp.tid()
    R = rot[e, i]
    low = float(0.0)
    for q in range(start[i], start[i + 1]):
        low = wp.max(low, -(R * offsets[q])[2])
    depth[e, i] = low + margin


@wp.kernel
def bind_points(x: wp.array2d(dtype=wp.vec3), x_rest: wp.array(dtype=wp.vec3), rot: wp.array2d(dtype=wp.mat33),
                point_rest: wp.array(dtype=wp.vec3), bind_idx: wp.array2d(dtype=int),
                bind_w: wp.array2d(dtype=float), ground: float, has_ground: int, out: wp.array3d(dtype=wp.vec3),
                frame: int):
    """Position of bound point p: Σ_b w_pb (x_b + R_b (X_p − X_b)), written to out[e, frame, p]; never below the
    ground plane z = ground (when has_ground != 0)."""
    e, p = wp.tid()
    X = point_rest[p]
    acc = wp.vec3(0.0, 0.0, 0.0)
    for k in range(bind_idx.shape[1]):
        b = bind_idx[p, k]
        acc = acc + bind_w[p, k] * (x[e, b] + rot[e, b] * (X - x_rest[b]))
    if has_ground != 0 and acc[2] < ground:
        acc = wp.vec3(acc[0], acc[1], ground)
    out[e, frame, p] = acc


@wp.kernel
def store_state(x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                out_x: wp.array3d(dtype=wp.vec3), out_v: wp.array3d(dtype=wp.vec3), frame: int):
    """Copy anchor positions and velocities into the per-frame output (E, T, N)."""
    e, i = wp.tid()
    out_x[e, frame, i] = x[e, i]
    out_v[e, frame, i] = v[e, i]
