"""GPU-tuned variants of the MPM substep kernels (a separate Warp module: the CPU never compiles them
unless asked to).

The physics is :mod:`.mpm_kernels`' (the same ``wp.func`` for the deformation update, the particle's side of
P2G (:func:`.mpm_kernels.particle_transfer`), the transfers and the tracked-point fit) and the laws are
:mod:`.constitutive`'s; what differs is how the work is laid out on a GPU:

* **P2G scatter** (:data:`P2G_KERNELS`):

  - ``"vector"``: each of the 27 node contributions (momentum + mass) is one 16-byte vector reduction
    ``red.global.add.v4.f32`` (sm_90 and later; Warp's vec4 atomic is four scalar atomics), else four
    scalar atomics.
  - ``"warp"``: warp-aggregated.  Particles are cell-sorted, so the 32 threads of a warp mostly share a
    few stencils.  Lanes with the same stencil (same lower node, hence the same 27 target nodes) are
    grouped once per substep (``__match_any_sync`` on the stencil's node index); per node the group's
    contributions are summed in a tree of register shuffles over the group's members and only the
    group's first lane issues the vector reduction.  Groups need not be contiguous lanes (the order
    decays between sorts).  Sums are reassociated, nothing else changes.

* **G2P** for the particles alone, :data:`g2p_particles` (no tracked-point code, so far fewer registers
  and higher occupancy: the tracked points' fit needs ~170 registers); node loads are one 16-byte
  read-only load (``__ldg``) each.  The tracked points are then moved by :data:`.mpm_kernels.g2p`
  launched over them alone (``n_particles = 0``).

Every native snippet is guarded by ``__CUDA_ARCH__``; on the CPU the kernels run with plain atomics
and loads and give bitwise the results of :mod:`.mpm_kernels` (which the tests check).  The kernels
that scatter with ``"warp"`` must be launched with the thread count rounded up to a multiple of 32
(:func:`padded_launch_dim`): whole warps, with the extra lanes inactive, one item per thread (no
``max_blocks``: every lane of a warp must reach the warp-wide grouping exactly once).
"""

from __future__ import annotations

import warp as wp

from .constitutive import ClassLaw
from .contact_kernels import rigid_floor
from .mpm_kernels import (HELD_FLAG, displacement_gradient_update, particle_advect, particle_stress_elastic,
                          particle_stress_general, particle_transfer)
from .mpm_stencil import (bspline_slopes, bspline_weights, gather_stencil, gather_stencil_with_gradient, stencil_base,
                          stencil_inside)

wp.set_module_options({"enable_backward": False})

WARP_SIZE = 32
SCATTER_MODES = ("atomic", "vector", "warp")
"""P2G scatter modes: ``"atomic"`` is :mod:`.mpm_kernels`' kernel (one Warp vec4 atomic per node)."""


def padded_launch_dim(threads: int) -> int:
    """Thread count rounded up to whole warps (the ``"warp"`` scatter needs every warp complete)."""
    return -(-threads // WARP_SIZE) * WARP_SIZE


# ------------------------------------------------------------------------------ native helpers
WARP_GROUPS_SNIPPET = r"""
#if defined(__CUDA_ARCH__)
    // Lanes of this warp that scatter to the same stencil (same key) form a group.  Returned plan:
    // [0] the active lanes' mask, [1] per tree step t (5 bits each) the lane to read, [2] flags: bit t =
    // step t adds, bit 5 = this lane is its group's first (it issues the reduction), bits 6-8 = steps.
    const unsigned active_mask = __ballot_sync(0xffffffffu, active);
    if (!active)
        return wp::vec_t<4, wp::int32>(0, 0, 0, 0);
    const unsigned peers = __match_any_sync(active_mask, key);
    const int lane = (int)(threadIdx.x & 31u);
    const int rank = __popc(peers & ((1u << lane) - 1u));
    const int size = __popc(peers);
#if __CUDA_ARCH__ >= 800
    const int largest = (int)__reduce_max_sync(active_mask, (unsigned)size);
#else
    const int largest = 32;
#endif
    int steps = 0;
    while ((1 << steps) < largest)
        ++steps;
    int sources = 0;
    int flags = (rank == 0 ? 32 : 0) | (steps << 6);
    for (int t = 0; t < steps; ++t) {
        const int stride = 1 << t;
        int source = lane;
        if ((rank & (2 * stride - 1)) == 0 && rank + stride < size) {
            // the lane of the group member of rank (rank + stride): the lowest bit position b with
            // more than rank + stride members at positions <= b
            const int want = rank + stride;
            int lo = 0;
            int hi = 31;
            while (lo < hi) {
                const int mid = (lo + hi) >> 1;
                const unsigned upto = (mid == 31) ? 0xffffffffu : ((2u << mid) - 1u);
                if (__popc(peers & upto) > want)
                    hi = mid;
                else
                    lo = mid + 1;
            }
            source = lo;
            flags |= 1 << t;
        }
        sources |= source << (5 * t);
    }
    return wp::vec_t<4, wp::int32>((int)active_mask, sources, flags, 0);
#else
    return wp::vec_t<4, wp::int32>(0, 0, 0, 0);
#endif
"""


@wp.func_native(WARP_GROUPS_SNIPPET)
def warp_groups(active: bool, key: int) -> wp.vec4i:
    """Group the warp's active lanes by ``key`` (all lanes of the warp must call this); see the snippet."""
    ...


VECTOR_RED_SNIPPET = r"""
    float* address = reinterpret_cast<float*>(wp::address(grid, index));
#if __CUDA_ARCH__ >= 900
    asm volatile("red.global.add.v4.f32 [%0], {%1, %2, %3, %4};"
                 :: "l"(__cvta_generic_to_global(address)), "f"(a), "f"(b), "f"(c), "f"(d) : "memory");
#else
    atomicAdd(address, a);
    atomicAdd(address + 1, b);
    atomicAdd(address + 2, c);
    atomicAdd(address + 3, d);
#endif
"""

SCATTER_VECTOR_SNIPPET = (r"""
#if defined(__CUDA_ARCH__)
    const float a = value[0];
    const float b = value[1];
    const float c = value[2];
    const float d = value[3];
""" + VECTOR_RED_SNIPPET + r"""
#else
    wp::atomic_add(grid, index, value);
#endif
""")


@wp.func_native(SCATTER_VECTOR_SNIPPET)
def scatter_vector(grid: wp.array(dtype=wp.vec4), index: int, value: wp.vec4):
    """``grid[index] += value`` as one 16-byte vector reduction (sm_90+; four atomics before, plain on the CPU)."""
    ...


SCATTER_WARP_SNIPPET = (r"""
#if defined(__CUDA_ARCH__)
    const unsigned active_mask = (unsigned)plan[0];
    const int sources = plan[1];
    const int flags = plan[2];
    const int steps = (flags >> 6) & 7;
    float a = value[0];
    float b = value[1];
    float c = value[2];
    float d = value[3];
    for (int t = 0; t < steps; ++t) {
        // tree over the group's members by rank: after step t, ranks divisible by 2^(t+1) hold the sum
        // of their next 2^(t+1) ranks (every active lane shuffles; only flagged lanes add)
        const int source = (sources >> (5 * t)) & 31;
        const float oa = __shfl_sync(active_mask, a, source);
        const float ob = __shfl_sync(active_mask, b, source);
        const float oc = __shfl_sync(active_mask, c, source);
        const float od = __shfl_sync(active_mask, d, source);
        if (flags & (1 << t)) {
            a += oa;
            b += ob;
            c += oc;
            d += od;
        }
    }
    if (flags & 32) {
""" + VECTOR_RED_SNIPPET + r"""
    }
#else
    wp::atomic_add(grid, index, value);
#endif
""")


@wp.func_native(SCATTER_WARP_SNIPPET)
def scatter_warp(grid: wp.array(dtype=wp.vec4), index: int, value: wp.vec4, plan: wp.vec4i):
    """``grid[index] += value`` summed over the lane's group (``plan`` from :func:`warp_groups`) first."""
    ...


# ------------------------------------------------------------------------------ P2G
def _make_p2g(general: bool, scatter: str):
    """P2G with the ``"vector"`` or ``"warp"`` scatter; ``general`` as in :func:`.mpm_kernels._make_p2g`.

    Same arguments as :data:`.mpm_kernels.p2g_general`; threads ``>= n_particles`` (the padding of
    the last warp) do nothing.  No lane returns before the warp-wide grouping.
    """
    aggregated = scatter == "warp"

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
        p = wp.tid()
        env = int(0)
        active = bool(False)
        if p < n_particles:
            env = p / n_per_env
            active = substep + step_base[0] < env_steps[env]
        xp = wp.vec3(0.0)
        origin = wp.vec3(0.0)
        base = wp.vec3(0.0)
        if active:
            xp = x[p]
            origin = env_origin[env]
            base = stencil_base(xp, origin, inv_dx)
            if not (wp.isfinite(xp) and stencil_inside(base, dims)):
                wp.atomic_add(lost, env, 1)
                active = False
                base = wp.vec3(0.0)
            elif rigid_static != 0:  # a held particle of a rigid class: its mass is on the grid already
                c0 = code[p]
                if c0 >= HELD_FLAG and laws[c0 % HELD_FLAG].held != 0:
                    active = False
                    base = wp.vec3(0.0)
        ib = int(base[0])
        jb = int(base[1])
        kb = int(base[2])
        block = env * nodes_per_env
        plan = wp.vec4i(0)
        if wp.static(aggregated):
            plan = warp_groups(active, block + (ib * dims[1] + jb) * dims[2] + kb)
        if not active:
            return

        dt = env_dt[env]
        c = code[p]
        held = c >= HELD_FLAG
        law = laws[c % HELD_FLAG]
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
        for i in range(3):
            ai = a0 + float(i) * cols[0]
            wi = w[i, 0]
            for j in range(3):
                aij = ai + float(j) * cols[1]
                wij = wi * w[j, 1]
                row = block + ((ib + i) * dims[1] + (jb + j)) * dims[2] + kb
                for k in range(3):
                    weight = wij * w[k, 2]
                    mom = weight * (aij + float(k) * cols[2])
                    contribution = wp.vec4(mom[0], mom[1], mom[2], weight * m)
                    if wp.static(aggregated):
                        scatter_warp(grid_mv, row + k, contribution, plan)
                    else:
                        scatter_vector(grid_mv, row + k, contribution)
                    if held:
                        wp.atomic_add(grid_held, row + k, weight * m)
                    if jn > 0.0:
                        wp.atomic_add(grid_contact, row + k, weight * jn)

    name = f"p2g_{scatter}_{'general' if general else 'elastic'}"
    p2g.__name__ = p2g.__qualname__ = name
    p2g.__doc__ = f"P2G, {'general' if general else 'elastic-only'} law, '{scatter}' scatter (see the module docstring)."
    return wp.kernel(p2g)


P2G_KERNELS = {(scatter, general): _make_p2g(general, scatter)
               for scatter in ("vector", "warp") for general in (False, True)}
"""``(scatter, general) -> kernel`` for the ``"vector"`` and ``"warp"`` scatter modes."""


# ------------------------------------------------------------------------------ G2P, split
def _make_g2p_particles(grid: bool):
    """The split particle G2P; ``grid`` as in :func:`.mpm_kernels._make_g2p`."""

    def g2p_particles(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
                      H: wp.array(dtype=wp.mat33), code: wp.array(dtype=wp.int32), laws: wp.array(dtype=ClassLaw),
                      grid_v: wp.array(dtype=wp.vec4),
                      env_dt: wp.array(dtype=float), env_steps: wp.array(dtype=wp.int32),
                      env_origin: wp.array(dtype=wp.vec3), step_base: wp.array(dtype=wp.int32),
                      n_per_env: int, nodes_per_env: int, dims: wp.vec3i, dx: float, inv_dx: float, has_ground: int,
                      ground_z: float, env_ground: wp.array(dtype=wp.vec3), substep: int):
        """The particle half of :data:`.mpm_kernels.g2p` (same results): gather v and C (and, compiled with ``grid``,
        update H from the grid's velocity gradient), advect."""
        tid = wp.tid()
        env = tid / n_per_env
        if substep + step_base[0] >= env_steps[env]:
            return
        c = code[tid]
        held = c >= HELD_FLAG
        if held:
            if laws[c % HELD_FLAG].held != 0:  # rigid (stationary): no deformation at all
                v[tid] = wp.vec3(0.0)
                C[tid] = wp.mat33(0.0)
                return
        xp = x[tid]
        if not wp.isfinite(xp):
            return
        origin = env_origin[env]
        base = stencil_base(xp, origin, inv_dx)
        if not stencil_inside(base, dims):
            return
        fx = (xp - origin) * inv_dx - base
        w = bspline_weights(fx)
        ib = int(base[0])
        jb = int(base[1])
        kb = int(base[2])
        block = env * nodes_per_env
        if wp.static(grid):
            vel, bi, bj, bk, grad = gather_stencil_with_gradient(grid_v, block, ib, jb, kb, dims, w,
                                                                 bspline_slopes(fx))
            H[tid] = displacement_gradient_update(H[tid], (env_dt[env] * inv_dx) * grad)
        else:
            vel, bi, bj, bk = gather_stencil(grid_v, block, ib, jb, kb, dims, w)
        particle_advect(tid, held, xp, fx, vel, bi, bj, bk, env_dt[env], dx, inv_dx,
                        rigid_floor(has_ground, env_ground[env]), ground_z, x, v, C)

    g2p_particles.__name__ = g2p_particles.__qualname__ = "g2p_particles_grid" if grid else "g2p_particles"
    return wp.kernel(g2p_particles)


g2p_particles = _make_g2p_particles(False)
g2p_particles_grid = _make_g2p_particles(True)
"""``g2p_particles`` with ``deformation_gradient = "grid"``: also updates each particle's H from the gradient of the
grid's velocity."""
