"""The solvers' settings declare their rules where their fields are (solvers/settings.py): every solver checks the
same kind of value with the same words, and no plain setting goes unchecked (issue 22)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.solvers.registry import SOLVERS
from unipixie.solvers.settings import KINDS, Rule, check_setting

UNRULED = {"softness", "stiffness", "initial_deformation", "skinning_params"}
"""Settings that are not one number, flag or word (a vector, a matrix, a real that may be -inf): checked by their
class's ``check``."""

SETTINGS = [SOLVERS[name].settings for name in sorted(SOLVERS)]


@pytest.mark.parametrize("cls", SETTINGS, ids=lambda c: c.__name__)
def test_every_plain_setting_declares_its_rule(cls):
    for f in fields(cls):
        assert f.name in UNRULED or isinstance(f.metadata.get("rule"), Rule), f"{cls.__name__}.{f.name} has no rule"


def _first(cls, kind):
    return next(f for f in fields(cls) if f.metadata.get("rule") and f.metadata["rule"].kind == kind
                and f.metadata["rule"].maximum is None and not f.metadata["rule"].optional)


@pytest.mark.parametrize("cls", SETTINGS, ids=lambda c: c.__name__)
def test_the_same_value_gets_the_same_answer_in_every_solver(cls):
    count = _first(cls, "count").name
    words = cls.solver_words
    assert getattr(cls(**{count: 12.0}), count) == 12 and isinstance(getattr(cls(**{count: 12.0}), count), int)
    assert getattr(cls(**{count: np.int64(7)}), count) == 7
    for bad in ("12", 12.5, True, 0, -3, None):
        with pytest.raises(UserError, match=f"^{words} setting '{count}' must be a positive whole number"):
            cls(**{count: bad})
    positive = _first(cls, "positive").name
    assert isinstance(getattr(cls(**{positive: 2}), positive), float)
    for bad in ("0.3", float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(UserError, match=f"^{words} setting '{positive}' must be (a number|positive)"):
            cls(**{positive: bad})
    flag = _first(cls, "flag").name
    assert getattr(cls(**{flag: np.bool_(False)}), flag) is False and getattr(cls(**{flag: 1}), flag) is True
    for bad in ("yes", 2, 0.0):
        with pytest.raises(UserError, match=f"^{words} setting '{flag}' must be true or false"):
            cls(**{flag: bad})
    choice = _first(cls, "choice")
    for bad in ("no-such-way", 3):
        with pytest.raises(UserError, match=f"setting '{choice.name}' must be one of "
                                            f"{', '.join(choice.metadata['rule'].choices)}"):
            cls(**{choice.name: bad})


@pytest.mark.parametrize("kind, value, expected", [
    ("count0", 0, 0), ("fraction", 1, 1.0), ("unit", 0, 0.0), ("count", None, None)])
def test_check_setting_edges(kind, value, expected):
    rule = Rule(kind, optional=value is None)
    assert check_setting("X", "s", rule, value) == expected
    if kind == "fraction":
        with pytest.raises(UserError, match=r"must lie in \(0, 1\]"):
            check_setting("X", "s", rule, 0)
    with pytest.raises(UserError, match="must be at most 5 \\(hint\\), got 6"):
        check_setting("X", "s", Rule("count", maximum=5, hint=" (hint)"), 6)
    with pytest.raises(ValueError, match="unknown setting rule"):
        Rule("integer")
    assert set(KINDS) == {"count", "count0", "positive", "fraction", "unit", "choice", "flag"}


def test_spring_mass_anchors_beyond_their_fill_are_refused_with_the_limit():
    """A network of more anchors than its fill points can give ``fill_per_anchor`` each (``anchors=1e9``: the fill
    stops at ``max_fill_points`` and every fill point would become an anchor, a build of minutes) is refused at once,
    naming the largest count; raising ``max_fill_points`` admits it."""
    from unipixie.solvers.spring_mass_settings import SpringMassSettings

    with pytest.raises(UserError, match=r"anchors' = 1,000,000,000 .* at most 33,333 anchors"):
        SpringMassSettings(anchors=10 ** 9)
    assert SpringMassSettings(anchors=33_333).anchors == 33_333
    with pytest.raises(UserError, match="at most 33,333"):
        SpringMassSettings(anchors=33_334)
    assert SpringMassSettings(anchors=50_000, max_fill_points=600_000).anchors == 50_000
