"""The effect registry: named, parameterised physical terms that every solver can switch on.

The base model is an elastic solid (fixed-corotated, E, ν, density) under
gravity, with the scenario's frictionless ground and clamp.  Everything else is
an *effect* (``shared/specs/measurement-format.md`` §2).  An effect is an
object with named parameters and one hook, :meth:`Effect.apply`, which writes
its contribution into a :class:`PhysicsTerms` record.  Solvers never look at
effect objects: they read the combined :class:`PhysicsTerms` (one per
simulated environment), so a new effect needs a new field in the terms and
support in each solver that gives it meaning, nothing else.

Command-line syntax (:func:`parse`)::

    linear_drag:c=0.5
    wind:acceleration=0,0.8,0
    stiffness_region:factor=3,box=0,0,0,0.1,0.1,0.05
    stiffness_region:factor=0.3,points=0-19+40+41
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Iterable, Mapping, Optional, Sequence

import numpy as np

from ..core.errors import UserError
from .registry import SOLVER_NAMES


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class Param:
    """One named parameter of an effect.

    name / unit / description: as shown in reports and the UI.
    default: value used when the user gives none.
    lower / upper: the bounds a fit may use (inclusive); also validated on input.
    log_scale: fit in log space (scale parameters spanning decades).
    size: 1 for scalars, 3 for vectors (``wind.acceleration``).
    fittable: False for structural parameters (``stiffness_region.region``).
    """

    name: str
    unit: str
    default: Any
    lower: float = -math.inf
    upper: float = math.inf
    description: str = ""
    log_scale: bool = False
    size: int = 1
    fittable: bool = True


# --------------------------------------------------------------------------- what solvers read
@dataclass
class PhysicsTerms:
    """The combined physics of all active effects, for one simulated environment.

    linear_drag: c, 1/s — body force −c·m·v.
    quadratic_drag: k, 1/m — body force −k·m·‖v‖·v.
    damping_eta: η, Pa·s — Kelvin–Voigt viscous stress 2η·sym(∇v) (leaves rigid motion alone).
    friction_mu: μ — Coulomb friction at the ground (0 = the base model's frictionless ground).
    ground_stiffness: Pa/m — normal stiffness of the ground per unit contact area (``inf`` = the base model's
        rigid ground; solvers realise it as the stiffest contact their step resolves, see :mod:`.contact`).
    ground_damping: Pa·s/m — normal dashpot of the ground per unit contact area (0 = the base model).
    yield_stress: Pa — von Mises yield of the elastic base material (``inf`` = no plasticity).
    extra_acceleration: (3,) m/s² — uniform acceleration on all mass (wind, mis-stated gravity).
    E_scale: ``None`` or (S,) float64 — multiplies Young's modulus of each solver sample point
        (``EffectContext.sample_positions`` order).
    """

    linear_drag: float = 0.0
    quadratic_drag: float = 0.0
    damping_eta: float = 0.0
    friction_mu: float = 0.0
    ground_stiffness: float = math.inf
    ground_damping: float = 0.0
    yield_stress: float = math.inf
    extra_acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))
    E_scale: Optional[np.ndarray] = None

    def is_base(self) -> bool:
        """True when no effect changes anything (the base model)."""
        return (self.linear_drag == 0 and self.quadratic_drag == 0 and self.damping_eta == 0
                and self.friction_mu == 0 and math.isinf(self.yield_stress)
                and math.isinf(self.ground_stiffness) and self.ground_damping == 0
                and not np.any(self.extra_acceleration) and (self.E_scale is None or np.all(self.E_scale == 1.0)))

    def E_multiplier(self, count: int) -> np.ndarray:
        """(count,) float64 multipliers of Young's modulus (ones when no region effect is active)."""
        if self.E_scale is None:
            return np.ones(count)
        if len(self.E_scale) != count:
            raise ValueError(f"E_scale has {len(self.E_scale)} entries for {count} sample points")
        return np.asarray(self.E_scale, dtype=np.float64)


@dataclass
class EffectContext:
    """What an effect may need to know about the simulated solid.

    sample_positions: (S, 3) metres, rest positions of the solver's material samples
        (MPM particles, spring-mass anchors, LBS cubature points).
    tracked_rest_positions: (M, 3) metres, rest positions of the tracked points (measurement
        points / mesh vertices); region effects given as point indices refer to these.
    """

    sample_positions: np.ndarray
    tracked_rest_positions: Optional[np.ndarray] = None


# --------------------------------------------------------------------------- base class
class Effect:
    """An effect with parameter values.  Subclasses set the class attributes and :meth:`apply`."""

    name: ClassVar[str] = ""
    label: ClassVar[str] = ""
    law: ClassVar[str] = ""
    signature: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    solvers: ClassVar[frozenset] = frozenset(SOLVER_NAMES)
    acts_at_ground: ClassVar[bool] = False
    """The effect acts only where the solid touches the ground (it changes nothing in a scene without one)."""

    def __init__(self, **values):
        known = {p.name: p for p in self.params}
        unknown = set(values) - set(known)
        if unknown:
            raise UserError(f"effect {self.name!r} has no parameter(s) {sorted(unknown)}; it takes {sorted(known)}")
        self.values: dict[str, Any] = {}
        for p in self.params:
            self.values[p.name] = self._validate(p, values.get(p.name, p.default))

    # -- validation -----------------------------------------------------------------
    def _validate(self, p: Param, v):
        if not p.fittable:
            return v
        if p.size == 1:
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise UserError(f"{self.name}.{p.name} must be a number ({p.unit}), got {v!r}") from None
            if not (math.isfinite(x) and p.lower <= x <= p.upper):
                raise UserError(f"{self.name}.{p.name} = {x:g} is outside [{p.lower:g}, {p.upper:g}] {p.unit}")
            return x
        arr = np.asarray(v, dtype=np.float64).reshape(-1)
        if arr.shape != (p.size,) or not np.all(np.isfinite(arr)):
            raise UserError(f"{self.name}.{p.name} must be {p.size} finite numbers ({p.unit}), got {v!r}")
        if np.any(arr < p.lower) or np.any(arr > p.upper):
            raise UserError(f"{self.name}.{p.name} = {arr.tolist()} is outside [{p.lower:g}, {p.upper:g}] {p.unit}")
        return arr

    # -- the hook -------------------------------------------------------------------
    def apply(self, terms: PhysicsTerms, ctx: EffectContext) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- fitting helpers --------------------------------------------------------------
    @classmethod
    def fittable_params(cls) -> tuple[Param, ...]:
        return tuple(p for p in cls.params if p.fittable)

    def fit_vector(self) -> np.ndarray:
        """The fittable parameters as one flat vector (vectors expanded)."""
        out: list[float] = []
        for p in self.fittable_params():
            v = self.values[p.name]
            out.extend(np.atleast_1d(np.asarray(v, dtype=np.float64)).tolist())
        return np.asarray(out, dtype=np.float64)

    @classmethod
    def fit_bounds(cls) -> tuple[np.ndarray, np.ndarray]:
        lo: list[float] = []
        hi: list[float] = []
        for p in cls.fittable_params():
            lo.extend([p.lower] * p.size)
            hi.extend([p.upper] * p.size)
        return np.asarray(lo), np.asarray(hi)

    def with_fit_vector(self, x: Sequence[float]) -> "Effect":
        """A copy with the fittable parameters replaced by ``x`` (clipped into bounds)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        values = dict(self.values)
        i = 0
        for p in self.fittable_params():
            chunk = np.clip(x[i:i + p.size], p.lower, p.upper)
            values[p.name] = float(chunk[0]) if p.size == 1 else chunk
            i += p.size
        if i != x.size:
            raise ValueError(f"{self.name}: fit vector has {x.size} entries, expected {i}")
        return type(self)(**values)

    def with_values(self, **changes) -> "Effect":
        values = dict(self.values)
        values.update(changes)
        return type(self)(**values)

    # -- (de)serialisation ---------------------------------------------------------
    def params_dict(self) -> dict:
        """JSON-able parameter values (vectors as lists)."""
        out = {}
        for k, v in self.values.items():
            if isinstance(v, np.ndarray):
                out[k] = v.tolist()
            elif isinstance(v, dict):
                out[k] = {kk: (vv.tolist() if isinstance(vv, np.ndarray) else vv) for kk, vv in v.items()}
            else:
                out[k] = v
        return out

    def to_dict(self) -> dict:
        return {"effect": self.name, "params": self.params_dict()}

    def to_spec(self) -> str:
        """The command-line form (``name:key=value,...``), read back by :func:`parse` (its inverse).

        Numbers are written with 6 significant digits; ``stiffness_region`` regions as
        ``box=x0,y0,z0,x1,y1,z1`` or ``points=i+j+...``.
        """
        return self.spec_of(self.values)

    @classmethod
    def spec_of(cls, values: Mapping[str, Any]) -> str:
        """:meth:`to_spec` of the given parameter values without validating them (e.g. a panel's fields).

        values: parameter name -> number, vector (any sequence) or region dict; parameters absent from
        ``values`` are left out of the spec (``parse`` gives them their defaults).
        """
        parts = []
        for p in cls.params:
            if p.name not in values:
                continue
            v = values[p.name]
            if isinstance(v, Mapping):
                if "box" in v:
                    parts.append("box=" + ",".join(f"{x:.6g}" for x in np.asarray(v["box"], dtype=float).reshape(-1)))
                else:
                    parts.append("points=" + "+".join(str(int(i)) for i in v["points"]))
            elif p.size > 1 or np.ndim(v) > 0:
                parts.append(f"{p.name}=" + ",".join(f"{float(x):.6g}" for x in v))
            else:
                parts.append(f"{p.name}={float(v):.6g}")
        return cls.name + (":" + ",".join(parts) if parts else "")

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v!r}" for k, v in self.params_dict().items())
        return f"{self.name}({inner})"

    def __eq__(self, other) -> bool:
        return isinstance(other, Effect) and self.to_dict() == other.to_dict()

    def __hash__(self):  # effects are values
        return hash(repr(self))


# --------------------------------------------------------------------------- the registry's effects
class LinearDrag(Effect):
    name = "linear_drag"
    label = "Linear drag"
    law = "force −c·m·v on every bit of mass (air resistance at low speed, mass-proportional damping)"
    signature = "centre of mass slows in free flight, in proportion to its speed"
    params = (Param("c", "1/s", 0.5, 0.0, 50.0, "drag rate"),)

    def apply(self, terms, ctx):
        terms.linear_drag += self.values["c"]


class QuadraticDrag(Effect):
    name = "quadratic_drag"
    label = "Quadratic drag"
    law = "force −k·m·‖v‖·v on every bit of mass (air resistance at high speed)"
    signature = "deceleration grows with the square of the speed"
    params = (Param("k", "1/m", 0.5, 0.0, 50.0, "drag coefficient per unit mass"),)

    def apply(self, terms, ctx):
        terms.quadratic_drag += self.values["k"]


class MaterialDamping(Effect):
    name = "material_damping"
    label = "Material (Kelvin–Voigt) damping"
    law = "viscous stress 2η·sym(∇v): damps deformation, leaves rigid motion alone"
    signature = "vibrations decay while the rigid motion is untouched"
    params = (Param("eta", "Pa·s", 10.0, 0.0, 1e6, "viscosity", log_scale=True),)

    def apply(self, terms, ctx):
        terms.damping_eta += self.values["eta"]


class GroundFriction(Effect):
    name = "ground_friction"
    label = "Ground friction"
    law = "Coulomb friction at the ground plane: tangential force ≤ μ × normal force; sticks below it"
    signature = "tangential residual only while in contact with the ground; abrupt stop"
    params = (Param("mu", "-", 0.5, 0.0, 2.0, "friction coefficient"),)
    acts_at_ground = True

    def apply(self, terms, ctx):
        terms.friction_mu = max(terms.friction_mu, self.values["mu"])


class ContactDamping(Effect):
    """The ground as a damped, yielding floor (a Kelvin–Voigt foundation) instead of the base model's rigid one.

    Where the solid's surface is a depth d below the ground plane, the ground pushes it back with the normal
    traction p = k·d + c·ḋ (never pulling).  The damper takes energy only while the floor gives: on a rigid
    floor (k → ∞) nothing moves at the contact and no contact law can take energy from an elastic solid,
    so ``c`` and ``k`` are fitted together.  Both are per unit contact area, so the law does not depend on a
    solver's resolution (``docs/contact.md``).
    """

    name = "contact_damping"
    label = "Contact damping (damped, yielding ground)"
    law = ("the ground pushes the solid's surface back with the normal traction k·d + c·ḋ at depth d (never "
           "pulling): a damped floor that takes energy at every contact")
    signature = "the solid loses energy, and rebounds lower, only at contacts with the ground; longer contacts"
    params = (Param("c", "Pa·s/m", 2.0e4, 0.0, 1.0e8, "normal damping per unit contact area", log_scale=True),
              Param("k", "Pa/m", 1.0e6, 1.0e3, 1.0e11, "normal stiffness of the floor per unit contact area",
                    log_scale=True))
    acts_at_ground = True

    def apply(self, terms, ctx):
        terms.ground_stiffness = min(terms.ground_stiffness, self.values["k"])
        terms.ground_damping = max(terms.ground_damping, self.values["c"])


class Plasticity(Effect):
    name = "plasticity"
    label = "Plasticity (von Mises)"
    law = "deviatoric stress capped at the yield stress; deformation past it is permanent"
    signature = "permanent change of rest shape where strain was high"
    params = (Param("yield_stress", "Pa", 1e4, 1.0, 1e10, "von Mises yield stress", log_scale=True),)

    def apply(self, terms, ctx):
        terms.yield_stress = min(terms.yield_stress, self.values["yield_stress"])


class Wind(Effect):
    name = "wind"
    label = "Wind / extra body force"
    law = "uniform extra acceleration on all mass (a steady wind or a mis-stated gravity)"
    signature = "drift growing as t²; shifted static equilibrium"
    params = (Param("acceleration", "m/s²", (0.0, 0.0, 0.0), -50.0, 50.0, "extra acceleration", size=3),)

    def apply(self, terms, ctx):
        terms.extra_acceleration = np.asarray(terms.extra_acceleration, dtype=np.float64) + self.values["acceleration"]


class StiffnessRegion(Effect):
    """Young's modulus multiplied by ``factor`` inside one region.

    ``region`` is either ``{"box": [[xmin, ymin, zmin], [xmax, ymax, zmax]]}`` (metres) or
    ``{"points": [indices of tracked points]}``; a solver sample belongs to a point region when
    its nearest tracked point (at rest) is in the list.
    """

    name = "stiffness_region"
    label = "Stiffness of one region"
    law = "Young's modulus multiplied by a factor inside one region of the solid"
    signature = "local hot spot of strain error"
    params = (Param("factor", "-", 2.0, 0.02, 50.0, "multiplier of E inside the region", log_scale=True),
              Param("region", "", None, description="{'box': [[x0,y0,z0],[x1,y1,z1]]} or {'points': [i, ...]}",
                    fittable=False))

    def _validate(self, p, v):
        if p.name != "region":
            return super()._validate(p, v)
        if v is None:
            raise UserError("stiffness_region needs a region: box=x0,y0,z0,x1,y1,z1 or points=i+j+k-l")
        if not isinstance(v, Mapping) or len(v) != 1 or next(iter(v)) not in ("box", "points"):
            raise UserError(f"stiffness_region.region must be {{'box': ...}} or {{'points': ...}}, got {v!r}")
        if "box" in v:
            box = np.asarray(v["box"], dtype=np.float64).reshape(-1)
            if box.size != 6 or not np.all(np.isfinite(box)):
                raise UserError("stiffness_region box must be 6 numbers x0,y0,z0,x1,y1,z1 (metres)")
            box = box.reshape(2, 3)
            if np.any(box[1] < box[0]):
                raise UserError("stiffness_region box: max corner below min corner")
            return {"box": box}
        idx = np.asarray(v["points"], dtype=np.int64).reshape(-1)
        if idx.size == 0 or np.any(idx < 0):
            raise UserError("stiffness_region points must be a non-empty list of non-negative indices")
        return {"points": np.unique(idx)}

    def region_mask(self, ctx: EffectContext) -> np.ndarray:
        """(S,) bool: which solver samples lie in the region."""
        pts = np.asarray(ctx.sample_positions, dtype=np.float64)
        region = self.values["region"]
        if "box" in region:
            lo, hi = region["box"]
            return np.all((pts >= lo) & (pts <= hi), axis=1)
        if ctx.tracked_rest_positions is None:
            raise UserError("stiffness_region given by point indices needs tracked points")
        tracked = np.asarray(ctx.tracked_rest_positions, dtype=np.float64)
        idx = region["points"]
        if idx.max() >= len(tracked):
            raise UserError(f"stiffness_region point index {int(idx.max())} out of range ({len(tracked)} tracked points)")
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(tracked).query(pts)
        member = np.zeros(len(tracked), dtype=bool)
        member[idx] = True
        return member[nearest]

    def apply(self, terms, ctx):
        mask = self.region_mask(ctx)
        scale = terms.E_multiplier(len(ctx.sample_positions)).copy()
        scale[mask] *= self.values["factor"]
        terms.E_scale = scale


EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (
    LinearDrag, QuadraticDrag, MaterialDamping, GroundFriction, ContactDamping, Plasticity, Wind, StiffnessRegion)}
"""Every registered effect class by name."""


def register(cls: type[Effect]) -> type[Effect]:
    """Add an effect class to the registry (usable as a decorator)."""
    if not cls.name or cls.name in EFFECTS:
        raise ValueError(f"effect name {cls.name!r} is empty or already registered")
    EFFECTS[cls.name] = cls
    return cls


def get(name: str) -> type[Effect]:
    try:
        return EFFECTS[name]
    except KeyError:
        raise UserError(f"unknown effect {name!r}; choose one of: {', '.join(EFFECTS)}") from None


def make(name: str, **values) -> Effect:
    """``make("linear_drag", c=0.5)``."""
    return get(name)(**values)


def from_dict(d: Mapping) -> Effect:
    """Inverse of :meth:`Effect.to_dict`."""
    if not isinstance(d, Mapping) or "effect" not in d:
        raise UserError(f"an effect must be {{'effect': name, 'params': {{...}}}}, got {d!r}")
    return make(d["effect"], **dict(d.get("params", {})))


def _parse_points(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split("+"):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def parse(spec: str) -> Effect:
    """Parse ``name[:key=value,...]`` (see the module docstring)."""
    spec = spec.strip()
    name, _, rest = spec.partition(":")
    cls = get(name.strip())
    values: dict[str, Any] = {}
    if rest.strip():
        # split on commas that start a new key=value (vector values contain commas)
        items: list[str] = []
        for tok in rest.split(","):
            if "=" in tok or not items:
                items.append(tok)
            else:
                items[-1] += "," + tok
        for item in items:
            if "=" not in item:
                raise UserError(f"effect spec {spec!r}: expected key=value, got {item!r}")
            key, val = (s.strip() for s in item.split("=", 1))
            try:
                if cls is StiffnessRegion and key in ("box", "points"):
                    values["region"] = {"box": [float(x) for x in val.split(",")]} if key == "box" else {"points": _parse_points(val)}
                elif "," in val:
                    values[key] = [float(x) for x in val.split(",")]
                else:
                    values[key] = float(val)
            except ValueError:
                raise UserError(f"effect spec {spec!r}: {key}={val!r} is not a number") from None
    return cls(**values)


def combine(effects: Iterable[Effect], ctx: EffectContext) -> PhysicsTerms:
    """Apply every effect's hook, in order, to fresh :class:`PhysicsTerms`."""
    terms = PhysicsTerms()
    seen: set[str] = set()
    for eff in effects:
        if not isinstance(eff, Effect):
            raise UserError(f"not an effect: {eff!r}")
        eff.apply(terms, ctx)
        seen.add(eff.name)
    return terms


def check_supported(effects: Iterable[Effect], solver: str) -> None:
    """Refuse effects that have no meaning in ``solver`` with a clear message."""
    for eff in effects:
        if solver not in eff.solvers:
            raise UserError(f"effect {eff.name!r} is not supported by the {solver} solver")
