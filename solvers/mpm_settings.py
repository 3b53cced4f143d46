"""The MPM solver's numerical settings (:class:`MPMSettings`) and their defaults (SI units).

Light on purpose (numpy only): the solver registry (:mod:`.registry`), cost estimates and the command line
read them without loading the solver or Warp.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import numpy as np

from ..core.errors import UserError
from .settings import SolverSettings, setting

MATERIAL_SAMPLINGS = ("nearest", "trilinear")
"""How voxel material fields are looked up at the particles (setting ``material_sampling``)."""
DEFORMATION_GRADIENTS = ("affine", "grid")
"""Which velocity gradient updates each particle's deformation gradient (setting ``deformation_gradient``)."""
P2G_SCATTER_MODES = ("atomic", "vector", "warp")
"""How P2G adds to the grid (setting ``p2g_scatter``; kernels in ``mpm_kernels`` / ``mpm_kernels_cuda``)."""

DEFAULT_CELLS_ACROSS = 32
"""Grid cells across a mesh body's largest extent by default."""
DEFAULT_CELLS_ACROSS_THINNEST = 4
"""Grid cells across a mesh body's thinnest parts by default (docs/fidelity.md: a clamped bar four cells thick
sags 1.6–2.0 % more than Euler–Bernoulli at rest and vibrates within 1 % of its frequency)."""
AUTO_MAX_PARTICLES = {"cpu": 200_000, "cuda": 2_000_000}
"""Particle budget of the automatic grid per device kind (settings ``auto_max_particles`` = None)."""


@dataclass
class MPMSettings(SolverSettings):
    """Numerical settings of the MPM solver (SI units).

    dx: grid cell size in metres; ``None`` = for a mesh, the finer of the body's largest extent / ``cells_across``
        and its thinnest parts' thickness (:func:`~.sampling.thinnest_part`) / ``cells_across_thinnest``, the
        latter no finer than ``auto_max_particles`` allow (a warning says so); for a particle set,
        ``particles_per_cell_axis`` × the point spacing.
    cells_across: grid cells across the largest extent of a mesh body (when ``dx`` is None); ``None`` =
        :data:`DEFAULT_CELLS_ACROSS`.
    cells_across_thinnest: grid cells across the thinnest parts of a mesh body (when ``dx`` is None): a slender
        bar, a trunk or a leaf bends as the continuum does only with several cells across it
        (docs/fidelity.md measures how many); 0 = the largest extent alone decides; ``None`` =
        :data:`DEFAULT_CELLS_ACROSS_THINNEST` when ``cells_across`` is not given either (the bake default),
        0 when it is (a caller that asks for N cells across gets N cells across, as the demo and tests do).
    auto_max_particles: the particle budget of the automatic ``dx``; ``None`` = :data:`AUTO_MAX_PARTICLES`
        of the device (a GPU affords ten times a CPU's particles in the same wall time).
    particles_per_cell_axis: mesh filling: particles per cell along each axis (2 → 8 per cell);
        particle volume = cell volume / particles per cell.
    jitter: random offset of the filling lattice, fraction of the particle spacing (0 = regular).
    seed: random seed of the jitter.
    cfl: the time step is at most ``cfl · dx / (c + |v|max + |a| Δt_frame)`` with
        c = sqrt((λ + 2μ)/ρ) the largest elastic (P-)wave speed.
    viscous_cfl: with material damping η the time step is also at most ``viscous_cfl · ρ dx² / η``.
    max_dt: a user cap on the time step in seconds (``None`` = no cap).
    max_substeps_per_frame: a frame needing more substeps than this stops the run as diverged.
    domain_margin_cells: empty cells kept around the material (plus the distance it can travel in
        one frame); the grid follows the material each frame.
    max_grid_nodes: largest grid (nodes per environment) the run may grow to.
    max_particles: refuse bodies that would need more particles than this.
    material_sampling: ``"nearest"`` or ``"trilinear"`` lookup of voxel material fields.
    initial_deformation: optional (3, 3) elastic deformation gradient every particle starts with
        (the body is given in its deformed shape, e.g. a pre-stretched bar); ``None`` = identity.
    sort_particles: reorder particles by grid cell before every chunk of substeps (memory locality;
        on a GPU it also lets a warp's particles share stencils, which the ``"warp"`` scatter exploits).
    deformation_gradient: the velocity gradient that updates each particle's deformation gradient,
        F ← (I + Δt ∇v) F: ``"grid"`` (the default since 2026-11-28) takes the gradient of the grid's interpolated
        velocity at the particle, Σ v_i ∇w_ipᵀ; ``"affine"`` takes APIC's affine matrix C = 4/Δx² Σ w v (x_i − x_p)ᵀ,
        as MLS-MPM does (the momentum transfer keeps C either way).  With ``"affine"`` a bar that swings across
        cells sinks a little every period (0.22 mm a period, 2.4 % of its sag, at the bake default; ``"grid"``
        0.03 mm; docs/fidelity.md, "MPM's creep").  Material damping's strain rate is C's either way.

    GPU tuning (the results do not depend on them beyond float reassociation; ``None``/``"auto"``
    picks the device's default, the CPU's being the plain kernels):

    p2g_scatter: how P2G adds to the grid: ``"atomic"`` (one Warp vec4 atomic = four scalar atomics
        per node), ``"vector"`` (one 16-byte vector reduction per node on sm_90+), ``"warp"``
        (warp-aggregated per stencil, then vector reductions) or ``"auto"`` (``"warp"`` on CUDA,
        ``"atomic"`` on the CPU).
    split_g2p: gather to particles and to tracked points in two kernels (fewer registers for the
        particles); ``None`` = on CUDA only.
    graph_substeps: replay substeps as captured graphs of up to this many substeps (0 = launch each
        kernel from Python); ``None`` = 16 on CUDA, 0 on the CPU.
    block_dim: threads per block of the substep kernels (a multiple of 32, at most 1024).
    sort_interval: also re-sort the particles every this many substeps within a chunk (0 = once per
        chunk).
    rigid_mass_once: scatter the mass of the held particles of rigid classes (``stationary``: they never move,
        carry no stress and send no momentum) to the grid once per grid placement instead of in every substep's
        P2G — the same masses, summed in another order; a clamped pot is over half the demo plant's particles.
    """

    solver_words: ClassVar[str] = "MPM"

    dx: Optional[float] = setting(None, "positive", optional=True)
    cells_across: Optional[int] = setting(None, "count", optional=True)
    cells_across_thinnest: Optional[int] = setting(None, "count0", optional=True)
    auto_max_particles: Optional[int] = setting(None, "count", optional=True)
    particles_per_cell_axis: int = setting(2, "count")
    jitter: float = setting(0.0, "unit")
    seed: int = setting(0, "count0")
    cfl: float = setting(0.4, "positive", maximum=1.0, hint=" (0.3-0.5 is usual)")
    viscous_cfl: float = setting(0.1, "positive")
    max_dt: Optional[float] = setting(None, "positive", optional=True)
    max_substeps_per_frame: int = setting(20000, "count")
    domain_margin_cells: int = setting(4, "count")
    max_grid_nodes: int = setting(1 << 25, "count")
    max_particles: int = setting(20_000_000, "count")
    material_sampling: str = setting("nearest", "choice", choices=MATERIAL_SAMPLINGS)
    initial_deformation: Optional[np.ndarray] = None
    sort_particles: bool = setting(True, "flag")
    deformation_gradient: str = setting("grid", "choice", choices=DEFORMATION_GRADIENTS)
    p2g_scatter: str = setting("auto", "choice", choices=("auto",) + P2G_SCATTER_MODES)
    split_g2p: Optional[bool] = setting(None, "flag", optional=True)
    graph_substeps: Optional[int] = setting(None, "count0", optional=True)
    block_dim: int = setting(256, "count", maximum=1024)
    sort_interval: int = setting(0, "count0")
    rigid_mass_once: bool = setting(True, "flag")

    def check(self):
        if self.cells_across_thinnest is None:
            self.cells_across_thinnest = DEFAULT_CELLS_ACROSS_THINNEST if self.cells_across is None else 0
        if self.cells_across is None:
            self.cells_across = DEFAULT_CELLS_ACROSS
        if not (32 <= self.block_dim and self.block_dim % 32 == 0):
            raise UserError(f"MPM setting 'block_dim' must be a multiple of 32 from 32 to 1024, got {self.block_dim}")
        if self.initial_deformation is not None:
            F = np.asarray(self.initial_deformation, dtype=np.float64)
            if F.shape != (3, 3) or not np.all(np.isfinite(F)) or np.linalg.det(F) <= 0:
                raise UserError("MPM setting 'initial_deformation' must be a finite 3x3 matrix with positive "
                                "determinant")
            self.initial_deformation = F
