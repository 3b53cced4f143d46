"""The solver registry: every solver UniPixie has, by name, once.

Each :class:`Solver` names its module in ``unipixie.solvers`` (which implements :mod:`.api`'s interface), how
people call it (``label``, ``description``: the panel's enum, reports, the command line) and its settings
class (a :class:`~.settings.SolverSettings` dataclass: its defaults are the solver's defaults).  Everything
that lists solvers — command-line choices, the panel, the model's heads, the effect registry's
``solvers``, benchmarks, reports — reads :data:`SOLVERS` (or :data:`SOLVER_NAMES`) rather than spelling
the names out.  Importing this module loads neither Warp nor torch.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.errors import UserError
from .lbs_settings import LBSSettings
from .mpm_settings import MPMSettings
from .settings import SolverSettings
from .spring_mass_settings import SpringMassSettings


@dataclass(frozen=True)
class Solver:
    """One solver.

    name: the canonical name (``"mpm"``), also its module in ``unipixie.solvers`` and the model head
        that predicts its material parameters.
    label: short display name (``"MPM"``).
    description: one line for the panel and help texts.
    settings: its settings dataclass (:meth:`~.settings.SolverSettings.from_any` builds it from a dict).
    """

    name: str
    label: str
    description: str
    settings: type[SolverSettings]

    def defaults(self) -> SolverSettings:
        """The settings the solver runs with when a caller gives none."""
        return self.settings()


SOLVERS: dict[str, Solver] = {s.name: s for s in (
    Solver("mpm", "MPM", "Material Point Method: large deformation, contact, plasticity", MPMSettings),
    Solver("lbs", "LBS", "Reduced-order linear blend skinning: fast elastic motion", LBSSettings),
    Solver("spring_mass", "Spring-mass", "Anchors joined by springs: fast, approximate", SpringMassSettings),
)}
"""Solver name -> :class:`Solver`, in the order of the model's heads."""

SOLVER_NAMES: tuple[str, ...] = tuple(SOLVERS)
"""``("mpm", "lbs", "spring_mass")``."""

ALIASES = {"spring": "spring_mass", "springmass": "spring_mass", "spring-mass": "spring_mass"}
"""Other spellings people type, -> the canonical name."""


def canonical_solver(name: str) -> str:
    """The canonical name of ``name`` (any case, an alias allowed); a clear error for an unknown solver."""
    key = (name or "").strip().lower()
    key = ALIASES.get(key, key)
    if key not in SOLVERS:
        raise UserError(f"unknown solver {name!r}; choose one of: {', '.join(SOLVERS)}")
    return key
