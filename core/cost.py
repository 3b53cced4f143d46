"""What a simulation will cost, said before it starts: frames × substeps, memory, and a limit.

Explicit solvers (MPM, spring-mass) take a substep no longer than the time an elastic wave needs
to cross their resolution: ``Δt ≈ safety · h / c`` with ``c = sqrt((λ + 2μ)/ρ)`` the P-wave speed
of the stiffest, lightest material and ``h`` the grid cell (MPM: the largest extent / ``cells_across``)
or the anchor spacing (spring-mass: extent / anchors^(1/3)).  The LBS solver is implicit: one step
per ``max_dt``.  The estimate reads each solver's own defaults and the user's settings; it is an
order of magnitude (the solvers' step also follows the motion), which is what deciding "is this
run sane?" needs.

:class:`CostEstimate` says it in one line and :meth:`CostEstimate.check` refuses a run past
:data:`LONG_JOB_SUBSTEPS` substeps, :data:`LONG_JOB_FRAMES` frames or :data:`LONG_JOB_BYTES` of
trajectory in memory unless the user passes ``--allow-long`` (``allow_long=True``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..solvers.materials import elastic_p_wave_per_e
from ..solvers.registry import SOLVERS
from .errors import UserError

LONG_JOB_SUBSTEPS = 20_000_000
"""Total substeps (over all simulations of a job) above which a run needs ``--allow-long``: about an
hour of a 2048-anchor spring-mass body on a 2-core CPU (docs: ~2·10³ substeps/s), minutes on a GPU."""
LONG_JOB_FRAMES = 20_000
"""Frames of one simulation above which a run needs ``--allow-long`` (14 minutes of animation at 24 fps)."""
LONG_JOB_BYTES = 4.0e9
"""Bytes of simulated positions held in memory above which a run needs ``--allow-long``."""
ALLOW_LONG_FLAG = "--allow-long"


def wave_speed(E: float, nu: float, density: float) -> float:
    """P-wave speed (m/s) ``sqrt((λ + 2μ)/ρ)`` of an isotropic solid (E Pa, ν, ρ kg/m³)."""
    nu = min(max(float(nu), -0.999), 0.499)  # an estimate: impossible ν are refused by the material's own check
    factor = float(elastic_p_wave_per_e(nu))
    return math.sqrt(max(float(E), 0.0) * factor / max(float(density), 1e-12))


def material_bounds(spec) -> tuple[float, float, float]:
    """(largest E Pa, largest ν, smallest density kg/m³) of a material spec (homogeneous, per point or a
    field); the stiffest, lightest corner sets the explicit solvers' time step."""
    E = np.asarray(getattr(spec, "E", 1e5), dtype=np.float64)
    nu = np.asarray(getattr(spec, "nu", 0.3), dtype=np.float64)
    rho = np.asarray(getattr(spec, "density", 1000.0), dtype=np.float64)
    return float(np.max(E)), float(np.max(nu)), float(np.min(rho))


def _setting(settings, name: str, default):
    """The number ``settings[name]`` (``default`` when absent or None); a value that is not a finite number is a
    :class:`UserError` naming the setting (the estimate runs before the solver checks its settings)."""
    if settings is None:
        return default
    if isinstance(settings, dict):
        v = settings.get(name, default)
    else:
        v = getattr(settings, name, default)
    if v is None:
        return default
    try:
        number = float(v)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(v, bool) or not math.isfinite(number):
        raise UserError(f"setting '{name}' must be a finite number, got {v!r}")
    return v


def substep_seconds(solver: str, size: float, E: float, nu: float, density: float, settings=None) -> float:
    """About how long one substep of ``solver`` is (s) for a body ``size`` metres across."""
    c = max(wave_speed(E, nu, density), 1e-9)
    if solver == "mpm":
        d = SOLVERS["mpm"].defaults()
        dx = _setting(settings, "dx", None) or size / max(int(float(_setting(settings, "cells_across", d.cells_across))), 1)
        dt = float(_setting(settings, "cfl", d.cfl)) * float(dx) / c
        max_dt = _setting(settings, "max_dt", None)
        return min(dt, float(max_dt)) if max_dt else dt
    if solver == "spring_mass":
        d = SOLVERS["spring_mass"].defaults()
        anchors = max(int(float(_setting(settings, "anchors", d.anchors))), 1)
        return float(_setting(settings, "safety", d.safety)) * size / anchors ** (1.0 / 3.0) / c
    if solver == "lbs":
        return float(_setting(settings, "max_dt", SOLVERS["lbs"].defaults().max_dt))
    raise UserError(f"unknown solver {solver!r}")


@dataclass
class CostEstimate:
    """An up-front estimate of a job.

    what: the job in words; frames: instants per simulation (the first is the rest state);
    duration: simulated seconds; substep: seconds per substep (about); simulations: how many
    simulations the job runs; points: tracked points (or vertices) stored per frame.
    """

    what: str
    frames: int
    duration: float
    substep: float
    simulations: int = 1
    points: int = 0

    @property
    def substeps_per_simulation(self) -> float:
        return max(self.frames - 1, self.duration / max(self.substep, 1e-300))

    @property
    def total_substeps(self) -> float:
        if not math.isfinite(self.substep):
            return 0.0  # frames only: the frame limit decides
        return self.simulations * self.substeps_per_simulation

    @property
    def trajectory_bytes(self) -> float:
        return 12.0 * self.frames * self.points  # float32 positions

    def describe(self) -> str:
        if not math.isfinite(self.substep):  # frames only (the material is not known yet)
            return self.what
        sims = f"{self.simulations} simulations × " if self.simulations > 1 else ""
        per_frame = self.substeps_per_simulation / max(self.frames - 1, 1)
        return (f"{self.what}: {sims}{self.frames - 1:,} frame steps ({self.duration:.3g} s simulated) × about "
                f"{per_frame:,.0f} substeps = about {self.total_substeps:.2g} substeps")

    def over_limits(self) -> list[str]:
        """Which limits the job passes, in words (empty: a sane job)."""
        from .atomic_io import format_bytes

        out = []
        if self.frames > LONG_JOB_FRAMES:
            out.append(f"{self.frames:,} frames (more than {LONG_JOB_FRAMES:,})")
        if self.total_substeps > LONG_JOB_SUBSTEPS:
            out.append(f"about {self.total_substeps:.2g} substeps (more than {LONG_JOB_SUBSTEPS:.0e})")
        if self.trajectory_bytes > LONG_JOB_BYTES:
            out.append(f"about {format_bytes(self.trajectory_bytes)} of positions in memory (more than "
                       f"{format_bytes(LONG_JOB_BYTES)})")
        return out

    def check(self, allow_long: bool = False, remedy: str = "") -> None:
        """Refuse a job past the limits unless ``allow_long``; ``remedy`` says how to make it smaller."""
        over = self.over_limits()
        if over and not allow_long:
            raise UserError(f"{self.describe()}: that is {' and '.join(over)}; "
                            + (f"{remedy}, or " if remedy else "")
                            + f"pass {ALLOW_LONG_FLAG} to run it anyway")


def estimate(what: str, solver: str, *, size: float, times, material_spec, points: int, settings=None,
             simulations: int = 1) -> CostEstimate:
    """The :class:`CostEstimate` of ``simulations`` runs of ``solver`` over ``times`` (s) for a body
    ``size`` metres across made of ``material_spec``, storing ``points`` positions per frame."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    duration = float(t[-1] - t[0]) if t.size > 1 else 0.0
    E, nu, rho = material_bounds(material_spec)
    dt = substep_seconds(solver, float(size), E, nu, rho, settings)
    return CostEstimate(what, int(t.size), duration, dt, int(simulations), int(points))


def frames_estimate(what: str, frames: int, points: int = 0) -> Optional[CostEstimate]:
    """A frames-only estimate (before the material is known): refuses absurd frame counts early."""
    return CostEstimate(what, int(frames), 0.0, math.inf, 1, int(points))
