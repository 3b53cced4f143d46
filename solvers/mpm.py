"""The Material Point Method solver (MLS-MPM / APIC, quadratic B-splines) in NVIDIA Warp.

Usage::

    from unipixie.solvers import mpm, effects
    sim = mpm.prepare(body, material, scenario, frame_times, device="cpu")   # fill, sample, compile
    base = sim.run([])                                                        # Trajectory
    drag = sim.run([effects.make("linear_drag", c=0.8)], particle_states=True)
    many = sim.run_batch([[], [drag_effect], [wind_effect]])                  # one launch per kernel

Set-up (:func:`prepare`: particle filling, material lookup, grid pitch, kernel compilation) is
done once; every :meth:`MPMSimulation.run` starts from the same initial state, so re-running
with other effect parameters costs only the stepping.  ``run_batch`` simulates its
environments together: the particle sets are stacked, each environment gets its own grid
block, time step and effect parameters, and each kernel is launched once per substep for all
of them (environments that need fewer substeps in a frame skip the extra launches), so a batch
returns the same trajectories as separate runs.

Algorithm, units and limits: ``docs/mpm.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..core.errors import SimulationDiverged, UserError
from ..core.progress import Progress, frame_done
from ..core.types import Trajectory
from . import materials
from .api import Simulation
from .body import Body
from .contact import RIGID_GROUND_STIFFNESS, clamp_to_ground
from .effects import PhysicsTerms
from .material_sampling import MaterialSpec
from .mpm_particles import initial_particles
from .mpm_settings import MPMSettings
from .scenario import Scenario

SOLVER_NAME = "mpm"
ELASTIC_RELEASE_FRACTION = 0.1
"""Speed a particle may gain from released elastic strain within a chunk, as a fraction of the wave speed."""
TRANSFER_SCHEME = "MLS-MPM (APIC affine transfer), quadratic B-splines, explicit symplectic Euler"
CUDA_GRAPH_SUBSTEPS = 16
"""Default of ``graph_substeps`` on CUDA: substeps per captured graph (launch overhead ~1 µs per graph)."""
BUFFER_CACHE_BYTES = 1 << 30
"""Device memory the particle buffers of different batch sizes may keep between runs (a diagnosis alternates
batch sizes; re-allocating them also re-captures every CUDA graph)."""
STATS_ITEMS_PER_LANE = 64
"""Particles each lane of the per-frame reduction (bounds, speeds) visits, at least."""


@dataclass(frozen=True)
class _Tuning:
    """The GPU-tuning settings resolved for a device (see :class:`MPMSettings`)."""

    scatter: str
    split_g2p: bool
    graph_substeps: int
    block_dim: int
    sort_interval: int
    rigid_once: bool


@dataclass
class _Buffers:
    """Device arrays of one batch size (reused between runs)."""

    envs: int
    particles: dict
    spare: dict
    tracked: dict
    sort_keys: object
    sort_values: object
    lanes: int
    stats: dict
    env: dict
    lost: object
    step_base: object  # (1,) int32: substep index a captured graph of substeps starts from
    grid: dict = field(default_factory=dict)
    grid_dims: tuple = (0, 0, 0)  # the grid's nodes per axis (per environment)
    grid_alloc: tuple = (0, 0, 0)  # the arrays' room: grid_dims may be smaller on the CPU (see _ensure_grid)
    initial: Optional[dict] = None  # the initial particle state (base material), uploaded once
    parity: int = 0  # which of the two particle buffers is current (flips with every sort)
    commands: dict = field(default_factory=dict)  # _StepCommands per (parity, kernels, ...); cleared with the grid
    frame_launches: dict = field(default_factory=dict)  # recorded per-frame launches (stats, sort) by their inputs


@dataclass
class _StepCommands:
    """The launches of one substep for one particle buffer and grid, and graphs of several substeps."""

    launches: list  # [(name, warp Launch)] in order; the ``substep`` parameter is set per launch
    graphs: dict = field(default_factory=dict)  # substep count -> captured graph (ending with step_base += count)


_PARTICLE_FIELDS = (("x", "vec3"), ("v", "vec3"), ("C", "mat33"), ("H", "mat33"), ("rot", "quat"), ("plastic", "float"),
                    ("mass", "float"), ("vol", "float"), ("mu", "float"), ("lam", "float"), ("code", "int32"),
                    ("pid", "int32"))
_BYTES_PER_PARTICLE = 3 * 140 + 16
"""Device bytes per particle and environment: the fields above (140 B) in the current, spare and initial
buffers, and the sort's keys and values."""


# ------------------------------------------------------------------------------------------ simulation
class MPMSimulation(Simulation):
    """A prepared MPM simulation (see the module docstring).

    Attributes (besides :class:`~unipixie.solvers.api.Simulation`'s)
    ----------
    settings: :class:`~.mpm_settings.MPMSettings`.
    dx: grid cell size, m.
    particle_volume: (P,) m³ rest volume per particle.
    material: :class:`~.material_sampling.SampledMaterial` of the P simulated particles (background removed).
    held: (P,) bool, particles held at rest (clamp box or a held-fixed class).
    tracked_held: (N,) bool, tracked points held at rest.
    setup_seconds: wall time of :func:`prepare`.
    """

    solver = SOLVER_NAME

    def __init__(self, body: Body, scenario: Scenario, frame_times, device: str, settings: MPMSettings):
        super().__init__(body, scenario, frame_times, device)
        self.settings = settings
        self.warnings: list[str] = list(body.warnings)
        self.thinnest_part: Optional[float] = None  # m, measured when dx is chosen automatically
        self._buffer_sets: dict[int, _Buffers] = {}  # batch size -> device arrays (least recently used first)
        self._kc = None  # mpm_kernels_cuda, imported on first use
        self._profile: Optional[list] = None  # (section, start, end) while profile() runs
        self._run_tuning: Optional[_Tuning] = None  # the tuning of the run in progress

    # ------------------------------------------------------------------ set-up
    def _setup(self, material: MaterialSpec, progress: Optional[Progress]):
        init = initial_particles(self.body, self.scenario, material, self.settings, self.device, self.tracked_rest,
                                 progress)
        self.warnings += init.warnings
        self.thinnest_part = init.thinnest_part
        self.dx = init.dx
        self.contact_radius = init.contact_radius
        self.contact_area = init.contact_area
        self.sample_positions = init.positions
        self.particle_volume = init.volumes
        self.material = sampled = init.material
        self.held = held = init.held
        self.tracked_held = init.tracked_held
        self._initial = init  # the rest state every run starts from

        if progress:
            progress.set_status("MPM: compiling kernels")
        from . import mpm_kernels
        from .constitutive import class_law_table
        from .warp_runtime import init_warp

        wp = init_warp()
        self._wp = wp
        self._k = mpm_kernels
        self._code = (sampled.material + np.where(held, int(mpm_kernels.HELD_FLAG), 0)).astype(np.int32)
        rigid_class = np.array([c.held_fixed for c in materials.MATERIAL_CLASSES])
        self._rigid_particles = int(np.count_nonzero(held & rigid_class[sampled.material]))
        wp.load_module(mpm_kernels, device=self.device)
        tuning = self._tuning()
        if tuning.scatter != "atomic" or tuning.split_g2p:
            self._cuda_kernels()  # compile the GPU-tuned kernels now rather than in the first run
        self._laws = class_law_table(self.device)

    @property
    def particle_count(self) -> int:
        return len(self.sample_positions)

    # ------------------------------------------------------------------ buffers
    def _buffers_for(self, envs: int) -> _Buffers:
        """The device arrays for a batch of ``envs`` environments: reused from an earlier run of that batch size
        (with their grid, launches and captured graphs) while the cached sets stay under
        :data:`BUFFER_CACHE_BYTES`; the least recently used sets are freed first."""
        cached = self._buffer_sets.pop(envs, None)
        if cached is None:
            cached = self._new_buffers(envs)
        self._buffer_sets[envs] = cached  # most recently used last
        budget = BUFFER_CACHE_BYTES
        for size in list(self._buffer_sets)[::-1]:
            budget -= size * self.particle_count * _BYTES_PER_PARTICLE
            if budget < 0 and size != envs:
                del self._buffer_sets[size]
        return cached

    def _new_buffers(self, envs: int) -> _Buffers:
        wp, dev = self._wp, self.device
        n = self.particle_count * envs
        m = max(len(self.tracked_rest), 1) * envs
        types = {"vec3": wp.vec3, "mat33": wp.mat33, "quat": wp.quat, "float": float, "int32": wp.int32}
        particles = {name: wp.zeros(n, dtype=types[t], device=dev) for name, t in _PARTICLE_FIELDS}
        spare = ({name: wp.zeros(n, dtype=types[t], device=dev) for name, t in _PARTICLE_FIELDS}
                 if self.settings.sort_particles else {})
        tracked = {"x": wp.zeros(m, dtype=wp.vec3, device=dev), "v": wp.zeros(m, dtype=wp.vec3, device=dev),
                   "held": wp.zeros(m, dtype=wp.int32, device=dev)}
        # reduction lanes per environment: enough threads to fill a GPU, few enough to read back cheaply (each
        # lane reduces STATS_ITEMS_PER_LANE or more particles; the host finishes over lanes)
        items = max(self.particle_count, len(self.tracked_rest), 1)
        lanes = int(min(16384 if str(dev).startswith("cuda") else 1024, -(-items // STATS_ITEMS_PER_LANE)))
        together = wp.zeros(3 * envs * lanes, dtype=wp.vec3, device=dev)  # read back in one copy per frame
        n_stats = envs * lanes
        stats = {"all": together, "lo": together[:n_stats], "hi": together[n_stats:2 * n_stats],
                 "stats": together[2 * n_stats:]}
        env = {"dt": wp.zeros(envs, dtype=float, device=dev), "steps": wp.zeros(envs, dtype=wp.int32, device=dev),
               "origin": wp.zeros(envs, dtype=wp.vec3, device=dev), "yield": wp.zeros(envs, dtype=float, device=dev),
               "eta": wp.zeros(envs, dtype=float, device=dev), "acc": wp.zeros(envs, dtype=wp.vec3, device=dev),
               "drag": wp.zeros(envs, dtype=wp.vec2, device=dev), "ground": wp.zeros(envs, dtype=wp.vec3, device=dev),
               "kick": wp.zeros(envs, dtype=float, device=dev)}
        sort_keys = wp.zeros(2 * n, dtype=wp.int32, device=dev) if self.settings.sort_particles else None
        sort_values = wp.zeros(2 * n, dtype=wp.int32, device=dev) if self.settings.sort_particles else None
        return _Buffers(envs, particles, spare, tracked, sort_keys, sort_values, lanes, stats, env,
                        wp.zeros(envs, dtype=wp.int32, device=dev), wp.zeros(1, dtype=wp.int32, device=dev))

    def _reset_particles(self, buf: _Buffers, terms_list: list) -> None:
        """Set the particle buffer to the initial state (device-to-device copy of a state uploaded once per batch
        size), with each environment's Young's-modulus scaling (stiffness_region) applied to μ and λ."""
        wp = self._wp
        E, N = buf.envs, self.particle_count
        if buf.initial is None:
            mu, lam = self.material.lame()
            f32 = np.float32
            rest = self._initial
            host = {"x": np.tile(self.sample_positions, (E, 1)).astype(f32),
                    "v": np.tile(rest.velocities, (E, 1)).astype(f32),
                    "C": np.tile(rest.affine_velocity, (E, 1, 1)), "H": np.tile(rest.displacement_gradient, (E, 1, 1)),
                    "rot": np.tile(rest.rotation, (E * N, 1)), "plastic": np.tile(rest.plastic, E).astype(f32),
                    "mass": np.tile(rest.masses, E).astype(f32), "vol": np.tile(self.particle_volume, E).astype(f32),
                    "mu": np.tile(mu, E).astype(f32), "lam": np.tile(lam, E).astype(f32),
                    "code": np.tile(self._code, E), "pid": np.arange(E * N, dtype=np.int32)}
            P = buf.particles
            buf.initial = {name: wp.array(host[name], dtype=P[name].dtype, device=self.device)
                           for name, _ in _PARTICLE_FIELDS}
        P = buf.particles
        for name, _ in _PARTICLE_FIELDS:
            wp.copy(P[name], buf.initial[name])
        for e, terms in enumerate(terms_list):
            if terms.E_scale is not None:
                mu_e, lam_e = self.material.lame(terms.E_multiplier(N))
                P["mu"][e * N:(e + 1) * N].assign(mu_e.astype(np.float32))
                P["lam"][e * N:(e + 1) * N].assign(lam_e.astype(np.float32))

    def _ensure_grid(self, buf: _Buffers, dims: tuple) -> None:
        """A grid of at least ``dims`` nodes.  The arrays grow by a quarter when too small; captured graphs (CUDA) use
        them whole, substeps launched from Python (the CPU) exactly ``dims``, so that no substep visits nodes the
        material cannot reach (a CPU thread per node)."""
        exact = self._run_tuning.graph_substeps == 0
        if not (all(a >= b for a, b in zip(buf.grid_alloc, dims)) and buf.grid):
            wp, dev = self._wp, self.device
            grow = tuple(int(max(a, math.ceil(b * 1.25))) if b > a else int(a) for a, b in zip(buf.grid_alloc, dims))
            nodes = int(np.prod(grow))
            if nodes > self.settings.max_grid_nodes or nodes * buf.envs >= 2 ** 31:
                raise UserError(f"the grid would need {nodes:,} nodes per environment ({grow[0]}x{grow[1]}x{grow[2]}), "
                                f"more than settings max_grid_nodes = {self.settings.max_grid_nodes:,}")
            total = nodes * buf.envs
            buf.grid = {"mv": wp.zeros(total, dtype=wp.vec4, device=dev), "held": wp.zeros(total, dtype=float, device=dev),
                        "contact": wp.zeros(total, dtype=float, device=dev), "v": wp.zeros(total, dtype=wp.vec4, device=dev),
                        "rigid": wp.zeros(total, dtype=float, device=dev)}
            buf.grid_alloc = buf.grid_dims = grow
            buf.commands.clear()  # launches and graphs hold the old grid
            buf.frame_launches.clear()  # so may recorded per-frame launches (rigid_mass) of the same dims
        if exact and buf.grid_dims != tuple(dims):
            buf.grid_dims = tuple(int(d) for d in dims)  # the accumulators are all zero between substeps
            buf.commands.clear()

    # ------------------------------------------------------------------ running
    def _run_terms(self, terms_list: list[PhysicsTerms], *, progress: Optional[Progress],
                   particle_states: bool) -> list[Trajectory]:
        if not terms_list:
            return []
        wp, k, dev, s = self._wp, self._k, self.device, self.settings
        t_start = time.perf_counter()
        E = len(terms_list)
        N = self.particle_count
        M = len(self.tracked_rest)
        M_alloc = max(M, 1)
        buf = self._buffers_for(E)
        dx = self.dx
        inv_dx = 1.0 / dx
        sc = self.scenario
        has_ground = int(sc.ground_height is not None)
        ground_z = float(sc.ground_height) if has_ground else 0.0

        # ---- per-environment parameters
        acc = np.zeros((E, 3))
        drag = np.zeros((E, 2))
        ground_law = np.zeros((E, 3))  # (k_g Pa/m, c_g Pa·s/m, μ) of the contact law (solvers/contact.py)
        yield_stress = np.full(E, np.inf)
        eta = np.zeros(E)
        for e, terms in enumerate(terms_list):
            acc[e] = sc.gravity + np.asarray(terms.extra_acceleration, dtype=np.float64)
            drag[e] = (terms.linear_drag, terms.quadratic_drag)
            ground_law[e] = (min(terms.ground_stiffness, RIGID_GROUND_STIFFNESS), terms.ground_damping, terms.friction_mu)
            yield_stress[e] = terms.yield_stress
            eta[e] = terms.damping_eta
        acc_norm = np.linalg.norm(acc, axis=1)
        rho_min = self._initial.min_density

        # ---- initial state
        tuning = self._tuning()
        self._reset_particles(buf, terms_list)
        T = buf.tracked
        tracked0 = np.zeros((E * M_alloc, 3), np.float32)
        tracked_v0 = np.zeros((E * M_alloc, 3), np.float32)
        tracked_h = np.ones(E * M_alloc, np.int32)
        if M:
            tracked0[:] = np.tile(self.tracked_rest, (E, 1))
            tracked_v0[:] = np.tile(self._initial.tracked_velocities, (E, 1))
            tracked_h[:] = np.tile(self.tracked_held.astype(np.int32), E)
        T["x"].assign(tracked0)
        T["v"].assign(tracked_v0)
        T["held"].assign(tracked_h)
        Env = buf.env
        Env["yield"].assign(yield_stress.astype(np.float32))
        Env["eta"].assign(eta.astype(np.float32))
        Env["acc"].assign(acc.astype(np.float32))
        Env["drag"].assign(drag.astype(np.float32))
        Env["ground"].assign(ground_law.astype(np.float32))
        buf.lost.zero_()
        self._p2g_kernel = self._choose_p2g(yield_stress)
        self._run_tuning = tuning

        times = self.frame_times
        F_count = len(times)
        out_positions = np.zeros((E, F_count, M, 3), np.float32)
        out_positions[:, 0] = self.tracked_rest[None]
        states = None
        if particle_states:
            states = {"x": np.zeros((F_count, N, 3), np.float32), "v": np.zeros((F_count, N, 3), np.float32),
                      "J": np.zeros((F_count, N), np.float32), "plastic": np.zeros((F_count, N), np.float32)}
            scratch = {"x": wp.zeros(N, dtype=wp.vec3, device=dev), "v": wp.zeros(N, dtype=wp.vec3, device=dev),
                       "J": wp.zeros(N, dtype=float, device=dev), "plastic": wp.zeros(N, dtype=float, device=dev)}
            self._record_state(buf, scratch, states, 0)
        dt_log = np.zeros((E, F_count - 1))
        steps_log = np.zeros((E, F_count - 1), np.int64)
        # tracked positions of every frame gather on the device (one read-back at the end, so the host can queue
        # the next frame while the GPU still steps this one)
        history = wp.empty(F_count * E * M_alloc, dtype=wp.vec3, device=dev) if M else None
        dt_staggered = np.zeros(E)  # (E,) the substep the stored velocities lag half of (leapfrog, see _kick)

        for f in range(1, F_count):
            frame_dt = float(times[f] - times[f - 1])
            lo, hi, vmax, cmax = self._frame_stats(buf, E, N, M, f - 1)
            if f > 1:
                self._check_lost(buf, N, f - 1, dt)
            # time step per environment
            dt = s.cfl * dx / (cmax + vmax + acc_norm * frame_dt + 1e-12)
            visc = eta > 0
            dt[visc] = np.minimum(dt[visc], s.viscous_cfl * rho_min * dx * dx / eta[visc])
            if s.max_dt is not None:
                dt = np.minimum(dt, s.max_dt)
            steps = np.maximum(1, np.ceil(frame_dt / dt - 1e-9)).astype(np.int64)
            if steps.max() > s.max_substeps_per_frame:
                e = int(np.argmax(steps))
                raise SimulationDiverged(
                    f"MPM: frame {f} (t = {times[f]:.4g} s) would need {int(steps[e])} substeps "
                    f"(settings max_substeps_per_frame = {s.max_substeps_per_frame}): particles move at up to "
                    f"{vmax[e]:.3g} m/s with wave speed {cmax[e]:.3g} m/s on a {dx:.3g} m grid. The simulation is "
                    "blowing up or the material is very stiff; lower E, raise max_substeps_per_frame, or use a "
                    "coarser grid (larger dx)")
            dt = frame_dt / steps
            self._kick(buf, E, N, M_alloc, 0.5 * (dt_staggered - dt))
            dt_staggered = dt
            dt_log[:, f - 1] = dt
            steps_log[:, f - 1] = steps
            Env["dt"].assign(dt.astype(np.float32))
            Env["steps"].assign(steps.astype(np.int32))
            # Substeps run in chunks; before each the grid is placed around the material with a margin of
            # domain_margin_cells + 2 cells, and a chunk is short enough that nothing travels further at the
            # current top speed plus what body forces and a release of elastic strain (10 % of the wave speed)
            # can add.  Particles that still leave the grid stop the run (SimulationDiverged).
            travel_budget = s.domain_margin_cells * dx
            speed_bound = vmax + acc_norm * frame_dt + ELASTIC_RELEASE_FRACTION * cmax
            done = 0
            while done < steps.max():
                if done > 0:
                    lo, hi, vmax, cmax = self._frame_stats(buf, E, N, M, f - 1)
                    speed_bound = vmax + acc_norm * frame_dt + ELASTIC_RELEASE_FRACTION * cmax
                active = steps > done
                per_step = speed_bound[active] * dt[active]
                chunk = int(np.min(np.floor(travel_budget / np.maximum(per_step, 1e-30))))
                chunk = max(1, min(chunk, int(steps.max()) - done))
                self._place_grid(buf, lo, hi, f)
                if s.sort_particles:
                    self._sort(buf, E, N)
                self._rigid_mass(buf, E, N, tuning)
                self._step_frame(buf, E, N, M_alloc, done, done + chunk, has_ground, ground_z, progress)
                done += chunk
            if M:
                wp.copy(history, T["x"], dest_offset=f * E * M_alloc, count=E * M_alloc)
            if states is not None:
                self._record_state(buf, scratch, states, f)
            frame_done(progress or None, 1.0, f"MPM frame {f}/{F_count - 1}")
        # last checks: NaN in the final state, particles lost in the last frame
        self._frame_stats(buf, E, N, M, F_count - 1)
        if F_count > 1:
            self._check_lost(buf, N, F_count - 1, dt)
        if M:
            out_positions[:, 1:] = history.numpy().reshape(F_count, E, M_alloc, 3)[1:, :, :M].transpose(1, 0, 2, 3)
            if has_ground:  # the solid sinks a little into any floor (its spring); what is recorded stays on the plane
                out_positions[...] = clamp_to_ground(out_positions, ground_z)
        if not np.all(np.isfinite(out_positions)):
            raise SimulationDiverged("MPM diverged: tracked points have NaN/inf positions; use a smaller time step "
                                     "(settings max_dt or cfl) or a lower E")
        wall = time.perf_counter() - t_start
        out = []
        for e in range(E):
            meta = {"dx": self.dx, "particles": N, "particles_per_cell": self.settings.particles_per_cell_axis ** 3,
                    "transfer": TRANSFER_SCHEME, "device": str(self.device), "environments": E,
                    "batched": E > 1, "grid_dims": list(buf.grid_dims),
                    "dt": dt_log[e].tolist(), "substeps": steps_log[e].tolist(),
                    "dt_min": float(dt_log[e].min()) if F_count > 1 else None,
                    "dt_max": float(dt_log[e].max()) if F_count > 1 else None,
                    "substeps_total": int(steps_log[e].sum()), "wall_time_s": wall, "warnings": list(self.warnings),
                    "particle_substeps": int(steps_log[e].sum()) * N}
            traj = Trajectory(times=times, positions=out_positions[e], solver=self.solver, meta=meta)
            if states is not None and e == 0:
                mu, lam = self.material.lame(terms_list[0].E_multiplier(N))
                traj.particle_positions = states["x"]
                traj.particle_attributes = {
                    "velocity": states["v"], "volume_ratio": states["J"], "plastic_state": states["plastic"],
                    "E": (mu * (3 * lam + 2 * mu) / (lam + mu)).astype(np.float32),
                    "nu": self.material.nu.astype(np.float32), "density": self.material.density.astype(np.float32),
                    "material": self.material.material.astype(np.int32), "held": self.held.astype(np.int8)}
            out.append(traj)
        return out

    # ------------------------------------------------------------------ pieces of a run
    def _kick(self, buf: _Buffers, E: int, N: int, M_alloc: int, tau: np.ndarray) -> None:
        """v += τ_e (gravity + extra acceleration) for the free particles and tracked points of each environment
        ((E,) τ in s; nothing when all are 0): keeps the velocities half a substep behind the positions for the
        body forces (``mpm_kernels.velocity_kick``)."""
        if not np.any(tau):
            return
        buf.env["kick"].assign(tau.astype(np.float32))
        P, T = buf.particles, buf.tracked
        self._wp.launch(self._k.velocity_kick, dim=E * N + E * M_alloc, device=self.device,
                        inputs=[P["v"], P["code"], T["v"], T["held"], buf.env["acc"], buf.env["kick"], N, M_alloc,
                                E * N])

    def _check_lost(self, buf: _Buffers, N: int, frame: int, dt: np.ndarray) -> None:
        """Raise SimulationDiverged if particles were lost (NaN/inf or off the grid) while stepping to ``frame``
        with the (E,) substeps ``dt`` (read after the next frame's statistics: no extra wait for the GPU)."""
        lost = buf.lost.numpy()
        if lost.any():
            e = int(np.argmax(lost))
            raise SimulationDiverged(
                f"MPM diverged at frame {frame} (t = {self.frame_times[frame]:.4g} s): {int(lost[e])} of {N} particles "
                f"have NaN/inf positions or left the grid (it follows the material with a margin of "
                f"{self.settings.domain_margin_cells} cells plus one frame of travel). Remedy: a smaller time step "
                f"(settings max_dt or cfl; the step was {dt[e]:.3g} s), a lower E, or a finer grid")

    def _choose_p2g(self, yield_stress: np.ndarray):
        """The elastic-only P2G when every deforming particle is purely elastic fixed-corotated and no
        environment has the plasticity effect, else the general one (same results for such runs); with the
        scatter of the ``p2g_scatter`` setting."""
        general = not (self._initial.elastic_only and np.all(np.isinf(yield_stress)))
        scatter = self._tuning().scatter
        if scatter == "atomic":
            return self._k.p2g_general if general else self._k.p2g_elastic
        return self._cuda_kernels().P2G_KERNELS[(scatter, general)]

    def _tuning(self) -> _Tuning:
        """The GPU-tuning settings resolved for this device (read at every run: they may be changed between runs)."""
        s = self.settings
        cuda = str(self.device).startswith("cuda")
        scatter = s.p2g_scatter if s.p2g_scatter != "auto" else ("warp" if cuda else "atomic")
        split = s.split_g2p if s.split_g2p is not None else cuda
        graphs = s.graph_substeps if s.graph_substeps is not None else (CUDA_GRAPH_SUBSTEPS if cuda else 0)
        return _Tuning(scatter, bool(split), int(graphs), int(s.block_dim), int(s.sort_interval), bool(s.rigid_mass_once))

    def _cuda_kernels(self):
        """The GPU-tuned kernel module (``mpm_kernels_cuda``), loaded for this device on first use."""
        if self._kc is None:
            from . import mpm_kernels_cuda

            self._wp.load_module(mpm_kernels_cuda, device=self.device)
            self._kc = mpm_kernels_cuda
        return self._kc

    def _frame_stats(self, buf: _Buffers, E: int, N: int, M: int, frame: int):
        """Per environment: (E, 3) lower and upper bounds, (E,) max speed and max wave speed; raises on NaN."""
        wp, k = self._wp, self._k
        P, st = buf.particles, buf.stats
        start = self._mark()
        self._frame_launch(buf, ("frame_stats", buf.parity), lambda: wp.launch(
            k.frame_stats, dim=E * buf.lanes, device=self.device, record_cmd=True,
            inputs=[P["x"], P["v"], P["mass"], P["vol"], P["mu"], P["lam"], P["plastic"], P["code"], self._laws,
                    buf.tracked["x"], N, M, buf.lanes],
            outputs=[st["lo"], st["hi"], st["stats"]]))
        self._record("frame_stats", start)
        together = st["all"].numpy().reshape(3, E, buf.lanes, 3)
        lo = together[0].min(1).astype(np.float64)
        hi = together[1].max(1).astype(np.float64)
        stats = together[2]
        bad = stats[:, :, 2].sum(1)
        if bad.any():
            e = int(np.argmax(bad))
            t = self.frame_times[frame]
            raise SimulationDiverged(
                f"MPM diverged at frame {frame} (t = {t:.4g} s): {int(bad[e])} of {N} particles/tracked points have "
                f"NaN/inf positions or velocities. Remedy: a smaller time step (settings max_dt or cfl), a lower E, "
                "or a finer grid")
        vmax = np.sqrt(stats[:, :, 0].max(1)).astype(np.float64)
        cmax = np.sqrt(stats[:, :, 1].max(1)).astype(np.float64)
        return lo, hi, vmax, cmax

    def _rigid_mass(self, buf: _Buffers, E: int, N: int, tuning: _Tuning) -> None:
        """The held rigid particles' grid mass at this grid placement (``mpm_kernels.rigid_mass``), else zeros."""
        G, P, wp = buf.grid, buf.particles, self._wp
        G["rigid"].zero_()
        if tuning.rigid_once and self._rigid_particles:
            start = self._mark()
            self._frame_launch(buf, ("rigid_mass", buf.parity, buf.grid_dims), lambda: wp.launch(
                self._k.rigid_mass, dim=E * N, device=self.device, record_cmd=True, outputs=[G["rigid"]],
                inputs=[P["x"], P["mass"], P["code"], self._laws, buf.env["origin"], N, int(np.prod(buf.grid_dims)),
                        wp.vec3i(*buf.grid_dims), 1.0 / self.dx]))
            self._record("rigid_mass", start)

    def _moving_count(self, E: int, N: int, tuning: _Tuning) -> int:
        """Particles per environment that P2G and G2P visit: ``N``, or with one environment, ``rigid_mass_once``, cell
        sorting and the plain kernels, those before the held rigid ones, which the sort puts last (``cell_keys``)."""
        plain = tuning.scatter == "atomic" and not tuning.split_g2p and self.settings.sort_particles
        return N - self._rigid_particles if E == 1 and tuning.rigid_once and plain else N

    def _sort(self, buf: _Buffers, E: int, N: int) -> None:
        """Reorder every particle field by grid cell (stable radix sort) into the spare buffer and swap buffers."""
        wp, k = self._wp, self._k
        P, S = buf.particles, buf.spare
        n = E * N
        dims, nodes = wp.vec3i(*buf.grid_dims), int(np.prod(buf.grid_dims))
        rigid_last = self._moving_count(E, N, self._run_tuning) < N
        start = self._mark()
        self._frame_launch(buf, ("cell_keys", buf.parity, buf.grid_dims, rigid_last), lambda: wp.launch(
            k.cell_keys, dim=n, device=self.device, record_cmd=True,
            inputs=[P["x"], P["code"], self._laws, buf.env["origin"], N, nodes, dims, 1.0 / self.dx, int(rigid_last)],
            outputs=[buf.sort_keys, buf.sort_values]))
        wp.utils.radix_sort_pairs(buf.sort_keys, buf.sort_values, n)
        names = [name for name, _ in _PARTICLE_FIELDS]
        self._frame_launch(buf, ("gather_particles", buf.parity), lambda: wp.launch(
            k.gather_particles, dim=n, device=self.device, record_cmd=True,
            inputs=[buf.sort_values] + [P[a] for a in names] + [S[a] for a in names]))
        self._record("sort", start)
        buf.particles, buf.spare = S, P
        buf.parity ^= 1

    @staticmethod
    def _frame_launch(buf: _Buffers, key: tuple, record) -> None:
        """Launch a per-frame kernel from its recorded command (``record()`` makes it once per ``key``: the
        arrays and sizes it is bound to); a recorded launch skips the argument packing of ``wp.launch``."""
        cmd = buf.frame_launches.get(key)
        if cmd is None:
            cmd = buf.frame_launches[key] = record()
        cmd.launch()

    def _place_grid(self, buf: _Buffers, lo: np.ndarray, hi: np.ndarray, frame: int) -> None:
        """Size the grid and set each environment's origin around its material's (E, 3) bounds."""
        s, dx = self.settings, self.dx
        margin = (s.domain_margin_cells + 2) * dx
        cell_lo = np.floor((lo - margin - self._initial.grid_anchor) / dx).astype(np.int64)
        cell_hi = np.ceil((hi + margin - self._initial.grid_anchor) / dx).astype(np.int64)
        need = cell_hi - cell_lo + 1
        try:
            self._ensure_grid(buf, tuple(int(a) for a in need.max(0)))
        except UserError as exc:
            t = self.frame_times[frame]
            raise SimulationDiverged(
                f"MPM: at frame {frame} (t = {t:.4g} s) the material spread too far: {exc}. The simulation is "
                "blowing up or the material (fluid, sand) spreads widely; lower the time step (settings max_dt / "
                "cfl), lower E, or raise max_grid_nodes / use a larger dx") from None
        dims = np.array(buf.grid_dims, np.int64)
        origin_cell = cell_lo - (dims[None] - need) // 2
        buf.env["origin"].assign((self._initial.grid_anchor[None] + origin_cell * dx).astype(np.float32))

    def _step_frame(self, buf: _Buffers, E: int, N: int, M_alloc: int, first: int, stop: int, has_ground: int,
                    ground_z: float, progress: Optional[Progress]) -> None:
        """Substeps ``first .. stop - 1`` of the current frame (one chunk), re-sorting every ``sort_interval``."""
        tuning = self._run_tuning
        segment = tuning.sort_interval if tuning.sort_interval > 0 and self.settings.sort_particles else stop - first
        step = first
        while step < stop:
            if step > first:
                self._sort(buf, E, N)
            end = min(stop, step + segment)
            self._step_range(buf, E, N, M_alloc, step, end, has_ground, ground_z, progress, tuning)
            step = end

    def _step_range(self, buf: _Buffers, E: int, N: int, M_alloc: int, first: int, stop: int, has_ground: int,
                    ground_z: float, progress: Optional[Progress], tuning: _Tuning) -> None:
        wp, k, dev = self._wp, self._k, self.device
        cmds = self._commands(buf, E, N, M_alloc, has_ground, ground_z, tuning)
        if tuning.graph_substeps > 0 and self._profile is None:
            # graphs of `size` substeps read their first substep index from step_base and advance it
            wp.launch(k.set_step, dim=1, inputs=[buf.step_base, first], device=dev)
            sizes = [tuning.graph_substeps] + [1 << i for i in reversed(range(tuning.graph_substeps.bit_length()))
                                                if (1 << i) < tuning.graph_substeps]
            step = first
            checked = first
            while step < stop:
                size = next(z for z in sizes if z <= stop - step)
                wp.capture_launch(self._graph(cmds, size, buf))
                step += size
                if progress is not None and step - checked >= 256:
                    progress.check()
                    checked = step
            return
        wp.launch(k.set_step, dim=1, inputs=[buf.step_base, 0], device=dev)
        slots = [(name, cmd, [a.label for a in cmd.kernel.adj.args].index("substep")) for name, cmd in cmds.launches]
        for step in range(first, stop):
            for name, cmd, slot in slots:
                cmd.set_param_at_index_from_ctype(slot, step)  # the int32 in place (by name: ~12 µs a call)
                self._launch(name, cmd)
            if progress is not None and step % 256 == 255:
                progress.check()

    def _commands(self, buf: _Buffers, E: int, N: int, M_alloc: int, has_ground: int, ground_z: float,
                  tuning: _Tuning) -> _StepCommands:
        """The substep launches for the current particle buffer, grid and kernels (built once, then reused)."""
        moving = self._moving_count(E, N, tuning)
        key = (buf.parity, self._p2g_kernel, tuning.split_g2p, tuning.block_dim, tuning.rigid_once, moving,
               self.settings.deformation_gradient)
        cmds = buf.commands.get(key)
        if cmds is not None:
            return cmds
        wp, k, dev = self._wp, self._k, self.device
        P, T, G, Env = buf.particles, buf.tracked, buf.grid, buf.env
        dims = wp.vec3i(*buf.grid_dims)
        nodes = int(np.prod(buf.grid_dims))
        dx, inv_dx = self.dx, 1.0 / self.dx
        grid_gradient = self.settings.deformation_gradient == "grid"
        g2p = k.g2p_grid if grid_gradient else k.g2p
        n = E * moving  # P2G/G2P threads (held rigid ones sorted last, left out); P2G >= 1 (0 records no command)
        bd = tuning.block_dim if str(dev).startswith("cuda") else None  # CPU kernels run thread by thread
        row = 1 if bd else buf.grid_dims[2]  # grid nodes per thread of grid_update: a row of nodes on the CPU
        p2g_dim = self._cuda_kernels().padded_launch_dim(n) if tuning.scatter == "warp" else max(n, 1)
        launches = [("p2g", wp.launch(self._p2g_kernel, dim=p2g_dim, device=dev, record_cmd=True, block_dim=bd,
                                      inputs=[P["x"], P["v"], P["C"], P["H"], P["rot"], P["plastic"], P["mass"],
                                              P["vol"], P["mu"], P["lam"], P["code"], self._laws, Env["dt"],
                                              Env["steps"], Env["yield"], Env["eta"], Env["origin"], buf.step_base,
                                              Env["ground"], has_ground, ground_z, self.contact_radius,
                                              self.contact_area, n, N, nodes, dims, dx, inv_dx,
                                              int(tuning.rigid_once), int(not grid_gradient), 0],
                                      outputs=[G["mv"], G["held"], G["contact"], buf.lost])),
                    ("grid_update", wp.launch(k.grid_update, dim=E * nodes // row, device=dev, block_dim=bd,
                                              record_cmd=True,
                                              inputs=[G["mv"], G["held"], Env["dt"], Env["steps"], Env["acc"],
                                                      Env["drag"], buf.step_base, nodes, row, 0, Env["ground"],
                                                      G["contact"], G["rigid"]],
                                              outputs=[G["v"]]))]
        if tuning.split_g2p:
            kc = self._cuda_kernels()
            g2p_particles = kc.g2p_particles_grid if grid_gradient else kc.g2p_particles
            launches.append(("g2p", wp.launch(g2p_particles, dim=n, device=dev, record_cmd=True, block_dim=bd,
                                              inputs=[P["x"], P["v"], P["C"], P["H"], P["code"], self._laws, G["v"],
                                                      Env["dt"], Env["steps"], Env["origin"], buf.step_base, N, nodes,
                                                      dims, dx, inv_dx, has_ground, ground_z, Env["ground"],
                                                      0])))
            if len(self.tracked_rest):  # the combined kernel over the tracked points alone (n_particles = 0)
                launches.append(("g2p_tracked", wp.launch(
                    g2p, dim=E * M_alloc, device=dev, record_cmd=True, block_dim=bd,
                    inputs=[P["x"], P["v"], P["C"], P["H"], P["code"], self._laws, T["x"], T["v"], T["held"], G["v"],
                            Env["dt"], Env["steps"], Env["origin"], buf.step_base, N, 0, M_alloc, nodes, dims, dx,
                            inv_dx, has_ground, ground_z, Env["ground"], 0])))
        else:
            launches.append(("g2p", wp.launch(g2p, dim=n + E * M_alloc, device=dev, record_cmd=True, block_dim=bd,
                                              inputs=[P["x"], P["v"], P["C"], P["H"], P["code"], self._laws, T["x"],
                                                      T["v"], T["held"], G["v"], Env["dt"], Env["steps"], Env["origin"],
                                                      buf.step_base, N, n, M_alloc, nodes, dims, dx, inv_dx,
                                                      has_ground, ground_z, Env["ground"], 0])))
        cmds = buf.commands[key] = _StepCommands(launches)
        return cmds

    def _graph(self, cmds: _StepCommands, size: int, buf: _Buffers):
        """The captured graph of ``size`` substeps starting at ``step_base`` (which it advances by ``size``)."""
        graph = cmds.graphs.get(size)
        if graph is None:
            wp = self._wp
            for module in (self._k,) + ((self._kc,) if self._kc is not None else ()):
                wp.load_module(module, device=self.device)
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                for offset in range(size):
                    for _, cmd in cmds.launches:
                        cmd.set_param_by_name("substep", offset)
                        cmd.launch()
                wp.launch(self._k.advance_step, dim=1, inputs=[buf.step_base, size], device=self.device)
            graph = cmds.graphs[size] = capture.graph
        return graph

    # ------------------------------------------------------------------ kernel timing (profile)
    def _mark(self):
        """Start of a timed section when profiling (an event on CUDA, a clock reading on the CPU), else None."""
        if self._profile is None:
            return None
        if str(self.device).startswith("cuda"):
            event = self._wp.Event(self.device, enable_timing=True)
            self._wp.get_stream(self.device).record_event(event)
            return event
        return time.perf_counter()

    def _record(self, name: str, start) -> None:
        if self._profile is None:
            return
        if str(self.device).startswith("cuda"):
            end = self._wp.Event(self.device, enable_timing=True)
            self._wp.get_stream(self.device).record_event(end)
            self._profile.append((name, start, end))
        else:
            self._profile.append((name, start, time.perf_counter()))

    def _launch(self, name: str, cmd) -> None:
        if self._profile is None:
            cmd.launch()
            return
        start = self._mark()
        cmd.launch()
        self._record(name, start)

    def profile(self, effects=(), progress: Optional[Progress] = None) -> dict:
        """One run with every kernel timed (CUDA events on a GPU, clock readings on the CPU; graphs are off).

        Returns seconds per section summed over the run — ``p2g``, ``grid_update``, ``g2p``, ``g2p_tracked``
        (when split), ``sort``, ``rigid_mass``, ``frame_stats`` — plus ``wall`` (the whole run), ``substeps`` and
        ``particle_substeps`` (of environment 0).
        """
        terms = self.terms_for(effects)
        self._profile = []
        try:
            t0 = time.perf_counter()
            traj = self._run_terms([terms], progress=progress, particle_states=False)[0]
            self._wp.synchronize_device(self.device)
            wall = time.perf_counter() - t0
            sections: dict = {}
            cuda = str(self.device).startswith("cuda")
            for name, start, end in self._profile:
                seconds = self._wp.get_event_elapsed_time(start, end) / 1e3 if cuda else end - start
                sections[name] = sections.get(name, 0.0) + seconds
        finally:
            self._profile = None
        sections.update(wall=wall, substeps=traj.meta["substeps_total"], particle_substeps=traj.meta["particle_substeps"])
        return sections

    def _record_state(self, buf: _Buffers, scratch: dict, states: dict, frame: int) -> None:
        wp, k = self._wp, self._k
        P = buf.particles
        N = self.particle_count
        wp.launch(k.scatter_state, dim=buf.envs * N, device=self.device,
                  inputs=[P["pid"], P["x"], P["v"], P["H"], P["plastic"], N],
                  outputs=[scratch["x"], scratch["v"], scratch["J"], scratch["plastic"]])
        for key in states:
            states[key][frame] = scratch[key].numpy()


# ------------------------------------------------------------------------------------------ ahead of time
def compile_cuda_kernels(arch: int = 90, module_dir=None) -> list:
    """Compile all MPM kernels (``mpm_kernels`` and the GPU-tuned ``mpm_kernels_cuda``) for a CUDA architecture
    ahead of time, with Warp's NVRTC; no GPU is needed.

    arch: compute capability as an integer (90 = H100/H200, sm_90).
    module_dir: where to write the sources and binaries; ``None`` = Warp's kernel cache, so that a later run on
        such a GPU (with the same kernel cache) loads them instead of compiling.
    Returns the paths of the compiled modules.  Raises :class:`UserError` when this Warp cannot compile for
    ``arch`` (no NVRTC), and Warp's error (naming file and line) when a kernel does not compile.
    """
    from . import mpm_kernels, mpm_kernels_cuda
    from .warp_runtime import init_warp

    wp = init_warp()
    supported = wp.get_cuda_supported_archs()
    if int(arch) not in supported:
        raise UserError(f"Warp cannot compile CUDA code for sm_{arch} here (NVRTC targets: {supported or 'none'})")
    paths = []
    for module in (mpm_kernels, mpm_kernels_cuda):
        paths += wp.compile_aot_module(module, arch=int(arch), module_dir=module_dir)
    return paths


# ------------------------------------------------------------------------------------------ entry point
def prepare(body: Body, material: MaterialSpec, scenario: Scenario, frame_times, device: str = "cpu",
            settings=None, progress: Optional[Progress] = None) -> MPMSimulation:
    """Prepare an MPM simulation: particles, material per particle, grid pitch, compiled kernels.

    body: :class:`~unipixie.solvers.body.Body` (closed mesh, filled with particles, or a particle set).
    material: homogeneous, per-point or voxel-field material (:mod:`~unipixie.solvers.material_sampling`).
    scenario: gravity, ground, clamp box, initial velocities.
    frame_times: (T,) seconds; the trajectory is reported at these instants (``frame_times[0]`` = rest).
    device: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``.
    settings: :class:`MPMSettings`, a dict of its fields, or ``None``.
    progress: receives status text during set-up; ``run`` advances it one step per frame.
    """
    from .warp_runtime import resolve_device

    if not isinstance(body, Body):
        raise UserError(f"prepare() needs a Body, got {type(body).__name__}")
    if not isinstance(scenario, Scenario):
        raise UserError(f"prepare() needs a Scenario, got {type(scenario).__name__}")
    t0 = time.perf_counter()
    s = MPMSettings.from_any(settings)
    sim = MPMSimulation(body, scenario, frame_times, resolve_device(device), s)
    sim._setup(material, progress)
    sim.setup_seconds = time.perf_counter() - t0
    return sim
