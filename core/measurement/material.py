"""The material the model believes for a measured solid (:class:`MeasuredMaterial`) and the check of its values.

Owns Young's modulus, Poisson's ratio and density as stated by a measurement (homogeneous or per tracked point),
their range check (:func:`check_material_values`) and the conversion to the solvers' material types.  It may use
:mod:`unipixie.core.errors` and, inside functions, :mod:`unipixie.solvers` (the material registry and samplers);
never the other modules of this package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import UserError


@dataclass
class MeasuredMaterial:
    """The material the model currently believes for the measured solid.

    E: Pa, nu: -, density: kg/m³ — each a float (homogeneous) or an (N,) array (per tracked point).
    material_class: registry name of the material class (``"jelly"`` by default).
    """

    E: Any
    nu: Any
    density: Any
    material_class: str = "jelly"

    @property
    def homogeneous(self) -> bool:
        return all(np.ndim(v) == 0 for v in (self.E, self.nu, self.density))

    def scaled(self, E_scale: float) -> "MeasuredMaterial":
        """A copy with Young's modulus multiplied by ``E_scale``."""
        E = float(self.E) * E_scale if np.ndim(self.E) == 0 else np.asarray(self.E) * E_scale
        return MeasuredMaterial(E, self.nu, self.density, self.material_class)

    def mean_E(self) -> float:
        return float(np.mean(self.E))

    def mean_density(self) -> float:
        return float(np.mean(self.density))

    def to_spec(self, rest_positions: np.ndarray):
        """The solver-side material: ``HomogeneousMaterial`` or ``PointMaterial`` over the rest positions."""
        from ...solvers.material_sampling import HomogeneousMaterial, PointMaterial
        from ...solvers import materials

        cls_id = materials.get(self.material_class).id
        if self.homogeneous:
            return HomogeneousMaterial(float(self.E), float(self.nu), float(self.density), cls_id)
        n = len(rest_positions)
        arr = {k: np.broadcast_to(np.asarray(getattr(self, k), dtype=np.float64), (n,)).copy()
               for k in ("E", "nu", "density")}
        return PointMaterial(rest_positions, arr["E"], arr["nu"], arr["density"], np.full(n, cls_id, dtype=np.int32))

    def to_dict(self) -> dict:
        """JSON-able summary (per-point fields as mean/min/max)."""
        out: dict[str, Any] = {"material_class": self.material_class}
        for k in ("E", "nu", "density"):
            v = getattr(self, k)
            if np.ndim(v) == 0:
                out[k] = float(v)
            else:
                a = np.asarray(v, dtype=np.float64)
                out[k] = {"mean": float(a.mean()), "min": float(a.min()), "max": float(a.max()), "per_point": True}
        return out


def check_material_values(E, nu, density, where: str) -> None:
    E = np.asarray(E, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    density = np.asarray(density, dtype=np.float64)
    if not (np.all(np.isfinite(E)) and np.all(E > 0)):
        raise UserError(f"{where} 'E' must be a positive number of pascals")
    if not (np.all(np.isfinite(nu)) and np.all((nu > -1.0) & (nu < 0.5))):
        raise UserError(f"{where} 'nu' must lie in (-1, 0.5)")
    if not (np.all(np.isfinite(density)) and np.all(density > 0)):
        raise UserError(f"{where} 'density' must be a positive number of kg/m³")

