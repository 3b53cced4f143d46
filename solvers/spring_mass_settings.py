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
from .settings import SolverSettings

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


STEP_BOUNDS = ("spectral", "gershgorin")
"""How the substep's stability limit bounds the network's highest frequency: ``spectral``, its largest eigenvalue
at rest (Lanczos, once per network); ``gershgorin``, per-anchor row sums (safe for any deformation, 2–3 times
shorter)."""


@dataclass
class SpringMassSettings(SolverSettings):
    """Set-up options of the spring-mass solver.

    anchors: N_a, number of anchors (fewer when the solid has fewer fill points).
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
    step_bound: ``"spectral"`` (default) or ``"gershgorin"``, how the stability limit bounds the network's highest
        frequency (:data:`STEP_BOUNDS`, :meth:`.spring_mass.SpringMassSimulation.stable_substep`).
    lanes_per_anchor: threads that gather one anchor's spring forces (a tile reduction joins them; more than
        1 on the CPU needs ``warp.config.enable_cpu_blocks``).  ``None``: :data:`.spring_mass.GPU_LANES_PER_ANCHOR` on a GPU,
        1 on the CPU.
    """

    solver_words: ClassVar[str] = "spring-mass"

    anchors: int = DEFAULT_ANCHORS
    neighbours: int = DEFAULT_NEIGHBOURS
    fixed_springs: int = DEFAULT_FIXED_SPRINGS
    softness: float = DEFAULT_SOFTNESS
    stiffness: Optional[np.ndarray] = None
    binding: int = DEFAULT_BINDING
    fill_per_anchor: int = 12
    max_fill_points: int = 400_000
    safety: float = 0.7
    substeps: Optional[int] = None
    max_substeps_per_frame: int = 200_000
    stiffness_calibration: float = STIFFNESS_CALIBRATION
    lanes_per_anchor: Optional[int] = None
    volumetric: bool = True
    step_bound: str = "spectral"

    def __post_init__(self):
        if self.step_bound not in STEP_BOUNDS:
            raise UserError(f"spring-mass setting 'step_bound' must be one of {', '.join(STEP_BOUNDS)}, "
                            f"got {self.step_bound!r}")
        if not isinstance(self.volumetric, (bool, np.bool_)):
            raise UserError(f"spring-mass setting 'volumetric' must be true or false, got {self.volumetric!r}")
        self.volumetric = bool(self.volumetric)
        if self.lanes_per_anchor is not None:
            lanes = self.lanes_per_anchor
            if not isinstance(lanes, (int, np.integer)) or not 1 <= lanes <= 1024:
                raise UserError(f"spring-mass setting 'lanes_per_anchor' must be None or a whole number in 1..1024, "
                                f"got {lanes!r}")
            self.lanes_per_anchor = int(lanes)
        for name in ("anchors", "neighbours", "binding", "fill_per_anchor", "max_fill_points", "max_substeps_per_frame"):
            val = getattr(self, name)
            if not isinstance(val, (int, np.integer)) or val < 1:
                raise UserError(f"spring-mass setting '{name}' must be a positive whole number, got {val!r}")
            setattr(self, name, int(val))
        if not isinstance(self.fixed_springs, (int, np.integer)) or self.fixed_springs < 0:
            raise UserError(f"spring-mass setting 'fixed_springs' must be a whole number >= 0, got {self.fixed_springs!r}")
        self.fixed_springs = min(int(self.fixed_springs), self.neighbours)
        try:
            self.softness = float(self.softness)
        except (TypeError, ValueError):
            raise UserError(f"spring-mass setting 'softness' must be a number, got {self.softness!r}") from None
        if math.isnan(self.softness) or self.softness == math.inf:
            raise UserError(f"spring-mass setting 'softness' must be a real number (or -inf), got {self.softness}")
        if not (0.0 < float(self.safety) <= 1.0):
            raise UserError(f"spring-mass setting 'safety' must lie in (0, 1], got {self.safety!r}")
        if self.substeps is not None and (int(self.substeps) != self.substeps or self.substeps < 1):
            raise UserError(f"spring-mass setting 'substeps' must be None or a positive whole number, got {self.substeps!r}")
        if not (np.isfinite(self.stiffness_calibration) and self.stiffness_calibration > 0):
            raise UserError("spring-mass setting 'stiffness_calibration' must be positive")
        if self.stiffness is not None:
            k = np.asarray(self.stiffness, dtype=np.float64).reshape(-1)
            if k.size == 0 or not np.all(np.isfinite(k)) or np.any(k <= 0):
                raise UserError("explicit spring stiffness vector must be finite and positive (newtons, one per anchor)")
            self.stiffness = k
