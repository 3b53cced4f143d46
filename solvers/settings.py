"""What the solvers' settings share: declared rules for their fields, and building them from what a caller hands over.

Each solver's settings are a dataclass deriving from :class:`SolverSettings`
(:class:`~.mpm_settings.MPMSettings`, :class:`~.lbs_settings.LBSSettings`,
:class:`~.spring_mass_settings.SpringMassSettings`).  A field states its rule where it is declared
(:func:`setting`: a whole number of at least 1 or 0, a positive number, a fraction, a choice, a flag; ``None``
allowed or not; an upper bound), and :meth:`SolverSettings.__post_init__` checks and normalises every declared
field the same way for all three — the same words in every message, ``"12"`` as text refused everywhere, ``12.0``
accepted as a whole number, ``12.5`` not — before the class's own :meth:`SolverSettings.check` looks at what a
single field's rule cannot say (a default that depends on another field, a vector, a matrix).
:meth:`SolverSettings.from_any` makes ``None``, an instance or a dict of fields mean the same to every solver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Optional

import numpy as np

from ..core.errors import UserError

KINDS = ("count", "count0", "positive", "fraction", "unit", "choice", "flag")
"""Rules a setting can declare: ``count`` a whole number ≥ 1, ``count0`` a whole number ≥ 0, ``positive`` a finite
number > 0, ``fraction`` a number in (0, 1], ``unit`` a number in [0, 1], ``choice`` one of the stated strings,
``flag`` true or false."""


@dataclass(frozen=True)
class Rule:
    """One setting's rule (:data:`KINDS`); optional: ``None`` is allowed (and kept); maximum: an upper bound (with
    ``hint``, a few words after it in the message); choices: the strings of a ``choice``."""

    kind: str
    optional: bool = False
    maximum: Optional[float] = None
    hint: str = ""
    choices: tuple = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown setting rule {self.kind!r}; the rules are {', '.join(KINDS)}")


def setting(default: Any, kind: str, *, optional: bool = False, maximum: Optional[float] = None, hint: str = "",
            choices: tuple = ()):
    """A dataclass field with ``default`` and its :class:`Rule` (checked by :meth:`SolverSettings.__post_init__`)."""
    return field(default=default, metadata={"rule": Rule(kind, optional, maximum, hint, tuple(choices))})


def _whole(value) -> Optional[int]:
    """``value`` as an int when it is a whole number (int, numpy integer, or a float with no fraction), else None."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)) and math.isfinite(float(value)) and float(value).is_integer():
        return int(value)
    return None


def as_number(value) -> Optional[float]:
    """``value`` as a float when it is a real number (not text, not a flag), else None."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    return float(value)


def check_setting(words: str, name: str, rule: Rule, value):
    """``value`` checked against ``rule`` and normalised (int, float, str or bool); a :class:`UserError` naming the
    setting (``"MPM setting 'dx' must be positive, got -0.1"``) otherwise."""
    if value is None and rule.optional:
        return None
    says = f"{words} setting '{name}' must"
    or_none = " (or None)" if rule.optional else ""
    if rule.kind in ("count", "count0"):
        n = _whole(value)
        least = 1 if rule.kind == "count" else 0
        if n is None or n < least:
            what = "a positive whole number" if least == 1 else "a whole number >= 0"
            raise UserError(f"{says} be {what}{or_none}, got {value!r}")
        out = n
    elif rule.kind in ("positive", "fraction", "unit"):
        x = as_number(value)
        if x is None:
            raise UserError(f"{says} be a number{or_none}, got {value!r}")
        if rule.kind == "positive" and not (math.isfinite(x) and x > 0):
            raise UserError(f"{says} be positive{or_none}, got {value!r}")
        if rule.kind == "fraction" and not 0.0 < x <= 1.0:
            raise UserError(f"{says} lie in (0, 1]{or_none}, got {value!r}")
        if rule.kind == "unit" and not 0.0 <= x <= 1.0:
            raise UserError(f"{says} lie in [0, 1]{or_none}, got {value!r}")
        out = x
    elif rule.kind == "choice":
        if not isinstance(value, str) or value not in rule.choices:
            raise UserError(f"{says} be one of {', '.join(rule.choices)}{or_none}, got {value!r}")
        out = value
    else:  # flag
        if isinstance(value, (bool, np.bool_)) or (_whole(value) in (0, 1) and not isinstance(value, float)):
            out = bool(value)
        else:
            raise UserError(f"{says} be true or false{or_none}, got {value!r}")
    if rule.maximum is not None and out > rule.maximum:
        raise UserError(f"{says} be at most {rule.maximum:g}{rule.hint}, got {value!r}")
    return out


class SolverSettings:
    """Base of the solvers' settings dataclasses.

    solver_words: the solver as error messages name it (``"MPM"``, ``"spring-mass"``).
    """

    solver_words: ClassVar[str] = ""

    def __post_init__(self):
        for f in fields(self):
            rule = f.metadata.get("rule")
            if rule is not None:
                setattr(self, f.name, check_setting(self.solver_words, f.name, rule, getattr(self, f.name)))
        self.check()

    def check(self) -> None:
        """What a single field's rule cannot say (overridden by the solvers; runs after the declared rules)."""

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
