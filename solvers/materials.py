"""The material-class registry: the one definition of material classes.

Used by the model (number and order of class logits), the solvers
(constitutive law and plasticity per class), the dataset (priors), and the UI
(enum items, colours).  The ids are the model's class-logit indices; do not
reorder them (checkpoints depend on it) — add new classes at the end.

Constitutive laws (MPM):

* ``fixed_corotated``: Ψ = μ‖F − R‖² + λ/2 (J − 1)² (Stomakhin et al. 2012).
* ``stvk_hencky``: St. Venant–Kirchhoff on the Hencky strain ε = log Σ,
  Ψ = μ tr(ε²) + λ/2 tr(ε)²; used with von Mises (metal) and Drucker–Prager (sand).
* ``weakly_compressible``: pressure only, p = K (1 − J) ≥ 0 with bulk modulus
  K = E / (3 (1 − 2ν)) (fluid); the deviatoric part is reset every step and J is capped
  at 1 (a free-surface fluid carries no tension).

Plasticity (return mapping on the singular values of the elastic deformation gradient):

* ``von_mises``: deviatoric Hencky strain capped so the Kirchhoff deviatoric stress
  stays below ``yield_stress``; ``softening`` > 0 lowers the yield stress with the
  accumulated plastic strain (plasticine).
* ``drucker_prager``: cohesionless sand with ``friction_angle_deg`` (Klár et al. 2016).
* ``snow``: singular values clamped to [1 − θc, 1 + θs], hardening
  exp(ξ (1 − Jp)) of μ and λ (Stomakhin et al. 2013).  Unlike PhysGaussian's snow,
  the elastic stress is kept (fixed-corotated with hardened Lamé parameters).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

from ..core.errors import UserError


DENSITY_REFUSE = 1e5
"""kg/m³: no solid is denser than this (4× osmium's 22 590): a stated density above it is a unit mistake, refused."""
E_REFUSE = 1e13
"""Pa: no solid is stiffer than this (8× diamond's 1.2e12): a stated Young's modulus above it is refused."""


@dataclass(frozen=True)
class MaterialClass:
    """One material class.

    id: stable integer id (the model's class-logit index).
    name: identifier used in files, the CLI and the API.
    label: human-readable name for the UI.
    elasticity: constitutive law (see module docstring).
    plasticity: return-mapping model (``"none"`` for purely elastic).
    params: class-specific constants, SI units (``yield_stress`` Pa, ``friction_angle_deg`` degrees,
        ``theta_c``/``theta_s``/``hardening`` dimensionless, ``softening`` dimensionless).
    simulated: False for classes that carry no mass in the solvers (background).
    held_fixed: True for classes whose material is kinematically fixed (stationary).
    colour: linear RGB for UI legends.
    typical_E / typical_nu / typical_density: plausible (low, high) ranges (Pa, -, kg/m³), used
        as dataset priors and UI slider limits.
    """

    id: int
    name: str
    label: str
    elasticity: str
    plasticity: str
    params: Mapping[str, float] = field(default_factory=dict)
    simulated: bool = True
    held_fixed: bool = False
    colour: tuple = (0.8, 0.8, 0.8)
    typical_E: tuple = (1e4, 1e7)
    typical_nu: tuple = (0.2, 0.45)
    typical_density: tuple = (100.0, 3000.0)
    description: str = ""

    def param(self, key: str) -> float:
        try:
            return float(self.params[key])
        except KeyError:
            raise KeyError(f"material class {self.name!r} has no parameter {key!r}") from None


_CLASSES = (
    MaterialClass(0, "jelly", "Jelly / elastic", "fixed_corotated", "none", {},
                  colour=(0.95, 0.45, 0.55), typical_E=(1e3, 1e7), typical_nu=(0.3, 0.49), typical_density=(500, 1500),
                  description="rubber, jelly, foam, leaves: purely elastic (fixed-corotated)"),
    MaterialClass(1, "metal", "Metal", "stvk_hencky", "von_mises", {"yield_stress": 2.0e8},
                  colour=(0.62, 0.66, 0.72), typical_E=(5e9, 2.5e11), typical_nu=(0.25, 0.35), typical_density=(2500, 9000),
                  description="elasto-plastic: StVK on Hencky strain with von Mises yield"),
    MaterialClass(2, "sand", "Sand / granular", "stvk_hencky", "drucker_prager", {"friction_angle_deg": 35.0},
                  colour=(0.93, 0.79, 0.45), typical_E=(1e5, 5e7), typical_nu=(0.2, 0.35), typical_density=(1400, 2000),
                  description="cohesionless granular: Drucker-Prager return mapping"),
    MaterialClass(3, "plasticine", "Plasticine / clay", "stvk_hencky", "von_mises",
                  {"yield_stress": 5.0e3, "softening": 0.5},
                  colour=(0.55, 0.75, 0.40), typical_E=(1e4, 1e7), typical_nu=(0.3, 0.45), typical_density=(1200, 2000),
                  description="von Mises with softening: deforms permanently under moderate load"),
    MaterialClass(4, "fluid", "Fluid", "weakly_compressible", "none", {},
                  colour=(0.30, 0.55, 0.95), typical_E=(1e4, 1e6), typical_nu=(0.3, 0.45), typical_density=(800, 1200),
                  description="weakly compressible fluid: pressure from volume change only"),
    MaterialClass(5, "snow", "Snow", "fixed_corotated", "snow",
                  {"theta_c": 2.5e-2, "theta_s": 7.5e-3, "hardening": 10.0},
                  colour=(0.92, 0.95, 1.0), typical_E=(1e4, 1e6), typical_nu=(0.2, 0.35), typical_density=(100, 600),
                  description="fixed-corotated with Stomakhin hardening and singular-value clamps"),
    MaterialClass(6, "stationary", "Stationary", "fixed_corotated", "none", {}, held_fixed=True,
                  colour=(0.35, 0.35, 0.35), typical_E=(1e8, 1e11), typical_nu=(0.2, 0.35), typical_density=(500, 8000),
                  description="held fixed at its rest position (walls, pots glued to the ground)"),
    MaterialClass(7, "background", "Background / empty", "fixed_corotated", "none", {}, simulated=False,
                  colour=(0.0, 0.0, 0.0), typical_E=(1e3, 1e3), typical_nu=(0.3, 0.3), typical_density=(1.0, 1.0),
                  description="not part of the object; carries no mass"),
)

MATERIAL_CLASSES: tuple[MaterialClass, ...] = _CLASSES
"""All classes, ordered by id."""

BY_NAME: Mapping[str, MaterialClass] = MappingProxyType({c.name: c for c in _CLASSES})
BY_ID: Mapping[int, MaterialClass] = MappingProxyType({c.id: c for c in _CLASSES})
NUM_CLASSES: int = len(_CLASSES)
ELASTICITY_MODELS = ("fixed_corotated", "stvk_hencky", "weakly_compressible")
PLASTICITY_MODELS = ("none", "von_mises", "drucker_prager", "snow")

assert [c.id for c in _CLASSES] == list(range(NUM_CLASSES)), "material ids must be 0..n-1 in order"


def get(key) -> MaterialClass:
    """Look a class up by name (``"jelly"``) or id (``0``); a :class:`UserError` names the valid choices."""
    if isinstance(key, MaterialClass):
        return key
    if isinstance(key, str):
        k = key.strip().lower()
        if k.isdigit():
            key = int(k)
        elif k in BY_NAME:
            return BY_NAME[k]
        else:
            raise UserError(f"unknown material class {key!r}; choose one of: {', '.join(BY_NAME)}")
    try:
        return BY_ID[int(key)]
    except (KeyError, ValueError, TypeError):
        raise UserError(f"unknown material class id {key!r}; valid ids are 0..{NUM_CLASSES - 1}") from None


def names() -> list[str]:
    return [c.name for c in _CLASSES]


def blender_enum_items() -> list[tuple[str, str, str]]:
    """Items for a Blender ``EnumProperty`` (identifier, label, description)."""
    return [(c.name, c.label, c.description) for c in _CLASSES if c.simulated]


def elastic_p_wave_per_e(nu):
    """P-wave modulus per unit E of an isotropic elastic solid, (λ + 2μ)/E = (1−ν)/((1+ν)(1−2ν)) (``nu``: Poisson's
    ratio, a number or array-like; returns float64 of its shape)."""
    import numpy as np

    nu = np.asarray(nu, np.float64)
    return (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))


def p_wave_factor(nu, material_ids):
    """Modulus that sets the solver's wave speed, per unit E: (1−ν)/((1+ν)(1−2ν)) (P-wave,
    :func:`elastic_p_wave_per_e`), or 1/(3(1−2ν)) (bulk) for weakly compressible classes (``nu``: Poisson's ratio,
    ``material_ids``: class ids; array-likes whose shapes broadcast; returns a float64 array).  The wave speed is
    sqrt(E · factor / ρ)."""
    import numpy as np

    nu = np.asarray(nu, np.float64)
    weak = np.array([c.elasticity == "weakly_compressible" for c in MATERIAL_CLASSES])[
        np.asarray(material_ids, np.int64)]
    return np.where(weak, 1.0 / (3.0 * (1.0 - 2.0 * nu)), elastic_p_wave_per_e(nu))
