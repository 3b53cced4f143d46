"""The spring-mass solver's set-up settings (:class:`SpringMassSettings`) and their defaults (SI units).

Light on purpose (numpy only): the solver registry (:mod:`.registry`), cost estimates, the model's
configuration and the command line read them without loading the solver or Warp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import numpy as np

from ..core.errors import UserError
from .settings import SolverSettings, as_number, setting

DEFAULT_ANCHORS = 2048
"""N_a: anchors of the network (the paper's spring head predicts N_a stiffnesses + 1 softness)."""
DEFAULT_NEIGHBOURS = 32
"""Springs from every anchor to its 32 nearest anchors (merged into undirected springs)."""
DEFAULT_FIXED_SPRINGS = 16
"""Springs of rank < 16 are never weakened by the softness."""
DEFAULT_SOFTNESS = 0.0
"""η used when the stiffness comes from a material field (Spring-Gaus's initial value)."""
DEFAULT_BINDING = 6
"""Anchors each tracked point / vertex is bound to."""
STIFFNESS_CALIBRATION = 0.94
"""c_E: measured correction of the affine estimate (docs/spring_mass.md, tests/test_spring_mass.py)."""


MIXING_RULES = ("arithmetic", "series", "harmonic")
"""How the network averages the moduli where materials mix (:attr:`SpringMassSettings.mixing`): ``arithmetic``, a
cell's E the volume-weighted mean of its fill points' and a spring the mean of its two ends (the stiff, Voigt,
bound); ``series``, the cells so, but a spring joining two moduli its two halves in series; ``harmonic``, the
springs so and a cell's E the volume-weighted harmonic mean of its fill points' (the soft, Reuss, bound).  All
three are exact for one material (docs/spring_mass.md, "Mixed materials")."""

LAYOUTS = ("farthest", "lattice")
"""Where the anchors lie (:attr:`SpringMassSettings.layout`): ``farthest``, farthest-point sampling of the fill,
closer together in thin parts, in the order the model's spring head predicts its stiffnesses; ``lattice``, a cubic
lattice centred on the body's bounding box, whose network keeps the box's mirror symmetries
(:mod:`.spring_mass_lattice`; docs/spring_mass.md, "The lattice layout")."""
LATTICE_STEP = 3
"""Fill spacings per anchor spacing along each axis of the lattice layout: no fill point is then equidistant from
two anchors (with 2, the points midway between two anchors would be shared out by index)."""
LATTICE_FILL_PER_ANCHOR = LATTICE_STEP ** 3
"""Fill points per anchor of the lattice layout (it does not use ``fill_per_anchor``)."""

STEP_BOUNDS = ("spectral", "gershgorin")
"""How the substep's stability limit bounds the network's highest frequency: ``spectral``, its largest eigenvalue
at rest (Lanczos, once per network); ``gershgorin``, per-anchor row sums (safe for any deformation, 2–3 times
shorter)."""


@dataclass
class SpringMassSettings(SolverSettings):
    """Set-up options of the spring-mass solver.

    anchors: N_a, number of anchors (fewer when the solid has fewer fill points); at most
        ``max_fill_points // fill_per_anchor`` (33,333 by default), so that every anchor has its fill points.
    neighbours: springs per anchor before merging (k of the k-NN graph).
    fixed_springs: ranks below this keep full strength whatever the softness (at most ``neighbours``).
    softness: η, the global softness (dimensionless real).
    stiffness: ``None`` (derive k from the material's E) or (N_a,) newtons — explicit per-anchor
        stiffness, what the model's spring head predicts.
    binding: anchors per tracked point.
    fill_per_anchor: fill points per anchor used for masses and cell volumes.
    max_fill_points: cap on the number of fill points.
    safety: fraction of the stability limit used as the substep (0 < safety <= 1).
    substeps: ``None`` (from stability) or a fixed number of substeps per frame interval.
    max_substeps_per_frame: refuse (UserError) a run whose stability limit needs more substeps
        per frame interval than this (e.g. a huge ``material_damping`` η: dashpots are explicit).
    stiffness_calibration: c_E (see module docstring).
    volumetric: the volumetric term per anchor that gives the network the material's Poisson ratio ν (springs
        rescaled to the material's shear modulus plus ½ λ_extra V (J − 1)² per anchor star, :mod:`.spring_mass`);
        False: springs only (ν = 1/4 whatever the material says; 1.6–1.8 times the substep rate on the CPU).
    mixing: ``"arithmetic"`` (default), ``"series"`` or ``"harmonic"``, how a cell's and a spring's modulus are
        averaged where materials mix (:data:`MIXING_RULES`); one material gives the same network with each.
    layout: ``"farthest"`` (default) or ``"lattice"``, where the anchors lie (:data:`LAYOUTS`): farthest-point
        sampling, refined in thin parts and in the spring head's order, or a lattice centred on the bounding box that
        keeps the body's mirror symmetries (27 fill points per anchor; ``fill_per_anchor`` is not used; the count is
        the nearest a cubic lattice inside the solid allows).
    step_bound: ``"spectral"`` (default) or ``"gershgorin"``, how the stability limit bounds the network's highest
        frequency (:data:`STEP_BOUNDS`, :meth:`.spring_mass.SpringMassSimulation.stable_substep`).
    lanes_per_anchor: threads that gather one anchor's spring forces (a tile reduction joins them; more than
        1 on the CPU needs ``warp.config.enable_cpu_blocks``).  ``None``: :data:`.spring_mass.GPU_LANES_PER_ANCHOR` on a GPU,
        1 on the CPU.
    """

    solver_words: ClassVar[str] = "spring-mass"

    anchors: int = setting(DEFAULT_ANCHORS, "count")
    neighbours: int = setting(DEFAULT_NEIGHBOURS, "count")
    fixed_springs: int = setting(DEFAULT_FIXED_SPRINGS, "count0")
    softness: float = DEFAULT_SOFTNESS
    stiffness: Optional[np.ndarray] = None
    binding: int = setting(DEFAULT_BINDING, "count")
    fill_per_anchor: int = setting(12, "count")
    max_fill_points: int = setting(400_000, "count")
    safety: float = setting(0.7, "fraction")
    substeps: Optional[int] = setting(None, "count", optional=True)
    max_substeps_per_frame: int = setting(200_000, "count")
    stiffness_calibration: float = setting(STIFFNESS_CALIBRATION, "positive")
    lanes_per_anchor: Optional[int] = setting(None, "count", optional=True, maximum=1024)
    volumetric: bool = setting(True, "flag")
    step_bound: str = setting("spectral", "choice", choices=STEP_BOUNDS)
    mixing: str = setting("arithmetic", "choice", choices=MIXING_RULES)
    layout: str = setting("farthest", "choice", choices=LAYOUTS)

    def check(self):
        self.fixed_springs = min(self.fixed_springs, self.neighbours)
        per_anchor = LATTICE_FILL_PER_ANCHOR if self.layout == "lattice" else self.fill_per_anchor
        if self.anchors * per_anchor > self.max_fill_points:  # the network would outgrow its fill
            raise UserError(
                f"spring-mass setting 'anchors' = {self.anchors:,} needs {self.anchors * per_anchor:,} fill "
                f"points ({per_anchor} per anchor), more than max_fill_points = {self.max_fill_points:,}: "
                f"give at most {self.max_fill_points // per_anchor:,} anchors, or raise max_fill_points")
        softness = as_number(self.softness)
        if softness is None:
            raise UserError(f"spring-mass setting 'softness' must be a number, got {self.softness!r}")
        self.softness = softness
        if math.isnan(self.softness) or self.softness == math.inf:
            raise UserError(f"spring-mass setting 'softness' must be a real number (or -inf), got {self.softness}")
        if self.stiffness is not None:
            k = np.asarray(self.stiffness, dtype=np.float64).reshape(-1)
            if k.size == 0 or not np.all(np.isfinite(k)) or np.any(k <= 0):
                raise UserError("explicit spring stiffness vector must be finite and positive (newtons, one per anchor)")
            self.stiffness = k
            if self.layout != "farthest":
                raise UserError("an explicit spring stiffness vector (the model's spring head) is one number per "
                                "anchor of the 'farthest' layout; give layout 'farthest' with it, or no stiffness vector")
