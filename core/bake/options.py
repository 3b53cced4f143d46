"""The bake request: :class:`BakeOptions`, everything a bake needs besides the object and the scenario (solver,
frames and fps, material source and α, effects, device, output and interpolation, armature tolerance, solver
settings), checked once when it is made: the options are every bake's entry (panel, command line, manifests,
Python API), so α is checked here (:func:`~unipixie.core.types.check_alpha`) and trusted by the material
sources and the model below.

Uses :mod:`.frames`, :mod:`.sources`, :mod:`.output` and the solvers' registry and effects.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import UserError
from ..types import check_alpha
from .frames import FrameRange, parse_frames
from .output import ARMATURE_TOLERANCE, INTERPOLATIONS, OUTPUT_MODES
from .sources import HomogeneousSource, MaterialSource


@dataclass
class BakeOptions:
    """Everything a bake needs besides the object and the scenario.

    solver: ``"mpm"``, ``"lbs"`` or ``"spring_mass"``.
    frames: the scene frames to bake; fps: frames per second of the scene.
    material: a :class:`MaterialSource`; alpha: the soft-to-stiff control in [0, 1] (or ``None``).
    effects: registry effects (``solvers.effects.Effect``) or their CLI specs (``"linear_drag:c=0.5"``).
    device: ``cpu`` / ``cuda`` / ``cuda:N`` / ``auto``.
    output: one of :data:`OUTPUT_MODES`.  interpolation: one of :data:`INTERPOLATIONS`.
    particles: MPM only — also make a point-cloud object of the particles with attributes.
    armature_tolerance: LBS armature error allowed, as a fraction of the object's size.
    solver_settings: passed to the solver's ``prepare(settings=...)`` (dict or settings object).
    cache_dir: where Mesh Cache PC2 files go (``None``: next to the .blend).
    """

    solver: str = "mpm"
    frames: FrameRange = field(default_factory=lambda: FrameRange(1, 48))
    fps: float = 24.0
    material: MaterialSource = field(default_factory=HomogeneousSource)
    alpha: Optional[float] = None
    effects: list = field(default_factory=list)
    device: str = "cpu"
    output: str = "auto"
    interpolation: str = "LINEAR"
    particles: bool = False
    armature_tolerance: float = ARMATURE_TOLERANCE
    solver_settings: object = None
    cache_dir: Optional[str] = None
    allow_long: bool = False
    """Run even when the up-front cost estimate (:mod:`unipixie.core.cost`) passes the long-job limit."""

    def __post_init__(self):
        from ...solvers import effects as effects_mod
        from ...solvers.api import canonical_solver

        self.solver = canonical_solver(self.solver)
        if isinstance(self.frames, str):
            self.frames = parse_frames(self.frames)
        elif not isinstance(self.frames, FrameRange):
            a, b = self.frames
            self.frames = FrameRange(int(a), int(b))
        self.fps = float(self.fps)
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise UserError(f"frames per second must be positive, got {self.fps!r}")
        if self.alpha is not None:
            self.alpha = check_alpha(self.alpha)     # the bake's one check of α; everything below trusts it
        parsed = []
        for e in self.effects or []:
            if isinstance(e, str):
                parsed.append(effects_mod.parse(e))
            elif isinstance(e, dict):
                parsed.append(effects_mod.from_dict(e))
            else:
                parsed.append(e)
        effects_mod.check_supported(parsed, self.solver)
        self.effects = parsed
        if self.output not in OUTPUT_MODES:
            raise UserError(f"unknown output {self.output!r}; choose one of {', '.join(OUTPUT_MODES)}")
        if self.output == "armature" and self.solver != "lbs":
            raise UserError(f"an armature bake needs the LBS solver (its handles become bones), not {self.solver}")
        self.interpolation = str(self.interpolation).upper()
        if self.interpolation not in INTERPOLATIONS:
            raise UserError(f"unknown interpolation {self.interpolation!r}; choose LINEAR or CONSTANT")
        if self.particles and self.solver != "mpm":
            raise UserError("a particle object is made for MPM bakes only (other solvers have no particles)")
        self.armature_tolerance = float(self.armature_tolerance)
        if not self.armature_tolerance >= 0:
            raise UserError("the armature tolerance must be a non-negative fraction of the object's size")

    def times(self) -> np.ndarray:
        return self.frames.times(self.fps)
