"""What the solvers' settings share: building them from what a caller hands over.

Each solver's settings are a dataclass that validates its fields in ``__post_init__``
(:class:`~.mpm_settings.MPMSettings`, :class:`~.lbs_settings.LBSSettings`,
:class:`~.spring_mass_settings.SpringMassSettings`); they derive from :class:`SolverSettings` for
:meth:`SolverSettings.from_any`, so ``None``, an instance or a dict of fields mean the same to every solver.
"""

from __future__ import annotations

from dataclasses import fields
from typing import ClassVar

from ..core.errors import UserError


class SolverSettings:
    """Base of the solvers' settings dataclasses.

    solver_words: the solver as error messages name it (``"MPM"``, ``"spring-mass"``).
    """

    solver_words: ClassVar[str] = ""

    @classmethod
    def from_any(cls, settings):
        """``None`` (the defaults), an instance of ``cls``, or a dict of its fields (unknown keys refused)."""
        if settings is None:
            return cls()
        if isinstance(settings, cls):
            return settings
        if isinstance(settings, dict):
            known = {f.name for f in fields(cls)}
            unknown = sorted(set(settings) - known)
            if unknown:
                raise UserError(f"unknown {cls.solver_words} setting(s) {unknown}; known: {sorted(known)}")
            return cls(**settings)
        raise UserError(f"{cls.solver_words} settings must be a dict or {cls.__name__}, "
                        f"got {type(settings).__name__}")
