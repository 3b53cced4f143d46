"""Per-part material property *ranges* and the inter-part constraints they must satisfy.

The paper's PixieMultiVerse annotates every part of an object with a plausible
range ``[y_min, y_max]`` of Young's modulus E (Pa), Poisson's ratio ν and
density ρ (kg/m³) plus a material class, and states inter-part constraints
("the trunk is stiffer than the leaves") that must hold for *any* value drawn
from the ranges.  The VLM of the paper writes these constraints as Python
``assert`` statements; here they are **data** (:class:`Constraint`) checked in
code — nothing is ever ``exec``-uted.  :func:`parse_constraint` reads the
paper's assert form with a strict pattern, refusing anything else.

What lives here
---------------
* :data:`CLASS_PRIORS` — the class-level priors of the procedural dataset:
  for each semantic class, its parts (material class from the registry in
  :mod:`unipixie.solvers.materials`, where the range centre and half-width of
  log10 E, ν and density may fall), appearance variants that shift the priors,
  the constraints, and the simulated scenario.
* :func:`sample_annotation` — draws an :class:`Annotation` from a class prior.
  Each part's *appearance code* ``u`` ∈ [0, 1] (chosen by the procedural
  generator, which also uses it for the part's colour and texture) places the
  range centre inside the prior, so appearance carries information about the
  material.  Draws that violate a constraint are re-drawn.
* :func:`validate` — every check a user-supplied annotation goes through
  (ranges non-empty and physical, classes known, constraints satisfied).
* :func:`interpolate` — the labels at any α: log10 E and log10 ρ are
  interpolated linearly in log space, ν linearly (the paper's LERP,
  ``y = (1 − α) y_min + α y_max``, on the model's channels); the class does
  not change with α.

Units: E in Pa, density in kg/m³, ν dimensionless; lengths (scenario) in metres.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from .errors import UserError, read_json
from ..solvers import materials

ANNOTATION_FORMAT = "unipixie.annotation/1"
QUANTITIES = ("E", "nu", "density")
"""The annotated quantities (Pa, 1, kg/m³)."""
LOG_QUANTITIES = frozenset({"E", "density"})
"""Quantities that are interpolated (and compared by the model) in log10 space."""

NU_BOUNDS = (-0.99, 0.499)
"""Poisson's ratio ν an annotation may use (a solid needs −1 < ν < 0.5)."""
E_BOUNDS = (1.0, 1.0e13)
"""Young's modulus E (Pa) an annotation may use."""
DENSITY_BOUNDS = (1.0, 25000.0)
"""Density (kg/m³) an annotation may use."""
_BOUNDS = {"E": E_BOUNDS, "nu": NU_BOUNDS, "density": DENSITY_BOUNDS}


# =========================================================================== annotations
@dataclass(frozen=True)
class PartRange:
    """The annotated ranges of one part.

    material: material-class name from :mod:`unipixie.solvers.materials` (``"jelly"``, ...).
    E: (min, max) Pa; nu: (min, max); density: (min, max) kg/m³.  min <= max for each.
    """

    material: str
    E: tuple
    nu: tuple
    density: tuple

    def range(self, quantity: str) -> tuple:
        return getattr(self, quantity)

    def to_dict(self) -> dict:
        return {"material": self.material, "E": list(self.E), "nu": list(self.nu), "density": list(self.density)}


@dataclass(frozen=True)
class Constraint:
    """An inter-part constraint on one quantity, as data.

    ``kind = "all"`` (the paper's: must hold for ANY values drawn from the ranges):
    ``greater``'s minimum is above ``lesser``'s maximum times ``factor``
    (``min(greater) > factor * max(lesser)``; ``factor`` multiplies the
    quantity itself, 1 by default).
    ``kind = "mid"``: the range midpoints are ordered (geometric midpoint for E and
    density), a weaker statement for parts whose ranges may overlap.
    """

    quantity: str
    greater: str
    lesser: str
    kind: str = "all"
    factor: float = 1.0

    def __post_init__(self):
        if self.quantity not in QUANTITIES:
            raise UserError(f"constraint quantity {self.quantity!r} is not one of {', '.join(QUANTITIES)}")
        if self.kind not in ("all", "mid"):
            raise UserError(f"constraint kind {self.kind!r} must be 'all' or 'mid'")
        if not (math.isfinite(self.factor) and self.factor > 0):
            raise UserError(f"constraint factor must be a positive number, got {self.factor!r}")
        if self.greater == self.lesser:
            raise UserError(f"constraint compares part {self.greater!r} with itself")

    def describe(self) -> str:
        word = {"E": "stiffer", "density": "denser", "nu": "of higher Poisson's ratio"}[self.quantity]
        how = "for every value in the ranges" if self.kind == "all" else "at the range midpoints"
        fac = f" by a factor {self.factor:g}" if self.factor != 1.0 else ""
        return f"{self.greater} {word} than {self.lesser}{fac} ({how})"

    def holds(self, parts: Mapping[str, PartRange]) -> bool:
        a = parts[self.greater].range(self.quantity)
        b = parts[self.lesser].range(self.quantity)
        if self.kind == "all":
            return bool(a[0] > self.factor * b[1])
        return bool(_midpoint(self.quantity, a) > self.factor * _midpoint(self.quantity, b))

    def to_dict(self) -> dict:
        return {"quantity": self.quantity, "greater": self.greater, "lesser": self.lesser, "kind": self.kind,
                "factor": self.factor}

    @classmethod
    def from_dict(cls, d) -> "Constraint":
        if isinstance(d, str):
            return parse_constraint(d)
        if not isinstance(d, Mapping):
            raise UserError(f"a constraint must be an object or an assert string, got {d!r}")
        missing = {"quantity", "greater", "lesser"} - set(d)
        if missing:
            raise UserError(f"constraint {dict(d)!r} lacks key(s) {', '.join(sorted(missing))}")
        try:
            return cls(str(d["quantity"]), str(d["greater"]), str(d["lesser"]), str(d.get("kind", "all")),
                       float(d.get("factor", 1.0)))
        except (TypeError, ValueError) as exc:
            raise UserError(f"constraint {dict(d)!r}: {exc}") from None


def _midpoint(quantity: str, r: tuple) -> float:
    if quantity in LOG_QUANTITIES:
        return math.sqrt(r[0] * r[1])
    return 0.5 * (r[0] + r[1])


_ASSERT = re.compile(
    r"""^\s*(?:assert\s+)?
        mat\[\s*['"](?P<a>[A-Za-z_][\w ]*)['"]\s*\]\[\s*['"](?P<qa>E|nu|density)['"]\s*\]\[\s*(?P<ia>[01])\s*\]
        \s*(?P<op>>=|<=|>|<)\s*
        (?:(?P<f>[0-9.eE+-]+)\s*\*\s*)?
        mat\[\s*['"](?P<b>[A-Za-z_][\w ]*)['"]\s*\]\[\s*['"](?P<qb>E|nu|density)['"]\s*\]\[\s*(?P<ib>[01])\s*\]
        \s*$""", re.VERBOSE)


def parse_constraint(text: str) -> Constraint:
    """Read one constraint in the paper's assert form, e.g. ``assert mat['pot']['E'][0] > mat['trunk']['E'][1]``.

    Only comparisons of a range end of one part with a range end of another part (same quantity,
    optional numeric factor on the right) are accepted; anything else is a :class:`UserError`.  The
    text is matched by a regular expression and never executed.  ``[0] > [1]`` reads as kind
    ``"all"``; any other pair of range ends is refused (it would not hold for every drawn value or is
    implied by a stronger statement).
    """
    m = _ASSERT.match(text or "")
    if not m:
        raise UserError(f"cannot read constraint {text!r}: expected the form "
                        "\"mat['A']['E'][0] > mat['B']['E'][1]\" (quantities E, nu, density; never executed)")
    if m["qa"] != m["qb"]:
        raise UserError(f"constraint {text!r} compares different quantities ({m['qa']} and {m['qb']})")
    a, b, ia, ib, op = m["a"], m["b"], m["ia"], m["ib"], m["op"]
    factor = float(m["f"]) if m["f"] else 1.0
    if op in ("<", "<="):  # mat[a][..][ia] < mat[b][..][ib]  ==  mat[b][..][ib] > mat[a][..][ia]
        if factor != 1.0:
            raise UserError(f"constraint {text!r}: a factor is only understood on the smaller side ('>' form)")
        a, b, ia, ib = b, a, ib, ia
    if (ia, ib) != ("0", "1"):
        raise UserError(f"constraint {text!r}: only 'min of one part above max of another' ([0] > [1]) is supported")
    return Constraint(m["qa"], a, b, "all", factor)


@dataclass
class Annotation:
    """The annotation of one object: semantic class, per-part ranges and constraints.

    semantic_class: the object's class (``"potted_plant"``, ...; free text for a user's own set).
    parts: part name -> :class:`PartRange`, in the object's part order (part ids are indices into it).
    constraints: inter-part :class:`Constraint` records.
    variant: appearance variant of the class (procedural objects), else ``""``.
    """

    semantic_class: str
    parts: dict
    constraints: list = field(default_factory=list)
    variant: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def part_names(self) -> list:
        return list(self.parts)

    def to_dict(self) -> dict:
        return {"format": ANNOTATION_FORMAT, "semantic_class": self.semantic_class, "variant": self.variant,
                "parts": {k: v.to_dict() for k, v in self.parts.items()},
                "constraints": [c.to_dict() for c in self.constraints], "meta": self.meta}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d, source: str = "annotation") -> "Annotation":
        """Parse and :func:`validate`; every problem is a :class:`UserError` naming ``source`` and the key."""
        if not isinstance(d, Mapping):
            raise UserError(f"{source}: must be a JSON object")
        fmt = d.get("format", ANNOTATION_FORMAT)
        if fmt != ANNOTATION_FORMAT:
            raise UserError(f"{source}: key 'format' is {fmt!r}, expected {ANNOTATION_FORMAT!r}")
        raw_parts = d.get("parts", d.get("material_dict"))
        if not isinstance(raw_parts, Mapping) or not raw_parts:
            raise UserError(f"{source}: key 'parts' must map part names to their ranges")
        parts = {}
        for name, pr in raw_parts.items():
            if not isinstance(pr, Mapping):
                raise UserError(f"{source}: part {name!r} must be an object with 'material', 'E', 'nu', 'density'")
            missing = {"material", "E", "nu", "density"} - set(pr)
            if missing:
                raise UserError(f"{source}: part {name!r} lacks key(s) {', '.join(sorted(missing))}")
            vals = {}
            for q in QUANTITIES:
                r = pr[q]
                try:
                    lo, hi = (float(x) for x in r)
                except (TypeError, ValueError):
                    raise UserError(f"{source}: part {name!r} key {q!r} must be [min, max], got {r!r}") from None
                vals[q] = (lo, hi)
            parts[str(name)] = PartRange(str(pr["material"]), vals["E"], vals["nu"], vals["density"])
        cons = d.get("constraints", [])
        if isinstance(cons, str):
            cons = [c for c in re.split(r"[\n;]", cons) if c.strip()]
        constraints = [Constraint.from_dict(c) for c in cons]
        ann = cls(str(d.get("semantic_class", "")), parts, constraints, str(d.get("variant", "")), dict(d.get("meta", {})))
        validate(ann, source)
        return ann

    @classmethod
    def load(cls, path) -> "Annotation":
        from pathlib import Path

        p = Path(path)
        if not p.is_file():
            raise UserError(f"{p}: annotation file not found")
        d = read_json(p)
        return cls.from_dict(d, str(p))


def problems(ann: Annotation) -> list[str]:
    """Every reason the annotation is not acceptable (empty list when it is)."""
    out = []
    if not ann.parts:
        out.append("no parts")
    for name, pr in ann.parts.items():
        if pr.material not in materials.BY_NAME:
            out.append(f"part {name!r}: unknown material class {pr.material!r} (choose from {', '.join(materials.names())})")
        elif not materials.BY_NAME[pr.material].simulated:
            out.append(f"part {name!r}: material class {pr.material!r} carries no mass and cannot label a part")
        for q in QUANTITIES:
            lo, hi = pr.range(q)
            blo, bhi = _BOUNDS[q]
            if not (math.isfinite(lo) and math.isfinite(hi)):
                out.append(f"part {name!r}: {q} range [{lo}, {hi}] is not finite")
            elif lo > hi:
                out.append(f"part {name!r}: {q} range [{lo:g}, {hi:g}] is empty (min > max)")
            elif lo < blo or hi > bhi:
                out.append(f"part {name!r}: {q} range [{lo:g}, {hi:g}] leaves the physical bounds [{blo:g}, {bhi:g}]")
    for c in ann.constraints:
        unknown = [p for p in (c.greater, c.lesser) if p not in ann.parts]
        if unknown:
            out.append(f"constraint '{c.describe()}' names unknown part(s) {', '.join(map(repr, unknown))}")
            continue
        if not out and not c.holds(ann.parts):
            a = ann.parts[c.greater].range(c.quantity)
            b = ann.parts[c.lesser].range(c.quantity)
            out.append(f"constraint violated: {c.describe()} — {c.greater}.{c.quantity} = [{a[0]:.4g}, {a[1]:.4g}], "
                       f"{c.lesser}.{c.quantity} = [{b[0]:.4g}, {b[1]:.4g}]")
    return out


def validate(ann: Annotation, source: str = "annotation") -> Annotation:
    """Raise :class:`UserError` listing every problem of ``ann`` (see :func:`problems`); return it when fine."""
    found = problems(ann)
    if found:
        raise UserError(f"{source}: " + "; ".join(found))
    return ann


def channel(values, quantity: str) -> np.ndarray:
    """Physical values -> the channel the model and the metrics use: log10 for E and density, as is for ν."""
    v = np.asarray(values, np.float64)
    return np.log10(v) if quantity in LOG_QUANTITIES else v


def interpolate(lo, hi, alpha, quantity: str):
    """The label at ``alpha`` between ``lo`` (α = 0) and ``hi`` (α = 1); arrays broadcast.

    log10-linear for E and density, linear for ν (the model's channels are log10 E, log10 ρ, ν).
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    a = np.asarray(alpha, dtype=np.float64)
    if quantity in LOG_QUANTITIES:
        return 10.0 ** ((1.0 - a) * np.log10(lo) + a * np.log10(hi))
    return (1.0 - a) * lo + a * hi


def part_table(ann: Annotation) -> dict:
    """Per-part arrays in part order: ``E_min``, ``E_max`` (Pa), ``nu_min``, ``nu_max``, ``density_min``,
    ``density_max`` (kg/m³), all (P,) float64, and ``material`` (P,) int16 class ids."""
    names = ann.part_names
    out = {"material": np.array([materials.get(ann.parts[n].material).id for n in names], dtype=np.int16)}
    for q in QUANTITIES:
        out[f"{q}_min"] = np.array([ann.parts[n].range(q)[0] for n in names], dtype=np.float64)
        out[f"{q}_max"] = np.array([ann.parts[n].range(q)[1] for n in names], dtype=np.float64)
    return out


# =========================================================================== class priors (data)
@dataclass(frozen=True)
class PartPrior:
    """Where one part's ranges may fall.

    material: material-class name (registry).
    log10_E: (low, high) of the range *centre* in log10 Pa; log10_E_halfwidth: (low, high) decades.
    nu: (low, high) of the centre; nu_halfwidth: (low, high).
    density: (low, high) of the centre in kg/m³; density_rel_halfwidth: (low, high) fraction of the centre.
    The part's appearance code u ∈ [0, 1] places the E centre (and, less strongly, the density centre):
    centre = low + (high − low) · clip(u + N(0, 0.08)), so a part that *looks* stiffer *is* stiffer.
    """

    material: str
    log10_E: tuple
    log10_E_halfwidth: tuple
    nu: tuple
    nu_halfwidth: tuple
    density: tuple
    density_rel_halfwidth: tuple = (0.04, 0.12)


@dataclass(frozen=True)
class VariantPrior:
    """An appearance variant of a class (``"basketball"``) and how it shifts the part priors.

    weight: relative sampling frequency.  E_shift: part -> decades added to the E centre range.
    density_scale: part -> factor on the density centre range.  parts_absent: parts this variant lacks.
    """

    name: str
    weight: float = 1.0
    E_shift: Mapping = field(default_factory=dict)
    density_scale: Mapping = field(default_factory=dict)
    parts_absent: tuple = ()


@dataclass(frozen=True)
class ScenarioPrior:
    """The short clip every object of a class is simulated in (cross-solver ground truth).

    kind: ``"drop"`` (falls from ``drop_height`` × its height onto the ground, with a small random
    tilt velocity) or ``"anchored"`` (the ``pinned_part``'s bounding box is clamped; the rest gets a
    sideways push of ``push_speed`` m/s, then sways under gravity).
    """

    kind: str = "drop"
    drop_height: tuple = (0.15, 0.35)
    pinned_part: str = ""
    push_speed: tuple = (0.3, 0.8)


@dataclass(frozen=True)
class ClassPrior:
    """The class-level prior of one semantic class (parts in label-priority order: later parts win overlaps)."""

    name: str
    parts: Mapping
    variants: tuple
    constraints: tuple
    scenario: ScenarioPrior = ScenarioPrior()
    description: str = ""


def _pp(material, logE, logE_hw, nu, nu_hw, density, dens_hw=(0.04, 0.12)):
    return PartPrior(material, tuple(logE), tuple(logE_hw), tuple(nu), tuple(nu_hw), tuple(density), tuple(dens_hw))


def _c(q, a, b, kind="all", factor=1.0):
    return Constraint(q, a, b, kind, factor)


_PRIORS = (
    ClassPrior(
        "potted_plant",
        {"pot": _pp("stationary", (8.8, 9.6), (0.15, 0.3), (0.16, 0.24), (0.01, 0.03), (1700, 2300)),
         "soil": _pp("sand", (5.0, 6.2), (0.2, 0.4), (0.26, 0.32), (0.01, 0.02), (1100, 1500)),
         "leaves": _pp("jelly", (4.0, 5.2), (0.15, 0.35), (0.38, 0.45), (0.01, 0.03), (200, 500)),
         "trunk": _pp("jelly", (6.5, 7.7), (0.2, 0.4), (0.30, 0.38), (0.01, 0.03), (500, 900))},
        (VariantPrior("shrub", 1.0), VariantPrior("sapling", 1.0, {"trunk": 0.2, "leaves": -0.2}),
         VariantPrior("succulent", 0.6, {"leaves": 0.4}, {"leaves": 1.3})),
        (_c("E", "pot", "trunk"), _c("E", "trunk", "leaves"), _c("density", "pot", "soil"),
         _c("density", "trunk", "leaves", "mid")),
        ScenarioPrior("anchored", pinned_part="pot", push_speed=(0.4, 1.0)),
        "a plant in a pot: ceramic pot (held fixed), soil, woody trunk, leafy crown"),
    ClassPrior(
        "sport_ball",
        {"cover": _pp("jelly", (6.0, 7.0), (0.15, 0.3), (0.40, 0.47), (0.01, 0.02), (900, 1250)),
         "core": _pp("jelly", (4.3, 5.3), (0.15, 0.3), (0.30, 0.40), (0.01, 0.03), (40, 140))},
        (VariantPrior("soccer", 1.0), VariantPrior("basketball", 1.0, {"cover": 0.2, "core": 0.2}),
         VariantPrior("tennis", 0.8, {"cover": -0.2, "core": 0.2}, {"core": 2.5}),
         VariantPrior("volleyball", 0.8, {"cover": -0.2, "core": -0.1})),
        (_c("E", "cover", "core"), _c("density", "cover", "core")),
        ScenarioPrior("drop", drop_height=(0.3, 0.6)),
        "an inflated ball: stiff rubber or leather cover around a soft, light core"),
    ClassPrior(
        "stuffed_toy",
        {"body": _pp("jelly", (3.4, 4.5), (0.15, 0.3), (0.20, 0.32), (0.01, 0.03), (40, 160)),
         "limbs": _pp("jelly", (3.3, 4.4), (0.15, 0.3), (0.20, 0.32), (0.01, 0.03), (40, 160)),
         "head": _pp("jelly", (3.5, 4.6), (0.15, 0.3), (0.20, 0.32), (0.01, 0.03), (40, 180)),
         "ears": _pp("jelly", (3.3, 4.3), (0.15, 0.3), (0.20, 0.32), (0.01, 0.03), (40, 160)),
         "eyes": _pp("jelly", (7.3, 8.3), (0.15, 0.3), (0.34, 0.40), (0.01, 0.02), (1000, 1300))},
        (VariantPrior("bear", 1.0), VariantPrior("bunny", 1.0, {"body": -0.1, "ears": -0.2}),
         VariantPrior("cat", 0.8, {"body": 0.1})),
        (_c("E", "eyes", "head"), _c("E", "eyes", "body"), _c("density", "eyes", "body")),
        ScenarioPrior("drop", drop_height=(0.2, 0.5)),
        "a plush toy: fabric with fibre stuffing, hard plastic button eyes"),
    ClassPrior(
        "rubber_duck",
        {"body": _pp("jelly", (5.4, 6.5), (0.15, 0.3), (0.42, 0.47), (0.005, 0.02), (120, 320)),
         "head": _pp("jelly", (5.4, 6.5), (0.15, 0.3), (0.42, 0.47), (0.005, 0.02), (120, 320)),
         "beak": _pp("jelly", (6.5, 7.2), (0.15, 0.3), (0.42, 0.47), (0.005, 0.02), (900, 1200)),
         "eyes": _pp("jelly", (7.4, 8.3), (0.15, 0.3), (0.36, 0.42), (0.005, 0.02), (1000, 1300))},
        (VariantPrior("classic", 1.5), VariantPrior("squeaky_soft", 1.0, {"body": -0.5, "head": -0.5}),
         VariantPrior("vinyl_hard", 0.7, {"body": 0.3, "head": 0.3, "beak": 0.3})),
        (_c("E", "beak", "body", "mid"), _c("E", "eyes", "body"), _c("density", "beak", "body")),
        ScenarioPrior("drop", drop_height=(0.2, 0.5)),
        "a hollow rubber or vinyl bath toy"),
    ClassPrior(
        "jelly_pudding",
        {"plate": _pp("stationary", (9.6, 10.4), (0.1, 0.3), (0.20, 0.25), (0.01, 0.02), (2200, 2600)),
         "jelly": _pp("jelly", (2.6, 3.9), (0.15, 0.35), (0.45, 0.485), (0.003, 0.01), (1000, 1100)),
         "topping": _pp("fluid", (3.4, 4.4), (0.1, 0.3), (0.40, 0.46), (0.01, 0.02), (1150, 1400))},
        (VariantPrior("gelatin", 1.0), VariantPrior("panna_cotta", 1.0, {"jelly": 0.4}),
         VariantPrior("flan", 1.0, {"jelly": 0.2, "topping": -0.2}, {"topping": 1.05})),
        (_c("E", "plate", "jelly"), _c("density", "plate", "jelly"), _c("density", "topping", "jelly", "mid")),
        ScenarioPrior("anchored", pinned_part="plate", push_speed=(0.2, 0.5)),
        "a wobbling dessert on a plate (plate held fixed), with a sauce topping"),
    ClassPrior(
        "metal_tool",
        {"handle": _pp("jelly", (9.4, 10.1), (0.1, 0.25), (0.30, 0.36), (0.01, 0.02), (550, 850)),
         "body": _pp("metal", (10.6, 11.3), (0.05, 0.15), (0.28, 0.33), (0.005, 0.015), (2600, 7900)),
         "contents": _pp("fluid", (5.5, 6.5), (0.1, 0.3), (0.40, 0.46), (0.01, 0.02), (980, 1060))},
        (VariantPrior("hammer", 1.0, parts_absent=("contents",)),
         VariantPrior("can", 1.0, {"body": -0.2}, {"body": 0.36}, parts_absent=("handle",)),
         VariantPrior("wrench", 0.8, parts_absent=("handle", "contents"))),
        (_c("E", "body", "handle"), _c("density", "body", "handle"), _c("E", "body", "contents"),
         _c("density", "body", "contents")),
        ScenarioPrior("drop", drop_height=(0.2, 0.4)),
        "steel or aluminium: a hammer with a wooden handle, a filled can, a spanner"),
    ClassPrior(
        "sand_pile",
        {"sand": _pp("sand", (5.0, 6.4), (0.2, 0.4), (0.24, 0.32), (0.01, 0.02), (1350, 1800)),
         "pebbles": _pp("jelly", (9.3, 10.3), (0.1, 0.3), (0.20, 0.28), (0.01, 0.02), (2400, 2800))},
        (VariantPrior("dry", 1.0), VariantPrior("wet", 0.8, {"sand": 0.4}, {"sand": 1.12}),
         VariantPrior("fine", 0.8, {"sand": -0.3}, parts_absent=("pebbles",))),
        (_c("E", "pebbles", "sand"), _c("density", "pebbles", "sand")),
        ScenarioPrior("drop", drop_height=(0.05, 0.2)),
        "a heap of sand with a few pebbles"),
    ClassPrior(
        "snow_pile",
        {"snow": _pp("snow", (4.0, 5.4), (0.15, 0.35), (0.20, 0.30), (0.01, 0.02), (120, 480)),
         "ice": _pp("jelly", (8.6, 9.4), (0.1, 0.25), (0.30, 0.34), (0.005, 0.015), (880, 920)),
         "nose": _pp("jelly", (6.0, 6.9), (0.1, 0.3), (0.35, 0.42), (0.01, 0.02), (900, 1100)),
         "arms": _pp("jelly", (8.3, 9.3), (0.1, 0.25), (0.30, 0.36), (0.01, 0.02), (400, 700))},
        (VariantPrior("mound", 1.0, parts_absent=("nose", "arms")),
         VariantPrior("snowman", 1.0, {"snow": 0.3}, {"snow": 1.2}, parts_absent=("ice",))),
        (_c("E", "ice", "snow"), _c("density", "ice", "snow"), _c("E", "arms", "snow"), _c("E", "nose", "snow")),
        ScenarioPrior("drop", drop_height=(0.05, 0.2)),
        "a snow mound with ice chunks, or a snowman with a carrot nose and stick arms"),
    ClassPrior(
        "fruit",
        {"flesh": _pp("jelly", (5.5, 6.7), (0.15, 0.3), (0.30, 0.40), (0.01, 0.02), (780, 1020)),
         "core": _pp("jelly", (6.8, 7.4), (0.1, 0.25), (0.30, 0.38), (0.01, 0.02), (900, 1150)),
         "stem": _pp("jelly", (7.6, 8.6), (0.1, 0.3), (0.30, 0.36), (0.01, 0.02), (600, 900)),
         "leaf": _pp("jelly", (5.6, 6.4), (0.1, 0.3), (0.35, 0.42), (0.01, 0.02), (500, 800))},
        (VariantPrior("apple", 1.0), VariantPrior("orange", 1.0, {"flesh": -0.4}, {"flesh": 1.05}, ("leaf",)),
         VariantPrior("pear", 0.8, {"flesh": -0.1}), VariantPrior("plum", 0.8, {"flesh": -0.6}, parts_absent=("leaf",))),
        (_c("E", "stem", "flesh"), _c("E", "core", "flesh", "mid"), _c("density", "core", "leaf", "mid")),
        ScenarioPrior("drop", drop_height=(0.3, 0.6)),
        "a fruit: flesh around a firmer core, woody stem, thin leaf"),
    ClassPrior(
        "wooden_furniture",
        {"legs": _pp("jelly", (9.5, 10.2), (0.1, 0.25), (0.30, 0.38), (0.01, 0.02), (500, 850)),
         "seat": _pp("jelly", (9.4, 10.1), (0.1, 0.25), (0.30, 0.38), (0.01, 0.02), (500, 850)),
         "backrest": _pp("jelly", (9.3, 10.0), (0.1, 0.25), (0.30, 0.38), (0.01, 0.02), (450, 800)),
         "cushion": _pp("jelly", (3.5, 4.6), (0.15, 0.3), (0.15, 0.30), (0.01, 0.03), (25, 90))},
        (VariantPrior("chair", 1.0), VariantPrior("stool", 0.8, parts_absent=("backrest",)),
         VariantPrior("padded_chair", 0.8, {"legs": -0.2, "seat": -0.2, "backrest": -0.2})),
        (_c("E", "legs", "cushion"), _c("E", "seat", "cushion"), _c("density", "seat", "cushion")),
        ScenarioPrior("drop", drop_height=(0.05, 0.15)),
        "a wooden chair or stool, sometimes with a foam cushion"),
)

CLASS_PRIORS: Mapping[str, ClassPrior] = MappingProxyType({p.name: p for p in _PRIORS})
"""Semantic class name -> its prior, in a fixed order (the dataset cycles through it)."""
SEMANTIC_CLASSES: tuple = tuple(CLASS_PRIORS)


def class_prior(name: str) -> ClassPrior:
    try:
        return CLASS_PRIORS[name]
    except KeyError:
        raise UserError(f"unknown semantic class {name!r}; choose one of: {', '.join(SEMANTIC_CLASSES)}") from None


def variant_prior(prior: ClassPrior, variant: str) -> VariantPrior:
    for v in prior.variants:
        if v.name == variant:
            return v
    raise UserError(f"class {prior.name!r} has no variant {variant!r}; choose one of: "
                    f"{', '.join(v.name for v in prior.variants)}")


def choose_variant(prior: ClassPrior, rng: np.random.Generator) -> str:
    w = np.array([v.weight for v in prior.variants], dtype=np.float64)
    return prior.variants[int(rng.choice(len(w), p=w / w.sum()))].name


def parts_of(prior: ClassPrior, variant: str) -> list[str]:
    """The parts of ``variant``, in label-priority order."""
    absent = set(variant_prior(prior, variant).parts_absent)
    return [p for p in prior.parts if p not in absent]


def check_priors(priors: Mapping[str, ClassPrior] = CLASS_PRIORS) -> list[str]:
    """Consistency of the prior data itself (materials known, ranges ordered, constraints name parts)."""
    out = []
    for name, cp in priors.items():
        for pname, pp in cp.parts.items():
            if pp.material not in materials.BY_NAME:
                out.append(f"{name}.{pname}: unknown material {pp.material!r}")
            for key in ("log10_E", "log10_E_halfwidth", "nu", "nu_halfwidth", "density", "density_rel_halfwidth"):
                lo, hi = getattr(pp, key)
                if not lo <= hi:
                    out.append(f"{name}.{pname}.{key}: ({lo}, {hi}) is not ordered")
        for c in cp.constraints:
            for p in (c.greater, c.lesser):
                if p not in cp.parts:
                    out.append(f"{name}: constraint names unknown part {p!r}")
        for v in cp.variants:
            for p in list(v.E_shift) + list(v.density_scale) + list(v.parts_absent):
                if p not in cp.parts:
                    out.append(f"{name}.{v.name}: names unknown part {p!r}")
        if cp.scenario.kind == "anchored" and cp.scenario.pinned_part not in cp.parts:
            out.append(f"{name}: pinned part {cp.scenario.pinned_part!r} is not a part")
        for v in cp.variants:  # at the middle of the prior with the widest ranges, every constraint must hold
            names = [p for p in cp.parts if p not in v.parts_absent]
            ranges = {p: _middle_part(cp.parts[p], v, p) for p in names}
            for c in cp.constraints:
                if c.greater in ranges and c.lesser in ranges and not c.holds(ranges):
                    out.append(f"{name}.{v.name}: constraint '{c.describe()}' fails at the middle of the prior")
    return out


def _middle_part(pp: PartPrior, vp: VariantPrior, part: str) -> PartRange:
    c = 0.5 * (pp.log10_E[0] + pp.log10_E[1]) + float(vp.E_shift.get(part, 0.0))
    hw = pp.log10_E_halfwidth[1]
    dc = float(vp.density_scale.get(part, 1.0)) * 0.5 * (pp.density[0] + pp.density[1])
    nu_c = 0.5 * (pp.nu[0] + pp.nu[1])
    dhw = pp.density_rel_halfwidth[1] * dc
    return PartRange(pp.material, (10 ** (c - hw), 10 ** (c + hw)), (nu_c - pp.nu_halfwidth[1], nu_c + pp.nu_halfwidth[1]),
                     (dc - dhw, dc + dhw))


def _draw_part(pp: PartPrior, vp: VariantPrior, part: str, u: float, rng: np.random.Generator,
               pull: float = 0.0) -> PartRange:
    """One part's ranges; ``pull`` ∈ [0, 1] moves the appearance code towards the prior's middle."""
    u = 0.5 + (1.0 - pull) * (u - 0.5)
    pos = float(np.clip(u + (1.0 - pull) * rng.normal(0.0, 0.08), 0.0, 1.0))
    shift = float(vp.E_shift.get(part, 0.0))
    c = pp.log10_E[0] + shift + pos * (pp.log10_E[1] - pp.log10_E[0])
    hw = rng.uniform(*pp.log10_E_halfwidth)
    E = (10.0 ** (c - hw), 10.0 ** (c + hw))
    nu_c = rng.uniform(*pp.nu)
    nu_hw = rng.uniform(*pp.nu_halfwidth)
    nu = (max(nu_c - nu_hw, NU_BOUNDS[0]), min(nu_c + nu_hw, NU_BOUNDS[1]))
    dpos = float(np.clip(0.5 * u + 0.5 * rng.uniform(), 0.0, 1.0))
    scale = float(vp.density_scale.get(part, 1.0))
    dc = scale * (pp.density[0] + dpos * (pp.density[1] - pp.density[0]))
    dhw = rng.uniform(*pp.density_rel_halfwidth) * dc
    return PartRange(pp.material, (float(E[0]), float(E[1])), (float(nu[0]), float(nu[1])),
                     (float(dc - dhw), float(dc + dhw)))


def sample_annotation(semantic_class: str, variant: str, appearance: Mapping[str, float], rng: np.random.Generator,
                      max_tries: int = 200) -> Annotation:
    """Draw the annotation of one object of ``semantic_class`` / ``variant``.

    appearance: part -> appearance code u ∈ [0, 1] (the same number that set the part's colour).
    Ranges that break a constraint are re-drawn (at most ``max_tries`` times, then :class:`UserError`);
    over the second half of the tries the codes are pulled gradually towards 0.5 (the middle of the
    prior), where :func:`check_priors` guarantees the constraints can hold.  Constraints naming parts
    the variant lacks are dropped.
    """
    prior = class_prior(semantic_class)
    vp = variant_prior(prior, variant)
    names = parts_of(prior, variant)
    missing = [p for p in names if p not in appearance]
    if missing:
        raise UserError(f"no appearance code for part(s) {', '.join(missing)} of {semantic_class}/{variant}")
    cons = [c for c in prior.constraints if c.greater in names and c.lesser in names]
    for attempt in range(max_tries):
        pull = max(0.0, (attempt - max_tries / 2) / (max_tries / 2 - 1)) if max_tries > 2 else 0.0
        parts = {p: _draw_part(prior.parts[p], vp, p, float(appearance[p]), rng, min(pull, 1.0)) for p in names}
        ann = Annotation(semantic_class, parts, list(cons), variant, {"draws": attempt + 1})
        if not problems(ann):
            return ann
    raise UserError(f"could not draw ranges for {semantic_class}/{variant} satisfying its constraints in "
                    f"{max_tries} tries: the prior data contradict the constraints")


def constraints_from_text(lines: Sequence[str]) -> list[Constraint]:
    """Several assert-form constraints (one per item) -> :class:`Constraint` records (see :func:`parse_constraint`)."""
    return [parse_constraint(t) for t in lines if t.strip()]
