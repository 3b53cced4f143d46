"""Material given to a solver, and its lookup at the solver's sample points.

A solver receives one of:

* :class:`HomogeneousMaterial` — one (E, ν, density, class) for the whole solid;
* :class:`PointMaterial` — values at scattered points (e.g. a measurement's per-point
  field), looked up by nearest point;
* :class:`~unipixie.core.types.MaterialField` — the model's per-voxel field, looked up
  by nearest occupied voxel or trilinear interpolation (log E and log ρ interpolated
  in log space).

:func:`sample_material` turns any of them into per-sample arrays, vectorised
(one KD-tree query for all points, never one call per particle).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np

from ..core.errors import UserError
from ..core.types import MaterialField
from . import materials


@dataclass
class SampledMaterial:
    """Per-sample material: E (S,) Pa, nu (S,), density (S,) kg/m³, material (S,) int32 class ids."""

    E: np.ndarray
    nu: np.ndarray
    density: np.ndarray
    material: np.ndarray

    def __post_init__(self):
        self.E = np.asarray(self.E, dtype=np.float64)
        self.nu = np.asarray(self.nu, dtype=np.float64)
        self.density = np.asarray(self.density, dtype=np.float64)
        self.material = np.asarray(self.material, dtype=np.int32)
        n = self.E.shape[0]
        for k in ("nu", "density", "material"):
            if getattr(self, k).shape != (n,):
                raise ValueError(f"SampledMaterial.{k} must have shape ({n},)")

    def __len__(self) -> int:
        return int(self.E.shape[0])

    def lame(self, E_scale: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Lamé parameters (μ, λ) in Pa, with E optionally multiplied per sample."""
        E = self.E if E_scale is None else self.E * E_scale
        mu = E / (2.0 * (1.0 + self.nu))
        lam = E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        return mu, lam


@dataclass
class HomogeneousMaterial:
    """One material for the whole solid: E Pa, nu, density kg/m³, material class (name or id)."""

    E: float
    nu: float
    density: float
    material: Union[int, str] = "jelly"

    def __post_init__(self):
        self.E = float(self.E)
        self.nu = float(self.nu)
        self.density = float(self.density)
        if not (np.isfinite(self.E) and self.E > 0):
            raise UserError(f"Young's modulus E must be a positive number of pascals, got {self.E!r}")
        if self.E > materials.E_REFUSE:
            raise UserError(f"Young's modulus E = {self.E:.3g} Pa is stiffer than any solid (diamond: 1.2e12 Pa): "
                            "give it in pascals (steel 2e11)")
        if not (-1.0 < self.nu < 0.5):
            raise UserError(f"Poisson's ratio nu must lie in (-1, 0.5), got {self.nu!r}")
        if not (np.isfinite(self.density) and self.density > 0):
            raise UserError(f"density must be a positive number of kg/m³, got {self.density!r}")
        if self.density > materials.DENSITY_REFUSE:
            raise UserError(f"density {self.density:.3g} kg/m³ is denser than any solid (osmium: 22 590 kg/m³): give it "
                            "in kg/m³ (water 1000)")
        self.material = materials.get(self.material).id


@dataclass
class PointMaterial:
    """Material values at scattered points (nearest-point lookup).

    points: (M, 3) metres; E, nu, density: (M,); material: (M,) class ids (default jelly).
    """

    points: np.ndarray
    E: np.ndarray
    nu: np.ndarray
    density: np.ndarray
    material: np.ndarray | None = None

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        m = len(self.points)
        for k in ("E", "nu", "density"):
            arr = np.asarray(getattr(self, k), dtype=np.float64).reshape(-1)
            if arr.shape != (m,):
                raise UserError(f"per-point material '{k}' must have one value per point ({m}), got {arr.shape}")
            setattr(self, k, arr)
        if self.material is None:
            self.material = np.zeros(m, dtype=np.int32)
        self.material = np.asarray(self.material, dtype=np.int32).reshape(-1)
        if np.any(self.E <= 0) or np.any(self.density <= 0) or np.any((self.nu <= -1) | (self.nu >= 0.5)):
            raise UserError("per-point material has non-positive E/density or nu outside (-1, 0.5)")


MaterialSpec = Union[HomogeneousMaterial, PointMaterial, MaterialField]


def sample_material(material: MaterialSpec, points: np.ndarray, mode: str = "nearest") -> SampledMaterial:
    """Material at (S, 3) sample points.

    mode: ``"nearest"`` (nearest occupied voxel / point) or ``"trilinear"`` (voxel fields only:
    trilinear interpolation of log E, ν, log ρ over the occupied voxels of the 2×2×2
    neighbourhood, class by nearest voxel).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if isinstance(material, HomogeneousMaterial):
        return SampledMaterial(np.full(n, material.E), np.full(n, material.nu), np.full(n, material.density),
                               np.full(n, material.material))
    from scipy.spatial import cKDTree

    if isinstance(material, PointMaterial):
        _, idx = cKDTree(material.points).query(pts)
        return SampledMaterial(material.E[idx], material.nu[idx], material.density[idx], material.material[idx])
    if isinstance(material, MaterialField):
        ind = material.indices
        if len(ind) == 0:
            raise UserError("the material field has no occupied voxels")
        centres = material.geometry.centres(ind)
        _, near = cKDTree(centres).query(pts)
        cls = material.material[near].astype(np.int32)
        if mode == "nearest":
            return SampledMaterial(material.E[near], material.nu[near], material.density[near], cls)
        if mode != "trilinear":
            raise UserError(f"unknown material sampling mode {mode!r}; use 'nearest' or 'trilinear'")
        geo = material.geometry
        R = geo.resolution
        lookup = -np.ones((R, R, R), dtype=np.int64)
        lookup[tuple(ind.T)] = np.arange(len(ind))
        u = (pts - geo.origin) / geo.voxel_size - 0.5
        base = np.floor(u).astype(np.int64)
        frac = u - base
        logE = np.log(material.E.astype(np.float64))
        logR = np.log(material.density.astype(np.float64))
        nu = material.nu.astype(np.float64)
        acc = np.zeros((n, 3))
        wsum = np.zeros(n)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    c = base + np.array([dx, dy, dz])
                    w = (np.where(dx, frac[:, 0], 1 - frac[:, 0]) * np.where(dy, frac[:, 1], 1 - frac[:, 1])
                         * np.where(dz, frac[:, 2], 1 - frac[:, 2]))
                    inside = np.all((c >= 0) & (c < R), axis=1)
                    k = np.full(n, -1, dtype=np.int64)
                    k[inside] = lookup[tuple(c[inside].T)]
                    ok = k >= 0
                    w = np.where(ok, w, 0.0)
                    kk = np.where(ok, k, 0)
                    acc += w[:, None] * np.stack([logE[kk], nu[kk], logR[kk]], axis=1)
                    wsum += w
        fallback = wsum <= 1e-12
        acc[fallback] = np.stack([logE[near], nu[near], logR[near]], axis=1)[fallback]
        wsum[fallback] = 1.0
        acc /= wsum[:, None]
        return SampledMaterial(np.exp(acc[:, 0]), acc[:, 1], np.exp(acc[:, 2]), cls)
    raise UserError(f"unsupported material specification: {type(material).__name__}")
