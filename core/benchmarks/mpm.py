"""``unipixie bench mpm``: MPM throughput in particle-substeps per second, against a reference APIC solver.

Case: a cube of jelly (fixed-corotated, E = 1 MPa, ν = 0.3, 1000 kg/m³) as a lattice of N
particles, 2 per cell per axis (8 per cell), falling at 1 m/s just above a frictionless ground
under gravity.  Both solvers take the same particles, cell size, time step and substep count.

* ours: :func:`unipixie.solvers.mpm.prepare` once, then ``sim.run([])`` of one frame of
  ``--substeps`` substeps (the time step is capped with ``max_dt``); the timed run includes
  everything a diagnosis re-run pays (initial-state reset, grid placement, particle sort,
  stepping, divergence checks, reading the tracked points back).  ``--variants`` times several
  presets of the solver's GPU-tuning settings (:data:`VARIANTS`) on the same prepared simulation,
  each followed by one profiled run whose per-kernel times (CUDA events on a GPU) are recorded as
  ``breakdown`` in µs per substep (p2g, grid_update, g2p, g2p_tracked, sort, frame_stats), with the
  profiled run's wall time and what the kernels leave of it (host work, launches, read-backs).
* reference: a straightforward PhysGaussian-style APIC solver written below (stepping only
  timed; initial state uploaded once): per substep it launches six kernels — clear the grid,
  compute stress (an SVD of every particle's F and a per-particle stress write), P2G (APIC
  momentum + stress, separate float and vec3 atomics into 3-D arrays), grid normalisation +
  gravity, ground collider, G2P (velocity, APIC C, F update, advection) — over a fixed cubic grid
  around the body, with particles in their original (unsorted) order and the material model
  chosen by branching on a model struct.

The metric is N × substeps / median wall time over ``--runs`` runs (after one warm-up run).
After timing, the two solvers' particle positions are compared (they solve the same
discretised equations; differences come from transfer details and float order), and every
variant's with the first variant's.  A variant that fails is reported and skipped.
"""

# No ``from __future__ import annotations``: the reference kernels are defined inside a function (so
# that importing this module for ``unipixie --help`` does not import Warp) and Warp must evaluate their
# annotations there.
import functools
import math
import statistics

import numpy as np

from ..commands._common import positive_int
from . import synchronized_times

HELP = "MPM solver throughput (particle-substeps/s) at several particle counts, with a reference APIC solver"

E_BENCH, NU_BENCH, RHO_BENCH = 1.0e6, 0.3, 1000.0
SPACING = 0.005  # m between particles; dx = 2 * SPACING
DROP_SPEED = 1.0  # m/s


VARIANTS = {
    "default": {},
    "baseline": {"p2g_scatter": "atomic", "split_g2p": False, "graph_substeps": 0},
    "graphs": {"p2g_scatter": "atomic", "split_g2p": False, "graph_substeps": 16},
    "split": {"p2g_scatter": "atomic", "split_g2p": True, "graph_substeps": 16},
    "vector": {"p2g_scatter": "vector", "split_g2p": True, "graph_substeps": 16},
    "warp": {"p2g_scatter": "warp", "split_g2p": True, "graph_substeps": 16},
    "warp-b128": {"p2g_scatter": "warp", "split_g2p": True, "graph_substeps": 16, "block_dim": 128},
    "warp-b512": {"p2g_scatter": "warp", "split_g2p": True, "graph_substeps": 16, "block_dim": 512},
    "warp-sort25": {"p2g_scatter": "warp", "split_g2p": True, "graph_substeps": 16, "sort_interval": 25},
    "affine": {"deformation_gradient": "affine"},
    "grid": {"deformation_gradient": "grid"},
}
"""Solver-setting presets compared by ``--variants`` (each builds on the solver's defaults; ``default`` = as
shipped: on CUDA the same as ``warp``).  ``baseline`` is the kernel layout measured before the GPU work
(Warp vec4 atomics, one G2P kernel, a Python launch per kernel)."""
TUNING_FIELDS = ("p2g_scatter", "split_g2p", "graph_substeps", "block_dim", "sort_interval", "deformation_gradient")


def add_arguments(p):
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--sizes", default="50000,200000,1000000",
                   help="comma-separated particle counts (rounded to cubes; default: 50000,200000,1000000)")
    p.add_argument("--runs", type=int, default=3, help="timed runs per size and solver (median; default 3)")
    p.add_argument("--substeps", type=positive_int, default=None,
                   help="substeps per timed run (default: 100 on a GPU, 10 on the CPU)")
    p.add_argument("--variants", default="default",
                   help="comma-separated solver-setting presets to compare in the same run: "
                        + ", ".join(VARIANTS) + " (default: default)")
    p.add_argument("--no-breakdown", action="store_true",
                   help="skip the per-kernel timing run of each variant (CUDA events on a GPU)")
    p.add_argument("--no-reference", action="store_true", help="skip the reference solver")
    p.add_argument("--no-sort", action="store_true",
                   help="run our solver without its per-chunk cell sort of the particles (to measure what it buys)")


# ------------------------------------------------------------------------------------------ reference solver
@functools.lru_cache(maxsize=None)
def _reference_kernels():
    """Build the reference solver's kernels once (compiled on first launch; never redefined, so timed runs
    never include a module reload)."""
    import warp as wp

    @wp.struct
    class RefModel:
        material: int  # 0 = fixed corotated (the only one the benchmark uses; others branch away)
        n_grid: int
        dx: float
        inv_dx: float
        dt: float
        gravity: wp.vec3
        ground_z: float
        grid_origin: wp.vec3

    @wp.func
    def ref_stencil(model: RefModel, xp: wp.vec3):
        """The quadratic B-spline stencil of a particle at ``xp`` (m): the index of its 3×3×3 block's lowest grid
        node (vec3i), the particle's offset from that node in cells (vec3, each in [0.5, 1.5)) and the weights
        (mat33: w[i, a] is the weight of the block's node i = 0, 1, 2 along axis a; a node's weight is the product
        over the three axes)."""
        g = (xp - model.grid_origin) * model.inv_dx
        base = wp.vec3i(int(g[0] - 0.5), int(g[1] - 0.5), int(g[2] - 0.5))
        fx = g - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        wa = wp.vec3(1.5) - fx
        wb = fx - wp.vec3(1.0)
        wc = fx - wp.vec3(0.5)
        w = wp.mat33(0.5 * wa[0] * wa[0], 0.5 * wa[1] * wa[1], 0.5 * wa[2] * wa[2],
                     0.75 - wb[0] * wb[0], 0.75 - wb[1] * wb[1], 0.75 - wb[2] * wb[2],
                     0.5 * wc[0] * wc[0], 0.5 * wc[1] * wc[1], 0.5 * wc[2] * wc[2])
        return base, fx, w

    @wp.kernel
    def ref_zero_grid(grid_m: wp.array3d(dtype=float), grid_v_in: wp.array3d(dtype=wp.vec3),
                      grid_v_out: wp.array3d(dtype=wp.vec3)):
        i, j, k = wp.tid()
        grid_m[i, j, k] = 0.0
        grid_v_in[i, j, k] = wp.vec3(0.0)
        grid_v_out[i, j, k] = wp.vec3(0.0)

    @wp.kernel
    def ref_compute_stress(model: RefModel, F_trial: wp.array(dtype=wp.mat33), F: wp.array(dtype=wp.mat33),
                           mu: wp.array(dtype=float), lam: wp.array(dtype=float),
                           stress: wp.array(dtype=wp.mat33)):
        p = wp.tid()
        Fp = F_trial[p]
        U = wp.mat33()
        sig = wp.vec3()
        V = wp.mat33()
        wp.svd3(Fp, U, sig, V)
        J = sig[0] * sig[1] * sig[2]
        s = wp.mat33(0.0)
        if model.material == 0:
            R = U @ wp.transpose(V)
            P = 2.0 * mu[p] * (Fp - R) + lam[p] * J * (J - 1.0) * wp.transpose(wp.inverse(Fp))
            s = P @ wp.transpose(Fp)
        elif model.material == 1:  # StVK-Hencky branch (not used by the benchmark case)
            eps = wp.vec3(wp.log(sig[0]), wp.log(sig[1]), wp.log(sig[2]))
            tr = eps[0] + eps[1] + eps[2]
            s = U @ wp.diag(2.0 * mu[p] * eps + wp.vec3(lam[p] * tr)) @ wp.transpose(U)
        F[p] = Fp
        stress[p] = s

    @wp.kernel
    def ref_p2g(model: RefModel, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                C: wp.array(dtype=wp.mat33), stress: wp.array(dtype=wp.mat33), vol: wp.array(dtype=float),
                mass: wp.array(dtype=float), grid_m: wp.array3d(dtype=float), grid_v_in: wp.array3d(dtype=wp.vec3)):
        p = wp.tid()
        base, fx, w = ref_stencil(model, x[p])
        stress_term = (-model.dt * vol[p] * 4.0 * model.inv_dx * model.inv_dx) * stress[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * model.dx
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    ix = base[0] + i
                    iy = base[1] + j
                    iz = base[2] + k
                    momentum = weight * mass[p] * (v[p] + C[p] @ dpos) + weight * (stress_term @ dpos)
                    wp.atomic_add(grid_v_in, ix, iy, iz, momentum)
                    wp.atomic_add(grid_m, ix, iy, iz, weight * mass[p])

    @wp.kernel
    def ref_grid_normalise(model: RefModel, grid_m: wp.array3d(dtype=float), grid_v_in: wp.array3d(dtype=wp.vec3),
                           grid_v_out: wp.array3d(dtype=wp.vec3)):
        i, j, k = wp.tid()
        if grid_m[i, j, k] > 1.0e-15:
            grid_v_out[i, j, k] = grid_v_in[i, j, k] / grid_m[i, j, k] + model.dt * model.gravity

    @wp.kernel
    def ref_ground_collider(model: RefModel, grid_v_out: wp.array3d(dtype=wp.vec3)):
        i, j, k = wp.tid()
        z = model.grid_origin[2] + float(k) * model.dx
        if z <= model.ground_z + 0.01 * model.dx:
            vel = grid_v_out[i, j, k]
            if vel[2] < 0.0:
                grid_v_out[i, j, k] = wp.vec3(vel[0], vel[1], 0.0)

    @wp.kernel
    def ref_g2p(model: RefModel, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
                F: wp.array(dtype=wp.mat33), F_trial: wp.array(dtype=wp.mat33), grid_v_out: wp.array3d(dtype=wp.vec3)):
        p = wp.tid()
        base, fx, w = ref_stencil(model, x[p])
        new_v = wp.vec3(0.0)
        new_C = wp.mat33(0.0)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = wp.vec3(float(i), float(j), float(k)) - fx
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    gv = grid_v_out[base[0] + i, base[1] + j, base[2] + k]
                    new_v = new_v + weight * gv
                    new_C = new_C + wp.outer(weight * gv, dpos) * (4.0 * model.inv_dx)
        v[p] = new_v
        C[p] = new_C
        F_trial[p] = (wp.identity(n=3, dtype=float) + model.dt * new_C) @ F[p]
        x[p] = x[p] + model.dt * new_v

    return RefModel, ref_zero_grid, ref_compute_stress, ref_p2g, ref_grid_normalise, ref_ground_collider, ref_g2p


class ReferenceAPIC:
    """The reference solver's state for one particle set (fixed cubic grid of ``n_grid``³ nodes)."""

    def __init__(self, wp, device, points, velocity, dx, dt, gravity, ground_z, margin_cells=8):
        (self.Model, self.k_zero, self.k_stress, self.k_p2g, self.k_norm, self.k_ground,
         self.k_g2p) = _reference_kernels()
        self.wp, self.device = wp, device
        n = len(points)
        lo, hi = points.min(0), points.max(0)
        n_grid = int(math.ceil(float((hi - lo).max()) / dx)) + 2 * margin_cells
        model = self.Model()
        model.material = 0
        model.n_grid = n_grid
        model.dx = dx
        model.inv_dx = 1.0 / dx
        model.dt = dt
        model.gravity = wp.vec3(*gravity)
        model.ground_z = ground_z
        origin = np.floor((lo - margin_cells * dx - np.array([0.0, 0.0, ground_z])) / dx) * dx + [0.0, 0.0, ground_z]
        model.grid_origin = wp.vec3(*origin)
        self.model, self.n_grid = model, n_grid
        mu = E_BENCH / (2 * (1 + NU_BENCH))
        lam = E_BENCH * NU_BENCH / ((1 + NU_BENCH) * (1 - 2 * NU_BENCH))
        vol = (dx / 2) ** 3
        f32 = np.float32
        self.x = wp.array(points.astype(f32), dtype=wp.vec3, device=device)
        self.v = wp.array(velocity.astype(f32), dtype=wp.vec3, device=device)
        self.C = wp.zeros(n, dtype=wp.mat33, device=device)
        eye = np.tile(np.eye(3, dtype=f32), (n, 1, 1))
        self.F = wp.array(eye, dtype=wp.mat33, device=device)
        self.F_trial = wp.array(eye, dtype=wp.mat33, device=device)
        self.stress = wp.zeros(n, dtype=wp.mat33, device=device)
        self.mu = wp.array(np.full(n, mu, f32), device=device)
        self.lam = wp.array(np.full(n, lam, f32), device=device)
        self.vol = wp.array(np.full(n, vol, f32), device=device)
        self.mass = wp.array(np.full(n, vol * RHO_BENCH, f32), device=device)
        shape = (n_grid, n_grid, n_grid)
        self.grid_m = wp.zeros(shape, dtype=float, device=device)
        self.grid_v_in = wp.zeros(shape, dtype=wp.vec3, device=device)
        self.grid_v_out = wp.zeros(shape, dtype=wp.vec3, device=device)
        self.n = n

    def step(self, substeps: int) -> None:
        wp, dev, m = self.wp, self.device, self.model
        shape = (self.n_grid,) * 3
        for _ in range(substeps):
            wp.launch(self.k_zero, dim=shape, inputs=[self.grid_m, self.grid_v_in, self.grid_v_out], device=dev)
            wp.launch(self.k_stress, dim=self.n, inputs=[m, self.F_trial, self.F, self.mu, self.lam, self.stress],
                      device=dev)
            wp.launch(self.k_p2g, dim=self.n, inputs=[m, self.x, self.v, self.C, self.stress, self.vol, self.mass,
                                                      self.grid_m, self.grid_v_in], device=dev)
            wp.launch(self.k_norm, dim=shape, inputs=[m, self.grid_m, self.grid_v_in, self.grid_v_out], device=dev)
            wp.launch(self.k_ground, dim=shape, inputs=[m, self.grid_v_out], device=dev)
            wp.launch(self.k_g2p, dim=self.n, inputs=[m, self.x, self.v, self.C, self.F, self.F_trial,
                                                      self.grid_v_out], device=dev)


# ------------------------------------------------------------------------------------------ the benchmark
def _cube(count: int) -> np.ndarray:
    """A lattice cube of about ``count`` particles in random order (as a Gaussian-splat point cloud comes)."""
    side = max(2, int(round(count ** (1.0 / 3.0))))
    idx = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = (idx + 0.5) * SPACING
    pts[:, 2] += 2 * SPACING  # just above the ground at z = 0
    return pts[np.random.default_rng(0).permutation(len(pts))]


def _label(count: int) -> str:
    """Case label of a requested size: 50000 -> '50k', 1000000 -> '1M'."""
    return f"{count / 1e6:g}M" if count >= 1_000_000 else f"{count / 1e3:g}k" if count >= 1000 else str(count)


def _breakdown(sim) -> dict:
    """Per-kernel time of one profiled run (CUDA events on a GPU; graphs off), in µs per substep, plus the run's
    wall time and what the kernels leave of it (host work, launches, synchronisation)."""
    prof = sim.profile([])
    steps = prof["substeps"]
    kernels = {k: v for k, v in prof.items() if k not in ("wall", "substeps", "particle_substeps")}
    out = {f"{k}_us_per_substep": 1e6 * v / steps for k, v in sorted(kernels.items())}
    out["profiled_run_s"] = prof["wall"]
    out["outside_kernels_s"] = prof["wall"] - sum(kernels.values())
    return out


def run(args) -> list[dict]:
    from ...core.errors import UserError
    from ...solvers import mpm
    from ...solvers.body import Body
    from ...solvers.material_sampling import HomogeneousMaterial
    from ...solvers.scenario import Scenario
    from ...solvers.warp_runtime import device_description, init_warp, resolve_device

    wp = init_warp()
    device = resolve_device(args.device)
    try:
        sizes = [int(float(s)) for s in str(args.sizes).split(",") if s.strip()]
    except ValueError:
        raise UserError(f"--sizes must be comma-separated particle counts, got {args.sizes!r}") from None
    if not sizes or min(sizes) < 8:
        raise UserError("--sizes needs particle counts of at least 8")
    if args.runs < 1:
        raise UserError("--runs must be at least 1")
    variants = [v.strip() for v in str(args.variants).split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise UserError(f"--variants: unknown preset(s) {unknown}; known: {', '.join(VARIANTS)}")
    substeps = args.substeps or (100 if device.startswith("cuda") else 10)
    if substeps < 1:
        raise UserError("--substeps must be at least 1")
    described = device_description(device)
    dx = 2 * SPACING
    c = math.sqrt(E_BENCH * (1 - NU_BENCH) / ((1 + NU_BENCH) * (1 - 2 * NU_BENCH)) / RHO_BENCH)
    dt = 0.3 * dx / (c + DROP_SPEED + 9.81 * 0.01)  # below every CFL bound of the run: both solvers use it
    gravity = (0.0, 0.0, -9.81)
    results = []
    failures = []
    for requested in sizes:
        points = _cube(requested)
        n = len(points)
        body = Body(points=points, point_volume=SPACING ** 3, tracked_points=points[:: max(1, n // 1000)])
        scenario = Scenario(gravity=list(gravity), ground_height=0.0, initial_velocity=[0.0, 0.0, -DROP_SPEED])
        sim = mpm.prepare(body, HomogeneousMaterial(E_BENCH, NU_BENCH, RHO_BENCH, "jelly"), scenario,
                          [0.0, substeps * dt], device=device,
                          settings={"dx": dx, "max_dt": dt, "sort_particles": not args.no_sort})
        shipped = {f: getattr(sim.settings, f) for f in TUNING_FIELDS}
        ref_rate = ref_x = None
        if not args.no_reference:
            velocity = np.tile([0.0, 0.0, -DROP_SPEED], (n, 1))
            ref = ReferenceAPIC(wp, device, points, velocity, dx, dt, gravity, 0.0)
            ref.step(1)  # warm-up (compiles)
            ref_times = []
            for _ in range(args.runs):
                ref = ReferenceAPIC(wp, device, points, velocity, dx, dt, gravity, 0.0)
                ref_times += synchronized_times(lambda: ref.step(substeps), 1, wp, device)
            ref_rate = n * substeps / statistics.median(ref_times)
            ref_x = ref.x.numpy()
            results.append({"case": f"{_label(requested)} particles, jelly, drop, reference APIC", "device": described,
                            "metric": "particle_substeps_per_s", "value": ref_rate, "runs": args.runs,
                            "particles": n, "substeps_per_run": substeps, "median_run_s": statistics.median(ref_times),
                            "grid_dims": [ref.n_grid] * 3})
            print(f"  {n:,} particles: reference {ref_rate:.3g} particle-substeps/s", flush=True)
        first_x = None
        for variant in variants:
            for name, value in {**shipped, **VARIANTS[variant]}.items():
                setattr(sim.settings, name, value)
            try:
                entry = _measure_variant(sim, variant, requested, n, substeps, args, wp, device, described,
                                         ref_rate, ref_x, first_x)
            except Exception as exc:  # report and go on with the other variants (a CUDA fault will stop them too)
                failures.append(f"{_label(requested)} {variant}: {type(exc).__name__}: {exc}")
                print(f"  {n:,} particles, {variant}: FAILED: {failures[-1]}", flush=True)
                continue
            if first_x is None:
                first_x = entry.pop("_x")
            else:
                entry.pop("_x")
            results.append(entry)
            parts = ""
            if "breakdown" in entry:
                parts = "; µs/substep " + ", ".join(f"{k.replace('_us_per_substep', '')} {v:.1f}"
                                                     for k, v in entry["breakdown"].items() if k.endswith("substep"))
            print(f"  {n:,} particles, {variant}: {entry['value']:.3g} particle-substeps/s"
                  + (f" (x{entry['vs']['ratio']:.2f} the reference; positions agree to "
                     f"{entry['max_position_difference_m']:.1e} m)" if "vs" in entry else "") + parts, flush=True)
    if failures:
        print("FAILED variants:\n  " + "\n  ".join(failures), flush=True)
    return results


def _measure_variant(sim, variant, requested, n, substeps, args, wp, device, described, ref_rate, ref_x, first_x):
    """Time one variant (settings already applied): warm-up, ``--runs`` timed runs, the final positions against
    the reference and the first variant, and the per-kernel breakdown."""
    last = {"traj": sim.run([])}  # warm-up (uploads the initial state, captures graphs)
    ours = synchronized_times(lambda: last.update(traj=sim.run([])), args.runs, wp, device)
    ours_rate = n * substeps / statistics.median(ours)
    label = _label(requested) + (", unsorted" if args.no_sort else "")
    entry = {"case": f"{label} particles, jelly, drop" + ("" if variant == "default" else f", {variant}"),
             "device": described, "metric": "particle_substeps_per_s", "value": ours_rate, "runs": args.runs,
             "particles": n, "substeps_per_run": substeps, "median_run_s": statistics.median(ours),
             "grid_dims": last["traj"].meta["grid_dims"],
             "settings": {f: getattr(sim.settings, f) for f in TUNING_FIELDS}}
    # same physics: final particle positions after the same substeps (order: the input points)
    x = sim.run([], particle_states=True).particle_positions[-1]
    entry["_x"] = x
    if first_x is not None:
        entry["max_position_difference_vs_first_variant_m"] = float(np.abs(x - first_x).max())
    if ref_rate is not None:
        entry["vs"] = {"what": "reference PhysGaussian-style APIC kernels, same run", "ratio": ours_rate / ref_rate}
        entry["max_position_difference_m"] = float(np.abs(x - ref_x).max())
    if not args.no_breakdown:
        entry["breakdown"] = _breakdown(sim)
    return entry
