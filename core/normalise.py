"""The normalised unit cube every object is looked at in, and the way back to world space.

Rendering, feature lifting and the model all work on the object *normalised*:
the centre of its world-space axis-aligned bounding box at the origin and its
largest extent scaled to 1, so it spans ``[-0.5, 0.5]`` along its longest axis.
The model's input and output grids are ``GRID_RESOLUTION``³ voxels over
``[-0.5, 0.5]³`` (:func:`unit_cube_grid`).

:class:`Normalisation` holds that similarity transform (uniform scale and
translation, no rotation, so axis-aligned grids stay axis-aligned) and maps
points, 4×4 matrices and :class:`~.types.GridGeometry` both ways.  A
``MaterialField`` predicted in the normalised cube is handed to the solvers in
world space with :meth:`Normalisation.field_to_world`.

    norm = Normalisation.from_points(mesh_vertices_world)        # metres
    grid_world = norm.geometry_to_world(unit_cube_grid())        # GridGeometry in metres
    field_world = norm.field_to_world(predicted_field)           # same data, world geometry
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import UserError
from .types import GridGeometry

GRID_RESOLUTION = 64
"""Voxels per axis of the model's grids (paper §3.1: 64³)."""

CUBE_HALF_EXTENT = 0.5
"""The normalised cube is ``[-CUBE_HALF_EXTENT, CUBE_HALF_EXTENT]³`` (edge 1, normalised units)."""


def unit_cube_grid(resolution: int = GRID_RESOLUTION) -> GridGeometry:
    """The ``resolution``³ grid over the normalised cube ``[-0.5, 0.5]³`` (voxel edge ``1 / resolution``)."""
    resolution = int(resolution)
    if resolution <= 0:
        raise UserError(f"grid resolution must be positive, got {resolution}")
    return GridGeometry(resolution=resolution, origin=np.full(3, -CUBE_HALF_EXTENT),
                        voxel_size=2.0 * CUBE_HALF_EXTENT / resolution)


@dataclass(frozen=True)
class Normalisation:
    """World space (metres) ↔ normalised cube (dimensionless): ``x_n = (x_w - centre) / scale``.

    centre: (3,) float64 metres, centre of the object's world-space bounding box.
    scale: float, metres per normalised unit (the bounding box's largest extent).
    """

    centre: tuple
    scale: float

    def __post_init__(self):
        centre = tuple(float(c) for c in np.asarray(self.centre, dtype=np.float64).reshape(3))
        object.__setattr__(self, "centre", centre)
        object.__setattr__(self, "scale", float(self.scale))
        if not (np.all(np.isfinite(centre)) and np.isfinite(self.scale) and self.scale > 0):
            raise UserError(f"invalid normalisation: centre {centre}, scale {self.scale} m (the object is empty, "
                            "flat to a point, or has NaN/inf coordinates)")

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_bounds(cls, bounds) -> "Normalisation":
        """From a (2, 3) world-space bounding box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in metres."""
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape != (2, 3) or not np.all(np.isfinite(b)):
            raise UserError(f"bounds must be a finite (2, 3) array, got shape {b.shape}")
        extent = float(np.max(b[1] - b[0]))
        if extent <= 0:
            raise UserError("the object has zero size (all its vertices coincide); nothing to normalise")
        return cls(centre=0.5 * (b[0] + b[1]), scale=extent)

    @classmethod
    def from_points(cls, points) -> "Normalisation":
        """From (N, 3) world-space points in metres (e.g. mesh vertices)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            raise UserError("cannot normalise an object without vertices")
        if not np.all(np.isfinite(p)):
            raise UserError("the object has NaN or infinite vertex positions")
        return cls.from_bounds(np.stack([p.min(axis=0), p.max(axis=0)]))

    @classmethod
    def from_matrix(cls, matrix) -> "Normalisation":
        """From the 4×4 world-to-normalised matrix (as stored in ``Views.normalisation``)."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise UserError(f"normalisation matrix must be 4×4, got {m.shape}")
        s = m[0, 0]
        if not (s > 0 and np.allclose(m[:3, :3], np.eye(3) * s, rtol=1e-9, atol=1e-12)
                and np.allclose(m[3], [0, 0, 0, 1])):
            raise UserError("normalisation matrix is not a uniform scale plus translation")
        scale = 1.0 / s
        return cls(centre=-m[:3, 3] * scale, scale=scale)

    @classmethod
    def identity(cls) -> "Normalisation":
        return cls(centre=(0.0, 0.0, 0.0), scale=1.0)

    # -- matrices -------------------------------------------------------------------------------
    @property
    def to_normalised_matrix(self) -> np.ndarray:
        """(4, 4) float64 world (m) → normalised."""
        m = np.eye(4)
        m[:3, :3] /= self.scale
        m[:3, 3] = -np.asarray(self.centre) / self.scale
        return m

    @property
    def to_world_matrix(self) -> np.ndarray:
        """(4, 4) float64 normalised → world (m)."""
        m = np.eye(4) * self.scale
        m[3, 3] = 1.0
        m[:3, 3] = self.centre
        return m

    # -- points ---------------------------------------------------------------------------------
    def to_normalised(self, points) -> np.ndarray:
        """(..., 3) world points in metres → (..., 3) float64 normalised points."""
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.centre)) / self.scale

    def to_world(self, points) -> np.ndarray:
        """(..., 3) normalised points → (..., 3) float64 world points in metres."""
        return np.asarray(points, dtype=np.float64) * self.scale + np.asarray(self.centre)

    def lengths_to_world(self, lengths):
        """Normalised lengths → metres."""
        return np.asarray(lengths, dtype=np.float64) * self.scale

    # -- grids ----------------------------------------------------------------------------------
    def geometry_to_world(self, geometry: GridGeometry) -> GridGeometry:
        """A grid given in normalised units → the same grid in world metres."""
        return GridGeometry(resolution=geometry.resolution, origin=self.to_world(geometry.origin),
                            voxel_size=geometry.voxel_size * self.scale)

    def geometry_to_normalised(self, geometry: GridGeometry) -> GridGeometry:
        """A grid given in world metres → the same grid in normalised units."""
        return GridGeometry(resolution=geometry.resolution, origin=self.to_normalised(geometry.origin),
                            voxel_size=geometry.voxel_size / self.scale)

    def field_to_world(self, grid_data):
        """A copy of a ``FeatureGrid`` / ``MaterialField`` (anything with ``geometry``) whose geometry is
        in world metres; the per-voxel data are unchanged (the voxels are the same)."""
        return dataclasses.replace(grid_data, geometry=self.geometry_to_world(grid_data.geometry),
                                   meta={**getattr(grid_data, "meta", {}), "space": "world"})

    def field_to_normalised(self, grid_data):
        """Inverse of :meth:`field_to_world`."""
        return dataclasses.replace(grid_data, geometry=self.geometry_to_normalised(grid_data.geometry),
                                   meta={**getattr(grid_data, "meta", {}), "space": "normalised"})

    # -- serialisation ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"centre": list(self.centre), "scale": self.scale}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalisation":
        try:
            return cls(centre=d["centre"], scale=d["scale"])
        except (KeyError, TypeError) as exc:
            raise UserError(f"normalisation record lacks {exc}; expected keys 'centre' and 'scale'") from None

    @classmethod
    def of(cls, grid_data) -> "Normalisation":
        """The normalisation recorded in a ``FeatureGrid``'s (or ``MaterialField``'s) ``meta["normalisation"]``."""
        meta = getattr(grid_data, "meta", {}) or {}
        if "normalisation" not in meta:
            raise UserError("this grid records no normalisation (meta['normalisation']); it was not made by "
                            "'unipixie features' or has lost its metadata")
        return cls.from_dict(meta["normalisation"])
