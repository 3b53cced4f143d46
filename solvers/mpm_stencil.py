"""The quadratic B-spline stencil of the MPM solver: weights and slopes, the stencil's corner and bounds, and a
particle's gather of the grid's velocity over its 3×3×3 nodes (with or without the velocity's gradient).

Warp functions only (no kernels): :mod:`.mpm_kernels` and the GPU-tuned :mod:`.mpm_kernels_cuda` build their G2P
and P2G from them, so the CPU and the GPU gather the same sums.  Grid layout as in :mod:`.mpm_kernels` (an
environment's block of ``nx·ny·nz`` nodes, x-major, z fastest; a node is a ``vec4``: velocity or momentum, then
mass).  Depends on Warp alone.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def bspline_weights(fx: wp.vec3):
    """Quadratic B-spline weights of the 3 nodes per axis (rows: node offset 0, 1, 2; columns: axis)."""
    w0 = wp.vec3(0.5 * (1.5 - fx[0]) * (1.5 - fx[0]), 0.5 * (1.5 - fx[1]) * (1.5 - fx[1]),
                 0.5 * (1.5 - fx[2]) * (1.5 - fx[2]))
    w1 = wp.vec3(0.75 - (fx[0] - 1.0) * (fx[0] - 1.0), 0.75 - (fx[1] - 1.0) * (fx[1] - 1.0),
                 0.75 - (fx[2] - 1.0) * (fx[2] - 1.0))
    w2 = wp.vec3(0.5 * (fx[0] - 0.5) * (fx[0] - 0.5), 0.5 * (fx[1] - 0.5) * (fx[1] - 0.5),
                 0.5 * (fx[2] - 0.5) * (fx[2] - 0.5))
    return wp.mat33(w0[0], w0[1], w0[2], w1[0], w1[1], w1[2], w2[0], w2[1], w2[2])


@wp.func
def bspline_slopes(fx: wp.vec3):
    """d/d(fx) of :func:`bspline_weights` (per cell; divide by Δx for per metre), same layout."""
    return wp.mat33(fx[0] - 1.5, fx[1] - 1.5, fx[2] - 1.5,
                    2.0 * (1.0 - fx[0]), 2.0 * (1.0 - fx[1]), 2.0 * (1.0 - fx[2]),
                    fx[0] - 0.5, fx[1] - 0.5, fx[2] - 0.5)


@wp.func
def stencil_base(xp: wp.vec3, origin: wp.vec3, inv_dx: float):
    """Lower corner (node indices) of the 3×3×3 stencil of a point, as float vector."""
    g = (xp - origin) * inv_dx
    return wp.vec3(wp.floor(g[0] - 0.5), wp.floor(g[1] - 0.5), wp.floor(g[2] - 0.5))


@wp.func
def plus_offset_times(acc: wp.vec3, offset: int, v: wp.vec3):
    """acc + offset · v for a stencil offset 0, 1 or 2 (m/s or m·kg/s alike), without the products by 0 and 1: the
    same sums as ``acc + float(offset) * v``, a few multiplications fewer in the 27-node loops."""
    if offset == 1:
        return acc + v
    if offset == 2:
        return acc + 2.0 * v
    return acc


@wp.func
def stencil_inside(base: wp.vec3, dims: wp.vec3i):
    return (base[0] >= 0.0 and base[1] >= 0.0 and base[2] >= 0.0 and base[0] <= float(dims[0] - 3)
            and base[1] <= float(dims[1] - 3) and base[2] <= float(dims[2] - 3))


LOAD_NODE_SNIPPET = r"""
#if defined(__CUDA_ARCH__)
    const float4 r = __ldg(reinterpret_cast<const float4*>(wp::address(grid, index)));
    return wp::vec_t<4, wp::float32>(r.x, r.y, r.z, r.w);
#else
    return wp::index(grid, index);
#endif
"""


@wp.func_native(LOAD_NODE_SNIPPET)
def load_node(grid: wp.array(dtype=wp.vec4), index: int) -> wp.vec4:
    """``grid[index]`` as one 16-byte read-only load on a GPU (the array must not change during the kernel)."""
    ...


@wp.func
def add_stencil_row_with_gradient(vel: wp.vec3, bi: wp.vec3, bj: wp.vec3, bk: wp.vec3, gx: wp.vec3, gy: wp.vec3,
                                  gz: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, w: wp.mat33, dw: wp.mat33,
                                  i: int, j: int):
    """Add stencil row (i, j) — node velocities ``v0, v1, v2`` (m/s) at k = 0, 1, 2 — to a particle's gather, for the
    setting ``deformation_gradient = "grid"``: the velocity ``vel`` = Σ w v, APIC's offset sums ``bi, bj, bk`` =
    Σ w v · (i, j, k) (:func:`particle_advect`) and the columns ``gx, gy, gz`` of the grid velocity's gradient
    Σ v ⊗ ∇w (per cell: × 1/Δx for 1/s).  ``w`` the B-spline weights, ``dw`` their slopes (:func:`bspline_slopes`).

    The row is first summed along k (Σ_k w_k v, Σ_k k w_k v, Σ_k dw_k v); everything else is that row sum times a
    product of the i and j factors, which costs fewer products than a node at a time: the gather with the gradient
    costs about what the gather without it does node by node."""
    a0 = w[0, 2] * v0
    a1 = w[1, 2] * v1
    a2 = w[2, 2] * v2
    s0 = a0 + a1 + a2
    wij = w[i, 0] * w[j, 1]
    r = wij * s0
    return (vel + r, plus_offset_times(bi, i, r), plus_offset_times(bj, j, r), bk + wij * (a1 + 2.0 * a2),
            gx + (dw[i, 0] * w[j, 1]) * s0, gy + (w[i, 0] * dw[j, 1]) * s0,
            gz + wij * (dw[0, 2] * v0 + dw[1, 2] * v1 + dw[2, 2] * v2))


@wp.func
def gather_stencil(grid_v: wp.array(dtype=wp.vec4), block: int, ib: int, jb: int, kb: int, dims: wp.vec3i, w: wp.mat33):
    """A particle's gather for ``deformation_gradient = "affine"``: (``vel`` = Σ w v m/s, APIC's offset sums ``bi, bj,
    bk`` = Σ w v · (i, j, k), :func:`particle_advect`) over the 3×3×3 stencil whose lower corner is node (``ib, jb,
    kb``) of the environment's block starting at ``block``, a node at a time (nodes read with :func:`load_node`)."""
    vel = wp.vec3(0.0)
    bi = wp.vec3(0.0)
    bj = wp.vec3(0.0)
    bk = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            wij = w[i, 0] * w[j, 1]
            row = block + ((ib + i) * dims[1] + (jb + j)) * dims[2] + kb
            for k in range(3):
                gv = load_node(grid_v, row + k)
                wv = (wij * w[k, 2]) * wp.vec3(gv[0], gv[1], gv[2])
                vel = vel + wv
                bi = plus_offset_times(bi, i, wv)
                bj = plus_offset_times(bj, j, wv)
                bk = plus_offset_times(bk, k, wv)
    return vel, bi, bj, bk


@wp.func
def gather_stencil_with_gradient(grid_v: wp.array(dtype=wp.vec4), block: int, ib: int, jb: int, kb: int,
                                 dims: wp.vec3i, w: wp.mat33, dw: wp.mat33):
    """A particle's whole gather for ``deformation_gradient = "grid"``: (``vel`` m/s, APIC's offset sums ``bi, bj, bk``
    (:func:`particle_advect`), the grid velocity's gradient Σ v ⊗ ∇w per cell (× 1/Δx for 1/s)) over the 3×3×3
    stencil whose lower corner is node (``ib, jb, kb``) of the environment's block starting at ``block``, a stencil row
    at a time (:func:`add_stencil_row_with_gradient`; nodes read with :func:`load_node`)."""
    zero = wp.vec3(0.0)
    vel, bi, bj, bk, gx, gy, gz = zero, zero, zero, zero, zero, zero, zero
    for i in range(3):
        for j in range(3):
            row = block + ((ib + i) * dims[1] + (jb + j)) * dims[2] + kb
            n0 = load_node(grid_v, row)
            n1 = load_node(grid_v, row + 1)
            n2 = load_node(grid_v, row + 2)
            vel, bi, bj, bk, gx, gy, gz = add_stencil_row_with_gradient(
                vel, bi, bj, bk, gx, gy, gz, wp.vec3(n0[0], n0[1], n0[2]), wp.vec3(n1[0], n1[1], n1[2]),
                wp.vec3(n2[0], n2[1], n2[2]), w, dw, i, j)
    return vel, bi, bj, bk, wp.matrix_from_cols(gx, gy, gz)
