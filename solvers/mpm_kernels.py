"""Warp kernels of the MPM solver: MLS-MPM with quadratic B-splines, batched over environments.

Layout (all float32, structure of arrays):

* particles: ``E`` environments × ``N`` particles, environment-major (particle ``p`` belongs to
  environment ``p // N``); positions ``x`` (m), velocities ``v`` (m/s), APIC affine velocity
  ``C`` (1/s, the velocity gradient estimate), the elastic displacement gradient ``H`` = F − I
  (F the elastic deformation gradient; stored as H for precision), the rotation of F's polar
  decomposition as a quaternion ``rot`` (warm start of the elastic fast path), one plastic state
  scalar, mass (kg), rest volume (m³), Lamé ``mu``/``lam`` (Pa) and a ``code`` (material-class id
  + ``HELD_FLAG`` × held).
* grid: every environment owns a block of ``nx·ny·nz`` nodes (x-major, z fastest) whose world
  origin moves with the material (``env_origin``); nodes lie on one global lattice of pitch
  ``dx``, so moving the block changes nothing physical.
* tracked points: ``E`` × ``M`` massless points advected by the grid velocity.

One substep is three launches: P2G (deformation update, return mapping, stress, the ground's
contact impulse on the particle (:func:`particle_ground_impulse`) and the scatter of mass and
momentum, fused; :data:`p2g_general`, or :data:`p2g_elastic` compiled for the elastic
fixed-corotated law only), :func:`grid_update` (forces, drag, the clamp; clears the
accumulators for the next substep) and :func:`g2p` (gather, advection; also moves the tracked
points).  Held particles of a rigid class (a clamped pot) never move and send only their mass: :func:`rigid_mass`
scatters it once per grid placement and P2G skips them (setting ``rigid_mass_once``); with one environment the
sort puts them last (:func:`cell_keys`) and P2G and G2P are launched over the other particles alone.  Environments whose frame needs fewer substeps than the launch count skip
the extra ones (``substep >= env_steps[env]``), so a batch gives the same trajectories as
separate runs.  The substep index is the launch parameter ``substep`` plus the device counter
``step_base[0]``: a captured CUDA graph of K substeps carries the offsets 0..K-1 and ends with
:func:`advance_step`, so one graph serves every position in a frame (:func:`set_step` starts it).

The material laws (stress, return mappings) are :mod:`.constitutive`'s.  GPU-tuned variants (vector and
warp-aggregated scatter, split G2P) are in :mod:`.mpm_kernels_cuda`; they share this module's physics functions
(:func:`particle_transfer`: what a particle sends to the grid) and :mod:`.mpm_stencil`'s B-spline stencil and gathers.
"""

from __future__ import annotations

import warp as wp

from .constitutive import (LAW_WEAKLY_COMPRESSIBLE, PLASTIC_SNOW, ClassLaw, constitutive_update,
                           elastic_fixed_corotated)
from .contact import RIGID_CONTACT_BETA, RIGID_SAMPLE_DAMPING_RATIO, SAMPLE_CONTACT_IMPLICIT
from .contact_kernels import ground_contact_impulse, rigid_contact_stiffness, rigid_floor
from .mpm_stencil import (bspline_slopes, bspline_weights, gather_stencil, gather_stencil_with_gradient,
                          plus_offset_times, stencil_base, stencil_inside)

wp.set_module_options({"enable_backward": False})

HELD_FLAG = wp.constant(16)
"""``code = class_id + HELD_FLAG`` marks a particle held at its rest position.

Held particles of a rigid class (``ClassLaw.held``: stationary) carry no stress.  Held particles
of any other class (material in the clamp box) keep their position and zero velocity but still
deform with the grid (their ``C`` and ``F`` follow the node velocities) and carry stress, so the
stress is continuous into the clamp, as for material embedded in a clamp."""

HELD_MASS_FRACTION = wp.constant(0.25)
"""A grid node is fixed when at least this fraction of its mass comes from held particles.

The node plane on the face of a clamp box gets about half its mass from held material, the next
plane outside about 5 %: a quarter fixes the first and frees the second."""

TRACKED_FIT_REGULARISATION = wp.constant(1.0e-3)
"""Ridge term (× total weight, in cells²: × dx² in m²) of the affine velocity fit at tracked points."""
RIGID_BETA2 = wp.constant(RIGID_CONTACT_BETA["mpm"] ** 2)
"""β² of MPM's rigid floor (:data:`.contact.RIGID_CONTACT_BETA`)."""
SAMPLE_IMPLICIT = wp.constant(SAMPLE_CONTACT_IMPLICIT["mpm"])
"""Whether MPM's particles take the ground's impulse implicitly (:data:`.contact.SAMPLE_CONTACT_IMPLICIT`)."""
SAMPLE_ZETA = wp.constant(RIGID_SAMPLE_DAMPING_RATIO["mpm"])
"""Damping ratio of a particle's own contact spring on MPM's rigid floor
(:data:`.contact.RIGID_SAMPLE_DAMPING_RATIO`)."""


@wp.func
def particle_ground_impulse(xp: wp.vec3, vp: wp.vec3, m: float, p_wave_modulus: float, eta: float, dt: float,
                            env: int, has_ground: int, ground_z: float, contact_radius: float, contact_area: float,
                            env_ground: wp.array(dtype=wp.vec3)):
    """The ground's impulse (N·s) on a particle over the substep (:func:`.contact_kernels.ground_contact_impulse`).

    A particle stands for a cube of material: its lower face lies ``contact_radius`` (half the particle spacing,
    m) below its centre and touches the ground over ``contact_area`` (the spacing², m²); p_wave_modulus: λ + 2μ
    of its material (Pa); eta: its Kelvin–Voigt viscosity (Pa·s).  env_ground[env] = (k_g Pa/m, c_g Pa·s/m, μ).  Added to the particle's momentum
    before the scatter, so the grid carries it.
    """
    if has_ground == 0:
        return wp.vec3(0.0)
    g = env_ground[env]
    rigid_k = rigid_contact_stiffness(RIGID_BETA2, p_wave_modulus, contact_area, 2.0 * contact_radius)
    return ground_contact_impulse(xp[2] - contact_radius, vp, m, contact_area, 2.0 * contact_radius, rigid_k,
                                  2.0 * eta * rigid_k / p_wave_modulus, SAMPLE_ZETA, dt, ground_z, g[0], g[1], 0.0,
                                  SAMPLE_IMPLICIT)


# ------------------------------------------------------------------------------ substep kernels
@wp.func
def displacement_gradient_update(H: wp.mat33, G: wp.mat33):
    """H ← H + G (I + H): the update F ← (I + G) F with G = Δt C, written for H = F − I.

    Particles store H, not F: a substep's increment of F is about Δt · strain rate, 10⁻⁷–10⁻⁶ for a
    slowly bending bar at a fine grid's time step, one to ten float32 units in the last place of
    entries near 1.  Added to F, most of each increment is rounded away, and the rounding is not
    symmetric (units in the last place are twice as large above 1 as below): a bar in sustained
    bending crept downwards by about 1 mm per period (docs/fidelity.md).  H's entries are of the
    strain's size, so the same increment keeps about seven significant digits.
    """
    return H + (G + G @ H)


@wp.func(inline=True)
def particle_stress_general(p: int, env: int, dt: float, law: ClassLaw, Cp: wp.mat33, H: wp.array(dtype=wp.mat33),
                            rot: wp.array(dtype=wp.quat), plastic: wp.array(dtype=float), mu_p: wp.array(dtype=float),
                            lam_p: wp.array(dtype=float), env_yield: wp.array(dtype=float),
                            env_eta: wp.array(dtype=float), update_f: int):
    """Deformation update F ← (I + Δt C) F, the class's law and Kelvin–Voigt viscosity of one deforming particle.

    ``H`` holds each particle's displacement gradient H = F − I (see :func:`displacement_gradient_update`).
    ``update_f`` = 0: G2P has updated H already (setting ``deformation_gradient = "grid"``); the law acts on it.
    Writes the particle's new H, rotation and plastic state; returns its Kirchhoff stress τ, Pa.
    """
    Hn = H[p]
    if update_f != 0:
        Hn = displacement_gradient_update(Hn, dt * Cp)
    Fn = wp.identity(n=3, dtype=float) + Hn
    tau, Fe, q, state, J = constitutive_update(law, Fn, rot[p], plastic[p], mu_p[p], lam_p[p], env_yield[env])
    plastic[p] = state
    eta = env_eta[env]
    if eta > 0.0:  # Kelvin-Voigt: Kirchhoff viscous stress J * 2 eta sym(grad v); zero for rigid motion
        tau = tau + (J * eta) * (Cp + wp.transpose(Cp))
    H[p] = Hn + (Fe - Fn)  # exactly Hn where the law did not project F
    rot[p] = q
    return tau


@wp.func(inline=True)
def particle_stress_elastic(p: int, env: int, dt: float, law: ClassLaw, Cp: wp.mat33, H: wp.array(dtype=wp.mat33),
                            rot: wp.array(dtype=wp.quat), plastic: wp.array(dtype=float), mu_p: wp.array(dtype=float),
                            lam_p: wp.array(dtype=float), env_yield: wp.array(dtype=float),
                            env_eta: wp.array(dtype=float), update_f: int):
    """:func:`particle_stress_general` for the elastic fixed-corotated law only (same results for such particles)."""
    Hn = H[p]
    if update_f != 0:
        Hn = displacement_gradient_update(Hn, dt * Cp)
    tau, q, J = elastic_fixed_corotated(wp.identity(n=3, dtype=float) + Hn, rot[p], mu_p[p], lam_p[p])
    eta = env_eta[env]
    if eta > 0.0:
        tau = tau + (J * eta) * (Cp + wp.transpose(Cp))
    H[p] = Hn
    rot[p] = q
    return tau


@wp.func(inline=True)
def particle_transfer(p: int, env: int, dt: float, tau: wp.mat33, Cp: wp.mat33, m: float, vol: wp.array(dtype=float),
                      v: wp.array(dtype=wp.vec3), mu_p: wp.array(dtype=float), lam_p: wp.array(dtype=float),
                      env_eta: wp.array(dtype=float), xp: wp.vec3, origin: wp.vec3, base: wp.vec3, held: bool,
                      has_ground: int, ground_z: float, contact_radius: float, contact_area: float,
                      env_ground: wp.array(dtype=wp.vec3), dx: float, inv_dx: float):
    """What particle ``p`` sends to its 3×3×3 stencil: the body every P2G kernel shares (only the scatter differs).

    tau: its Kirchhoff stress (Pa); Cp: its APIC affine velocity (1/s); m: its mass (kg); base: the stencil's
    lower corner (:func:`stencil_base`).  A held particle sends zero velocity; any other gets the ground's contact
    impulse (:func:`particle_ground_impulse`) first.  Returns (w, cols, a0, jn): the B-spline weights (rows: node
    offset, columns: axis), and the momentum sent to node (i, j, k), ``weight · (a0 + i cols[0] + j cols[1] +
    k cols[2])`` (kg·m/s), which is weight · (m v + affine (node − x)) with node − x = ((i, j, k) − fx) dx built up
    incrementally from the columns of affine · dx; jn: the contact impulse, N·s (0 when none).
    """
    affine = (-dt * vol[p] * 4.0 * inv_dx * inv_dx) * tau + m * Cp
    vp = v[p]
    jn = float(0.0)
    if held:
        vp = wp.vec3(0.0)
    else:
        jn = particle_ground_impulse(xp, vp, m, lam_p[p] + 2.0 * mu_p[p], env_eta[env], dt, env, has_ground,
                                     ground_z, contact_radius, contact_area, env_ground)[2]
        vp = vp + wp.vec3(0.0, 0.0, jn / m)
    fx = (xp - origin) * inv_dx - base
    w = bspline_weights(fx)
    cols = wp.transpose(affine * dx)
    a0 = m * vp - cols[0] * fx[0] - cols[1] * fx[1] - cols[2] * fx[2]
    return w, cols, a0, jn


def _make_p2g(general: bool):
    """The P2G kernel.  ``general=False`` compiles only the elastic fixed-corotated law (far fewer
    registers on a GPU), for runs whose deforming material is all jelly without plasticity."""

    def p2g(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
            H: wp.array(dtype=wp.mat33), rot: wp.array(dtype=wp.quat), plastic: wp.array(dtype=float),
            mass: wp.array(dtype=float), vol: wp.array(dtype=float), mu_p: wp.array(dtype=float),
            lam_p: wp.array(dtype=float), code: wp.array(dtype=wp.int32), laws: wp.array(dtype=ClassLaw),
            env_dt: wp.array(dtype=float), env_steps: wp.array(dtype=wp.int32), env_yield: wp.array(dtype=float),
            env_eta: wp.array(dtype=float), env_origin: wp.array(dtype=wp.vec3), step_base: wp.array(dtype=wp.int32),
            env_ground: wp.array(dtype=wp.vec3), has_ground: int, ground_z: float, contact_radius: float,
            contact_area: float,
            n_particles: int, n_per_env: int, nodes_per_env: int, dims: wp.vec3i, dx: float, inv_dx: float,
            rigid_static: int, update_f: int, substep: int, grid_mv: wp.array(dtype=wp.vec4),
            grid_held: wp.array(dtype=float), grid_contact: wp.array(dtype=float), lost: wp.array(dtype=wp.int32)):
        """Deformation update, plasticity, stress, the ground's contact impulse and the fused scatter of mass and
        momentum (one atomic per node; the contact impulse also to ``grid_contact``, N·s, for friction).

        ``rigid_static`` = 1: held particles of a rigid class are skipped; their mass is on the grid already
        (:func:`rigid_mass`, once per grid placement).  ``update_f`` = 0: G2P updated the deformation already
        (``deformation_gradient = "grid"``)."""
        p = wp.tid()
        if p >= n_particles:  # padding of a launch rounded up to whole warps
            return
        env = p / n_per_env
        if substep + step_base[0] >= env_steps[env]:
            return
        dt = env_dt[env]
        xp = x[p]
        if not wp.isfinite(xp):
            wp.atomic_add(lost, env, 1)
            return
        origin = env_origin[env]
        base = stencil_base(xp, origin, inv_dx)
        if not stencil_inside(base, dims):
            wp.atomic_add(lost, env, 1)
            return

        c = code[p]
        held = c >= HELD_FLAG
        law = laws[c % HELD_FLAG]
        if held and law.held != 0 and rigid_static != 0:
            return
        m = mass[p]
        Cp = C[p]
        tau = wp.mat33(0.0)
        if law.held == 0:
            if wp.static(general):
                tau = particle_stress_general(p, env, dt, law, Cp, H, rot, plastic, mu_p, lam_p, env_yield, env_eta,
                                              update_f)
            else:
                tau = particle_stress_elastic(p, env, dt, law, Cp, H, rot, plastic, mu_p, lam_p, env_yield, env_eta,
                                              update_f)

        w, cols, a0, jn = particle_transfer(p, env, dt, tau, Cp, m, vol, v, mu_p, lam_p, env_eta, xp, origin, base,
                                            held, has_ground, ground_z, contact_radius, contact_area, env_ground, dx,
                                            inv_dx)
        ib = int(base[0])
        jb = int(base[1])
        kb = int(base[2])
        block = env * nodes_per_env
        for i in range(3):
            ai = a0 + float(i) * cols[0]
            wi = w[i, 0]
            for j in range(3):
                aij = ai + float(j) * cols[1]
                wij = wi * w[j, 1]
                row = block + ((ib + i) * dims[1] + (jb + j)) * dims[2] + kb
                for k in range(3):
                    weight = wij * w[k, 2]
                    mom = weight * plus_offset_times(aij, k, cols[2])
                    wp.atomic_add(grid_mv, row + k, wp.vec4(mom[0], mom[1], mom[2], weight * m))
                    if held:
                        wp.atomic_add(grid_held, row + k, weight * m)
                    if jn > 0.0:
                        wp.atomic_add(grid_contact, row + k, weight * jn)

    p2g.__name__ = p2g.__qualname__ = "p2g_general" if general else "p2g_elastic"
    return wp.kernel(p2g)


p2g_general = _make_p2g(True)
p2g_elastic = _make_p2g(False)


@wp.kernel
def rigid_mass(x: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), code: wp.array(dtype=wp.int32),
               laws: wp.array(dtype=ClassLaw), env_origin: wp.array(dtype=wp.vec3), n_per_env: int,
               nodes_per_env: int, dims: wp.vec3i, inv_dx: float, grid_rigid: wp.array(dtype=float)):
    """The mass (kg) that the held particles of rigid classes (``stationary``) give each node, scattered once per
    grid placement: they never move, carry no stress and send no momentum, so every substep's P2G would scatter the
    same masses (P2G with ``rigid_static`` skips them; :func:`grid_update` adds ``grid_rigid`` to the node's mass
    and to its held mass).  A particle off the grid is left to P2G, which counts it as lost."""
    p = wp.tid()
    c = code[p]
    if c < HELD_FLAG:
        return
    if laws[c % HELD_FLAG].held == 0:
        return
    xp = x[p]
    if not wp.isfinite(xp):
        return
    origin = env_origin[p / n_per_env]
    base = stencil_base(xp, origin, inv_dx)
    if not stencil_inside(base, dims):
        return
    w = bspline_weights((xp - origin) * inv_dx - base)
    m = mass[p]
    row0 = (p / n_per_env) * nodes_per_env
    ib = int(base[0])
    jb = int(base[1])
    kb = int(base[2])
    for i in range(3):
        wi = w[i, 0]
        for j in range(3):
            wij = wi * w[j, 1]
            row = row0 + ((ib + i) * dims[1] + (jb + j)) * dims[2] + kb
            for k in range(3):
                wp.atomic_add(grid_rigid, row + k, (wij * w[k, 2]) * m)


@wp.func
def grid_update_node(n: int, env: int, dt: float, grid_mv: wp.array(dtype=wp.vec4), grid_held: wp.array(dtype=float),
                     env_acc: wp.array(dtype=wp.vec3), env_drag: wp.array(dtype=wp.vec2),
                     env_ground: wp.array(dtype=wp.vec3), grid_contact: wp.array(dtype=float),
                     grid_rigid: wp.array(dtype=float), grid_v: wp.array(dtype=wp.vec4)):
    """:func:`grid_update` at node ``n`` of environment ``env`` (substep ``dt``, s)."""
    mv = grid_mv[n]
    rigid = grid_rigid[n]
    m = mv[3] + rigid
    if m <= 0.0:
        grid_v[n] = wp.vec4(0.0)
    else:
        vel = wp.vec3(mv[0], mv[1], mv[2]) / m + dt * env_acc[env]
        drag = env_drag[env]
        if drag[0] > 0.0:  # linear drag -c v, integrated exactly
            vel = vel * wp.exp(-drag[0] * dt)
        if drag[1] > 0.0:  # quadratic drag -k |v| v, implicit in |v| (unconditionally stable)
            vel = vel / (1.0 + drag[1] * wp.length(vel) * dt)
        if grid_held[n] + rigid >= HELD_MASS_FRACTION * m:
            vel = wp.vec3(0.0)
        jn = grid_contact[n]
        if jn > 0.0:
            mu = env_ground[env][2]
            vt = wp.vec3(vel[0], vel[1], 0.0)
            st = wp.length(vt)
            if mu > 0.0 and st > 0.0:
                vel = vel - vt * (wp.min(mu * jn / m, st) / st)
            grid_contact[n] = 0.0
        grid_v[n] = wp.vec4(vel[0], vel[1], vel[2], m)
        grid_mv[n] = wp.vec4(0.0)
        grid_held[n] = 0.0


@wp.kernel
def grid_update(grid_mv: wp.array(dtype=wp.vec4), grid_held: wp.array(dtype=float),
                env_dt: wp.array(dtype=float), env_steps: wp.array(dtype=wp.int32),
                env_acc: wp.array(dtype=wp.vec3), env_drag: wp.array(dtype=wp.vec2),
                step_base: wp.array(dtype=wp.int32), nodes_per_env: int, nodes_per_thread: int, substep: int,
                env_ground: wp.array(dtype=wp.vec3), grid_contact: wp.array(dtype=float),
                grid_rigid: wp.array(dtype=float), grid_v: wp.array(dtype=wp.vec4)):
    """Node velocities from momentum; gravity + extra acceleration, drag, held nodes, and Coulomb friction with
    the ground's normal impulse that P2G gathered at the node (``grid_contact``, N·s): the tangential velocity
    loses at most μ × that impulse / the node's mass (the ground's normal push acts on the particles, in P2G).
    ``grid_rigid``: the node's mass from held rigid particles (:func:`rigid_mass`; zero where P2G scattered them),
    added to its mass and held mass.

    Thread ``t`` updates nodes ``t · nodes_per_thread`` onwards, ``nodes_per_thread`` of them (a divisor of
    ``nodes_per_env``: 1 on a GPU; a row of nodes on the CPU, where a thread per node costs more than the update).
    Writes (velocity, mass) to ``grid_v`` and clears the accumulators for the next substep.
    """
    first = wp.tid() * nodes_per_thread
    env = first / nodes_per_env
    if substep + step_base[0] >= env_steps[env]:
        return
    dt = env_dt[env]
    for n in range(first, first + nodes_per_thread):
        grid_update_node(n, env, dt, grid_mv, grid_held, env_acc, env_drag, env_ground, grid_contact, grid_rigid,
                         grid_v)


@wp.func(inline=True)
def particle_advect(tid: int, held: bool, xp: wp.vec3, fx: wp.vec3, vel: wp.vec3, bi: wp.vec3, bj: wp.vec3,
                    bk: wp.vec3, dt: float, dx: float, inv_dx: float, rigid: bool, ground_z: float,
                    x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33)):
    """Store a particle's gathered velocity ``vel`` and affine matrix and move it (held ones stay put).

    ``rigid``: the plane z = ``ground_z`` is a rigid floor (:func:`.contact_kernels.rigid_floor`), which the
    particle's centre may not pass; a floor that gives lets it sink (its spring pushes it back).

    ``bi, bj, bk``: Σ w v_node times the node's stencil offset i, j, k; B = (Σ w v (i, j, k)ᵀ − v fxᵀ) dx and
    C = 4 B / dx² (quadratic B-splines).
    """
    B = (wp.matrix_from_cols(bi, bj, bk) - wp.outer(vel, fx)) * dx
    C[tid] = (4.0 * inv_dx * inv_dx) * B
    if held:  # clamped material: stays put, deforms with the grid
        v[tid] = wp.vec3(0.0)
        return
    xn = xp + dt * vel
    if rigid and xn[2] < ground_z:
        xn = wp.vec3(xn[0], xn[1], ground_z)
    x[tid] = xn
    v[tid] = vel


def _make_g2p(grid: bool):
    """The G2P kernel; ``grid=True`` also updates H from the grid velocity's gradient (setting
    ``deformation_gradient = "grid"``, the default), compiled apart so that neither variant pays for the other."""

    def g2p(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
            H: wp.array(dtype=wp.mat33), code: wp.array(dtype=wp.int32), laws: wp.array(dtype=ClassLaw),
            tx: wp.array(dtype=wp.vec3),
            tv: wp.array(dtype=wp.vec3),
            t_held: wp.array(dtype=wp.int32), grid_v: wp.array(dtype=wp.vec4),
            env_dt: wp.array(dtype=float), env_steps: wp.array(dtype=wp.int32), env_origin: wp.array(dtype=wp.vec3),
            step_base: wp.array(dtype=wp.int32),
            n_per_env: int, n_particles: int, m_per_env: int, nodes_per_env: int, dims: wp.vec3i, dx: float,
            inv_dx: float, has_ground: int, ground_z: float, env_ground: wp.array(dtype=wp.vec3), substep: int):
        """Gather velocity and affine velocity to particles and advect them; advect the tracked points.

        Only a rigid floor puts particles back on the plane (:func:`particle_advect`).  Tracked points are never put
        back here, on any floor: they move with the material's velocity, and the host puts their *recorded* positions
        back on the plane (:func:`.contact.clamp_to_ground`).  Putting them back here detached them from the material:
        on the rigid floor a particle's lower face sinks about a millimetre into the floor's spring
        (:data:`.contact.RIGID_CONTACT_BETA`), the lower-face tracked points were held up on the plane by that much
        and kept the offset after the bounce, so they left the floor that much early (the drop's contact duration
        was 25 ms where the solid touched for 33; docs/mpm.md, "Contact duration").

        Threads ``[0, n_particles)`` are particles, the rest tracked points.  A tracked point's
        velocity is a mass-weighted affine least-squares fit of the node velocities of its stencil
        (exact for rigid motion and uniform strain, also at the surface where outer nodes are empty).
        """
        tid = wp.tid()
        particle = tid < n_particles
        env = int(0)
        held = bool(False)
        xp = wp.vec3()
        if particle:
            env = tid / n_per_env
            if substep + step_base[0] >= env_steps[env]:
                return
            c = code[tid]
            if c >= HELD_FLAG:
                held = True
                if laws[c % HELD_FLAG].held != 0:  # rigid (stationary): no deformation at all
                    v[tid] = wp.vec3(0.0)
                    C[tid] = wp.mat33(0.0)
                    return
            xp = x[tid]
        else:
            t = tid - n_particles
            env = t / m_per_env
            if substep + step_base[0] >= env_steps[env] or t_held[t] != 0:
                return
            xp = tx[t]
        if not wp.isfinite(xp):
            return
        origin = env_origin[env]
        base = stencil_base(xp, origin, inv_dx)
        if not stencil_inside(base, dims):
            return
        dt = env_dt[env]
        fx = (xp - origin) * inv_dx - base
        w = bspline_weights(fx)
        ib = int(base[0])
        jb = int(base[1])
        kb = int(base[2])
        block = env * nodes_per_env
        if particle:  # v = Σ w v_i and APIC's offset sums (particle_advect forms C from them)
            if wp.static(grid):  # F ← (I + Δt ∇v) F here, ∇v = Σ v_i ∇w_ip; P2G then only applies the law
                vel, bi, bj, bk, grad = gather_stencil_with_gradient(grid_v, block, ib, jb, kb, dims, w,
                                                                     bspline_slopes(fx))
                H[tid] = displacement_gradient_update(H[tid], (dt * inv_dx) * grad)
            else:
                vel, bi, bj, bk = gather_stencil(grid_v, block, ib, jb, kb, dims, w)
            particle_advect(tid, held, xp, fx, vel, bi, bj, bk, dt, dx, inv_dx,
                            rigid_floor(has_ground, env_ground[env]), ground_z, x, v, C)
            return
        # tracked point: mass-weighted affine least-squares fit of the stencil's node velocities, in stencil
        # coordinates e = (i, j, k) - 1 (cells; the point is at fx - 1).  The weighted moments are summed a stencil
        # row (i, j) at a time: with e in {-1, 0, 1} a row needs three mass sums and two momentum sums, and the
        # second moments follow from them (the fit is translation-invariant, so this is the centred fit of
        # velocities against node offsets, written with far fewer products)
        W = float(0.0)
        s1 = wp.vec3(0.0)  # sum wm e
        sxx = float(0.0)  # sum wm e e^T, its six entries
        syy = float(0.0)
        szz = float(0.0)
        sxy = float(0.0)
        sxz = float(0.0)
        syz = float(0.0)
        sv = wp.vec3(0.0)  # sum wm v
        svx = wp.vec3(0.0)  # sum wm v e^T, its columns
        svy = wp.vec3(0.0)
        svz = wp.vec3(0.0)
        vlo = wp.vec3(3.0e38)
        vhi = wp.vec3(-3.0e38)
        for i in range(3):
            ei = float(i) - 1.0
            for j in range(3):
                ej = float(j) - 1.0
                wij = w[i, 0] * w[j, 1]
                row = block + ((ib + i) * dims[1] + (jb + j)) * dims[2] + kb
                a0 = float(0.0)  # the row's sum wm, sum wm e_z, sum wm e_z^2
                a1 = float(0.0)
                a2 = float(0.0)
                r0 = wp.vec3(0.0)  # the row's sum wm v, sum wm v e_z
                r1 = wp.vec3(0.0)
                for k in range(3):
                    ek = float(k) - 1.0
                    gv = grid_v[row + k]
                    vi = wp.vec3(gv[0], gv[1], gv[2])
                    wm = (wij * w[k, 2]) * gv[3]  # 0 at an empty node (its velocity is 0 too)
                    wv = wm * vi
                    a0 = a0 + wm
                    a1 = a1 + ek * wm
                    a2 = a2 + (ek * ek) * wm
                    r0 = r0 + wv
                    r1 = r1 + ek * wv
                    if wm > 0.0:
                        vlo = wp.min(vlo, vi)
                        vhi = wp.max(vhi, vi)
                W = W + a0
                s1 = s1 + wp.vec3(ei * a0, ej * a0, a1)
                sxx = sxx + (ei * ei) * a0
                syy = syy + (ej * ej) * a0
                szz = szz + a2
                sxy = sxy + (ei * ej) * a0
                sxz = sxz + ei * a1
                syz = syz + ej * a1
                sv = sv + r0
                svx = svx + ei * r0
                svy = svy + ej * r0
                svz = svz + r1
        t = tid - n_particles
        vt = tv[t]
        if W > 0.0:
            ebar = s1 / W
            vbar = sv / W
            cov = wp.mat33(sxx, sxy, sxz, sxy, syy, syz, sxz, syz, szz) - W * wp.outer(ebar, ebar) + wp.identity(
                n=3, dtype=float) * (TRACKED_FIT_REGULARISATION * W)
            grad = (wp.matrix_from_cols(svx, svy, svz) - W * wp.outer(vbar, ebar)) @ wp.inverse(cov)  # m/s per cell
            fit = vbar + grad @ (fx - wp.vec3(1.0) - ebar)  # the fitted field at the tracked point
            # guard against ill-conditioned fits (few massive nodes, e.g. in a thin film): stay within the node
            # velocities' range widened by that range on each side (a single node gives its own velocity)
            spread = vhi - vlo
            fit = wp.min(wp.max(fit, vlo - spread), vhi + spread)
            vt = vbar
            if wp.isfinite(fit):
                vt = fit
        tx[t] = xp + dt * vt  # never put back on the plane here: a tracked point moves with the material
        tv[t] = vt

    g2p.__name__ = g2p.__qualname__ = "g2p_grid" if grid else "g2p"
    return wp.kernel(g2p)


g2p = _make_g2p(False)
g2p_grid = _make_g2p(True)
"""``g2p`` with ``deformation_gradient = "grid"``: also updates each particle's H from the gradient of the grid's
velocity."""


@wp.kernel
def set_step(step_base: wp.array(dtype=wp.int32), value: int):
    """``step_base[0] = value`` (the substep index that a graph of substeps starts from)."""
    step_base[0] = value


@wp.kernel
def advance_step(step_base: wp.array(dtype=wp.int32), count: int):
    """``step_base[0] += count`` (the last node of a graph of ``count`` substeps)."""
    step_base[0] = step_base[0] + count


# ------------------------------------------------------------------------------ per-frame kernels
@wp.kernel
def velocity_kick(v: wp.array(dtype=wp.vec3), code: wp.array(dtype=wp.int32), tracked_v: wp.array(dtype=wp.vec3),
                  tracked_held: wp.array(dtype=wp.int32), env_acc: wp.array(dtype=wp.vec3),
                  env_tau: wp.array(dtype=float), n_per_env: int, m_per_env: int, n_total: int):
    """Leapfrog bookkeeping for the body forces: v += τ_e a_e for every free particle (threads < n_total) and
    tracked point (the rest) of environment e; a_e: (E,) m/s² gravity + extra acceleration, τ_e: (E,) s.
    With τ = −Δt/2 before the first substep and (Δt − Δt')/2 where the substep changes, the stored velocities
    stay half a substep behind the positions, so a free fall is exact instead of falling g t Δt/2 too far."""
    tid = wp.tid()
    if tid < n_total:
        env = tid / n_per_env
        if code[tid] < HELD_FLAG:
            v[tid] = v[tid] + env_tau[env] * env_acc[env]
    else:
        k = tid - n_total
        env = k / m_per_env
        if tracked_held[k] == 0:
            tracked_v[k] = tracked_v[k] + env_tau[env] * env_acc[env]


@wp.kernel
def frame_stats(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float),
                vol: wp.array(dtype=float), mu_p: wp.array(dtype=float), lam_p: wp.array(dtype=float),
                plastic: wp.array(dtype=float), code: wp.array(dtype=wp.int32), laws: wp.array(dtype=ClassLaw),
                tx: wp.array(dtype=wp.vec3), n_per_env: int, m_per_env: int, lanes: int,
                out_lo: wp.array(dtype=wp.vec3), out_hi: wp.array(dtype=wp.vec3), out_stats: wp.array(dtype=wp.vec3)):
    """Per-lane partial reductions: bounds of particles and tracked points, max speed², max wave speed², bad count.

    Lane ``l`` of environment ``e`` (thread ``e * lanes + l``) visits particles ``l, l + lanes, ...``
    (coalesced); the host finishes the reduction over lanes.
    """
    tid = wp.tid()
    env = tid / lanes
    lane = tid - env * lanes
    big = float(3.0e38)
    lo = wp.vec3(big)
    hi = wp.vec3(-big)
    vmax2 = float(0.0)
    c2max = float(0.0)
    bad = float(0.0)
    i = lane
    while i < n_per_env:
        p = env * n_per_env + i
        xp = x[p]
        vp = v[p]
        if wp.isfinite(xp) and wp.isfinite(vp):
            lo = wp.min(lo, xp)
            hi = wp.max(hi, xp)
            vmax2 = wp.max(vmax2, wp.dot(vp, vp))
            c = code[p]
            law = laws[c % HELD_FLAG]
            if law.held == 0:
                modulus = lam_p[p] + 2.0 * mu_p[p]
                if law.elastic == LAW_WEAKLY_COMPRESSIBLE:
                    modulus = lam_p[p] + 2.0 / 3.0 * mu_p[p]
                if law.plastic == PLASTIC_SNOW:
                    modulus = modulus * wp.min(wp.exp(law.hardening * (1.0 - plastic[p])), law.max_hardening)
                c2max = wp.max(c2max, modulus * vol[p] / mass[p])
        else:
            bad = bad + 1.0
        i = i + lanes
    i = lane
    while i < m_per_env:
        xt = tx[env * m_per_env + i]
        if wp.isfinite(xt):
            lo = wp.min(lo, xt)
            hi = wp.max(hi, xt)
        else:
            bad = bad + 1.0
        i = i + lanes
    out_lo[tid] = lo
    out_hi[tid] = hi
    out_stats[tid] = wp.vec3(vmax2, c2max, bad)


@wp.kernel
def cell_keys(x: wp.array(dtype=wp.vec3), code: wp.array(dtype=wp.int32), laws: wp.array(dtype=ClassLaw),
              env_origin: wp.array(dtype=wp.vec3), n_per_env: int, nodes_per_env: int, dims: wp.vec3i, inv_dx: float,
              rigid_last: int, keys: wp.array(dtype=wp.int32), values: wp.array(dtype=wp.int32)):
    """Sort keys: the node index of each particle's stencil centre (environment blocks in order).

    ``rigid_last`` = 1 (one environment only): the held particles of rigid classes get keys after every other
    particle's (+ ``nodes_per_env``), so the stable sort puts them at the end, the others in the same order as
    without it, and P2G and G2P can be launched over the others alone (they skip rigid particles anyway)."""
    p = wp.tid()
    env = p / n_per_env
    xp = x[p]
    key = env * nodes_per_env
    c = code[p]
    if rigid_last != 0 and c >= HELD_FLAG:
        if laws[c % HELD_FLAG].held != 0:
            key = key + nodes_per_env
    if wp.isfinite(xp):
        b = stencil_base(xp, env_origin[env], inv_dx)
        i = wp.clamp(int(b[0]) + 1, 0, dims[0] - 1)
        j = wp.clamp(int(b[1]) + 1, 0, dims[1] - 1)
        k = wp.clamp(int(b[2]) + 1, 0, dims[2] - 1)
        key = key + (i * dims[1] + j) * dims[2] + k
    keys[p] = key
    values[p] = p


@wp.kernel
def gather_particles(order: wp.array(dtype=wp.int32),
                     x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
                     H: wp.array(dtype=wp.mat33), rot: wp.array(dtype=wp.quat), plastic: wp.array(dtype=float),
                     mass: wp.array(dtype=float),
                     vol: wp.array(dtype=float), mu_p: wp.array(dtype=float), lam_p: wp.array(dtype=float),
                     code: wp.array(dtype=wp.int32), pid: wp.array(dtype=wp.int32),
                     x2: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3), C2: wp.array(dtype=wp.mat33),
                     H2: wp.array(dtype=wp.mat33), rot2: wp.array(dtype=wp.quat), plastic2: wp.array(dtype=float),
                     mass2: wp.array(dtype=float),
                     vol2: wp.array(dtype=float), mu2: wp.array(dtype=float), lam2: wp.array(dtype=float),
                     code2: wp.array(dtype=wp.int32), pid2: wp.array(dtype=wp.int32)):
    """Reorder every particle field by ``order`` (cell-sorted) into the second buffer."""
    i = wp.tid()
    s = order[i]
    x2[i] = x[s]
    v2[i] = v[s]
    C2[i] = C[s]
    H2[i] = H[s]
    rot2[i] = rot[s]
    plastic2[i] = plastic[s]
    mass2[i] = mass[s]
    vol2[i] = vol[s]
    mu2[i] = mu_p[s]
    lam2[i] = lam_p[s]
    code2[i] = code[s]
    pid2[i] = pid[s]


@wp.kernel
def scatter_state(pid: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                  H: wp.array(dtype=wp.mat33), plastic: wp.array(dtype=float), count: int,
                  out_x: wp.array(dtype=wp.vec3), out_v: wp.array(dtype=wp.vec3), out_J: wp.array(dtype=float),
                  out_plastic: wp.array(dtype=float)):
    """Particle state of environment 0 in the original particle order (for baking)."""
    p = wp.tid()
    q = pid[p]
    if q < count:
        out_x[q] = x[p]
        out_v[q] = v[p]
        out_J[q] = wp.determinant(wp.identity(n=3, dtype=float) + H[p])
        out_plastic[q] = plastic[p]
