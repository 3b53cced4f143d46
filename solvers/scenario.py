"""The scenario a solid is simulated in: the same fields as a measurement file's scenario.

See ``shared/specs/measurement-format.md`` §1.  Z is up; SI units.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from ..core.errors import UserError

SCENARIO_FORMAT = "unipixie.measurement/1"
SCENARIO_KEYS = ("format", "gravity", "ground", "initial_velocity", "initial_angular_velocity", "pinned_box", "material",
                 "notes")
"""The scenario JSON's own keys (``shared/specs/measurement-format.md`` §1); others are kept and ignored."""
_KNOWN = frozenset(SCENARIO_KEYS)


def require_json_numbers(value, what: str) -> None:
    """Numbers read from JSON (a scenario, a CSV's side-car, a bake manifest) are JSON numbers: text such as
    ``"9.81"`` or true/false is refused in every key, at any depth of nesting — one rule for every file.
    ``what`` names the key in the message (``"scenario key 'gravity'"``)."""
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, (list, tuple)):
            stack.extend(v)
        elif isinstance(v, (str, bytes, bool, np.str_, np.bool_)):
            raise UserError(f"{what} must hold numbers (JSON numbers, not text or true/false), got {value!r}")


def _not_text(value, key: str) -> None:
    require_json_numbers(value, f"scenario key '{key}'")


def _vec3(value, key: str) -> np.ndarray:
    _not_text(value, key)
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise UserError(f"scenario key '{key}' must be a list of 3 numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise UserError(f"scenario key '{key}' must be 3 finite numbers, got {value!r}")
    return arr


@dataclass
class Scenario:
    """Where and how the solid moves.

    gravity: (3,) m/s², default (0, 0, -9.81).
    ground_height: the ground plane z = height in metres, or ``None`` for no ground.  The base
        model's ground is frictionless (friction is the ``ground_friction`` effect).
    initial_velocity: (3,) m/s, rigid initial velocity of the whole solid.
    initial_angular_velocity: (3,) rad/s about the solid's centre of mass.
    pinned_box: ``None`` or (2, 3) [[xmin, ymin, zmin], [xmax, ymax, zmax]] metres: material
        inside is held at its rest position for all time.
    notes: free text.  extras: unknown keys, kept and ignored.
    """

    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    ground_height: Optional[float] = 0.0
    initial_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    initial_angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pinned_box: Optional[np.ndarray] = None
    notes: str = ""
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        self.gravity = _vec3(self.gravity, "gravity")
        self.initial_velocity = _vec3(self.initial_velocity, "initial_velocity")
        self.initial_angular_velocity = _vec3(self.initial_angular_velocity, "initial_angular_velocity")
        if self.ground_height is not None:
            _not_text(self.ground_height, "ground")
            try:
                self.ground_height = float(self.ground_height)
            except (TypeError, ValueError):
                raise UserError(f"scenario key 'ground' must be null or {{\"height\": number}}, got {self.ground_height!r}") from None
            if not np.isfinite(self.ground_height):
                raise UserError("scenario key 'ground': height must be finite")
        if self.pinned_box is not None:
            _not_text(self.pinned_box, "pinned_box")
            try:
                box = np.asarray(self.pinned_box, dtype=np.float64)
            except (TypeError, ValueError):
                raise UserError(f"scenario key 'pinned_box' must be [[xmin,ymin,zmin],[xmax,ymax,zmax]], got "
                                f"{self.pinned_box!r}") from None
            if box.shape != (2, 3) or not np.all(np.isfinite(box)):
                raise UserError(f"scenario key 'pinned_box' must be [[xmin,ymin,zmin],[xmax,ymax,zmax]], got {self.pinned_box!r}")
            if np.any(box[1] < box[0]):
                raise UserError("scenario key 'pinned_box': max corner must not be below min corner")
            self.pinned_box = box

    # ------------------------------------------------------------------ helpers
    def pinned_mask(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) rest positions -> (N,) bool, True for material held by the clamp."""
        pts = np.asarray(points, dtype=np.float64)
        if self.pinned_box is None:
            return np.zeros(len(pts), dtype=bool)
        lo, hi = self.pinned_box
        return np.all((pts >= lo) & (pts <= hi), axis=1)

    def initial_velocities(self, points: np.ndarray, masses: np.ndarray | None = None) -> np.ndarray:
        """Rigid initial velocity v + ω × (x − x_com) at (N, 3) points (pinned material gets zero)."""
        pts = np.asarray(points, dtype=np.float64)
        w = np.ones(len(pts)) if masses is None else np.asarray(masses, dtype=np.float64)
        com = (pts * w[:, None]).sum(0) / max(w.sum(), 1e-30)
        v = self.initial_velocity[None, :] + np.cross(self.initial_angular_velocity[None, :], pts - com)
        v[self.pinned_mask(pts)] = 0.0
        return v

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        d: dict[str, Any] = dict(self.extras)
        d.update({
            "format": SCENARIO_FORMAT,
            "gravity": self.gravity.tolist(),
            "ground": None if self.ground_height is None else {"height": self.ground_height},
            "initial_velocity": self.initial_velocity.tolist(),
            "initial_angular_velocity": self.initial_angular_velocity.tolist(),
            "pinned_box": None if self.pinned_box is None else self.pinned_box.tolist(),
            "notes": self.notes,
        })
        return d

    def to_json(self, **extra) -> str:
        d = self.to_dict()
        d.update(extra)
        return json.dumps(d)

    @classmethod
    def from_dict(cls, d: dict) -> "Scenario":
        """Parse a scenario dict (the measurement spec's JSON); errors name the offending key."""
        if not isinstance(d, dict):
            raise UserError("scenario must be a JSON object")
        fmt = d.get("format")
        if fmt != SCENARIO_FORMAT:
            raise UserError(f"scenario key 'format' is {fmt!r}, expected {SCENARIO_FORMAT!r}")
        ground = d.get("ground", {"height": 0.0})
        if ground is None:
            height = None
        elif isinstance(ground, dict) and "height" in ground:
            height = ground["height"]
        else:
            raise UserError(f"scenario key 'ground' must be null or {{\"height\": number}}, got {ground!r}")
        extras = {k: v for k, v in d.items() if k not in _KNOWN}
        return cls(gravity=d.get("gravity", [0.0, 0.0, -9.81]), ground_height=height,
                   initial_velocity=d.get("initial_velocity", [0.0, 0.0, 0.0]),
                   initial_angular_velocity=d.get("initial_angular_velocity", [0.0, 0.0, 0.0]),
                   pinned_box=d.get("pinned_box"), notes=str(d.get("notes", "")), extras=extras)

    @classmethod
    def from_json(cls, text: str) -> "Scenario":
        try:
            d = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise UserError(f"scenario is not valid JSON: {exc}") from None
        return cls.from_dict(d)
