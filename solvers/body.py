"""The solid handed to a solver: its shape and the points whose motion is reported."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..core.errors import UserError


@dataclass
class Body:
    """A solid to simulate.

    mesh: a closed, outward-oriented ``trimesh.Trimesh`` (metres), or ``None``.
    points: (S, 3) metres — the solid as a particle set when there is no mesh (each point
        stands for ``point_volume`` m³ of material), or ``None``.
    point_volume: m³ per point of ``points`` (``None``: estimated from the points' spacing).
    tracked_points: (N, 3) metres — points whose motion the solver reports (defaults to the
        mesh's vertices, else ``points``).
    warnings: what was repaired or assumed while building the body (shown to the user).
    """

    mesh: object = None
    points: Optional[np.ndarray] = None
    point_volume: Optional[float] = None
    tracked_points: Optional[np.ndarray] = None
    warnings: list = field(default_factory=list)

    def __post_init__(self):
        if self.mesh is None and self.points is None:
            raise UserError("a body needs a closed mesh or a set of points")
        if self.points is not None:
            self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
            if len(self.points) == 0 or not np.all(np.isfinite(self.points)):
                raise UserError("the body's points are empty or contain NaN/inf")
        if self.tracked_points is None:
            self.tracked_points = (np.asarray(self.mesh.vertices, dtype=np.float64) if self.mesh is not None
                                   else self.points.copy())
        self.tracked_points = np.asarray(self.tracked_points, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(self.tracked_points)):
            raise UserError("tracked points contain NaN/inf")

    @classmethod
    def from_mesh(cls, mesh, tracked_points: np.ndarray | None = None, repair: bool = True) -> "Body":
        """A body from a triangle mesh; open or badly oriented meshes are repaired where possible.

        Raises :class:`UserError` for a mesh with no faces, zero volume, or NaN vertices; a mesh
        that stays open after repair is used through its surface shell with a warning.
        """
        import trimesh

        if not isinstance(mesh, trimesh.Trimesh):
            raise UserError(f"expected a triangle mesh, got {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise UserError("the mesh has no faces")
        if not np.all(np.isfinite(mesh.vertices)):
            raise UserError("the mesh has NaN or infinite vertex positions")
        warnings: list[str] = []
        m = mesh.copy()
        if repair:
            before = len(m.faces)
            m.update_faces(m.nondegenerate_faces())
            m.remove_unreferenced_vertices()
            if len(m.faces) < before:
                warnings.append(f"removed {before - len(m.faces)} zero-area faces")
            if len(m.faces) == 0:
                raise UserError("the mesh has only zero-area faces")
            if not m.is_watertight:
                trimesh.repair.fill_holes(m)
            trimesh.repair.fix_normals(m)
            if not m.is_watertight:
                warnings.append("the mesh is not closed; its inside is taken from the surface shell (winding), "
                                "which may be approximate")
            elif m.volume < 0:
                m.invert()
        extent = float(np.max(m.extents))
        if extent <= 0:
            raise UserError("the mesh has zero size")
        return cls(mesh=m, tracked_points=tracked_points, warnings=warnings)

    @property
    def rest_points(self) -> np.ndarray:
        """Points that describe the solid's extent: ``points`` or the mesh's vertices."""
        return self.points if self.points is not None else np.asarray(self.mesh.vertices, dtype=np.float64)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds in metres of the solid and the tracked points."""
        pts = np.concatenate([self.rest_points, self.tracked_points])
        return np.stack([pts.min(0), pts.max(0)])
