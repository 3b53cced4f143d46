"""The object of a bake as plain arrays and the solid a solver gets from it.

* :class:`BakeObject` — a mesh object as arrays: rest vertices in the object's local space (Blender units),
  triangles, ``matrix_world`` and the scene's unit scale; it converts between local coordinates and world metres.
* :func:`build_body` — the :class:`~unipixie.solvers.body.Body` a solver needs, with the checks a user needs
  (empty mesh, open mesh, zero-area faces, absurd sizes: :func:`check_size`) as
  :class:`~unipixie.core.errors.UserError` or warnings.

Units: world positions are metres; Blender-local positions are Blender units (metres divided by the scene's
unit scale, in the object's own frame).  Uses numpy, trimesh, :mod:`unipixie.solvers.body` and
:mod:`unipixie.core.errors`; nothing else of the bake.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import UserError


SIZE_WARN_RANGE = (1e-3, 1e3)
"""Objects whose largest world extent (m) falls outside this range get a warning (real-world physics)."""
SIZE_REFUSE_RANGE = (1e-6, 1e5)
"""Outside this range (m) the bake is refused: almost certainly a unit or scale mistake."""


@dataclass
class BakeObject:
    """A Blender mesh object as plain arrays.

    name: the object's name.
    rest_local: (N, 3) float64 rest vertex positions in the object's local space (Blender units).
    triangles: (F, 3) int64 vertex indices of the triangulated faces.
    matrix_world: (4, 4) float64 the object's world matrix (Blender units).
    unit_scale: metres per Blender unit (the scene's unit scale).
    properties: the object's bake settings as plain values (material, etc.; free-form).
    """

    name: str
    rest_local: np.ndarray
    triangles: np.ndarray
    matrix_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    unit_scale: float = 1.0
    properties: dict = field(default_factory=dict)

    def __post_init__(self):
        self.rest_local = np.asarray(self.rest_local, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        self.matrix_world = np.asarray(self.matrix_world, dtype=np.float64).reshape(4, 4)
        self.unit_scale = float(self.unit_scale)
        if len(self.rest_local) == 0:
            raise UserError(f"object '{self.name}': the mesh has no vertices")
        if len(self.triangles) == 0:
            raise UserError(f"object '{self.name}': the mesh has no faces (only loose vertices or edges); "
                            "a solid needs a closed surface")
        if not np.all(np.isfinite(self.rest_local)):
            raise UserError(f"object '{self.name}': the mesh has NaN or infinite vertex positions")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.rest_local):
            raise UserError(f"object '{self.name}': face indices out of range")
        if not (np.isfinite(self.unit_scale) and self.unit_scale > 0):
            raise UserError(f"the scene's unit scale must be positive, got {self.unit_scale!r}")
        if not np.all(np.isfinite(self.matrix_world)):
            raise UserError(f"object '{self.name}': its transform contains NaN/inf")
        det = float(np.linalg.det(self.matrix_world[:3, :3]))
        if abs(det) < 1e-30:
            raise UserError(f"object '{self.name}' has a zero scale on some axis (its transform is singular); "
                            "set its scale to non-zero values")

    @property
    def vertex_count(self) -> int:
        return int(self.rest_local.shape[0])

    @property
    def world_from_local(self) -> np.ndarray:
        """(4, 4) float64: Blender-local coordinates → world metres."""
        s = np.diag([self.unit_scale] * 3 + [1.0])
        return s @ self.matrix_world

    @property
    def local_from_world(self) -> np.ndarray:
        """(4, 4) float64: world metres → Blender-local coordinates."""
        return np.linalg.inv(self.world_from_local)

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """(..., 3) local (Blender units) → (..., 3) float64 world metres."""
        m = self.world_from_local
        return np.asarray(local, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]

    def to_local(self, world: np.ndarray) -> np.ndarray:
        """(..., 3) world metres → (..., 3) float64 local Blender units."""
        m = self.local_from_world
        return np.asarray(world, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]

    @property
    def rest_world(self) -> np.ndarray:
        """(N, 3) float64 rest vertex positions in world metres."""
        return self.to_world(self.rest_local)

    @property
    def size(self) -> float:
        """Largest extent of the world-space bounding box, metres."""
        w = self.rest_world
        return float(np.max(w.max(0) - w.min(0)))


def check_size(obj: BakeObject) -> list[str]:
    """Refuse absurd sizes, warn about unusual ones (returns the warnings)."""
    size = obj.size
    lo, hi = SIZE_REFUSE_RANGE
    if size <= 0:
        raise UserError(f"object '{obj.name}' has zero size (all its vertices coincide)")
    if size < lo or size > hi:
        raise UserError(f"object '{obj.name}' is {size:.3g} m across in the world, outside the range UniPixie "
                        f"simulates ({lo:g} m to {hi:g} m): check the object's scale and the scene's unit scale "
                        "(Scene Properties > Units)")
    wlo, whi = SIZE_WARN_RANGE
    if size < wlo or size > whi:
        return [f"object '{obj.name}' is {size:.3g} m across: the physics is simulated at this real-world size "
                "(object scale and scene unit scale applied); if that is not intended, change the scale"]
    return []


def build_body(obj: BakeObject, solver: str = "mpm", repair: bool = True):
    """The solid to simulate: a closed world-space mesh whose vertices are the tracked points.

    Returns ``(body, warnings)``.  Zero-area faces are removed and small holes filled (with a
    warning); a mesh that stays open after repair is refused (every solver fills the inside of
    the surface with material), with a message that says how to close it.
    """
    import trimesh

    from ...solvers.body import Body

    warnings = check_size(obj)
    world = obj.rest_world
    mesh = trimesh.Trimesh(vertices=world, faces=obj.triangles, process=False)
    area = mesh.area_faces
    if not np.any(area > 0):
        raise UserError(f"object '{obj.name}': every face has zero area (the mesh is flat to a line or point)")
    body = Body.from_mesh(mesh, tracked_points=world, repair=repair)
    open_note = [w for w in body.warnings if "not closed" in w]
    if open_note:
        boundary, non_manifold = _edge_defects(body.mesh)
        what = (f"open ({boundary} boundary edges remain after filling holes)" if boundary else
                f"not a closed surface ({non_manifold} edges are shared by more than two faces, or it is flat)")
        raise UserError(f"object '{obj.name}': the mesh is {what}, so it has no inside for the {solver} solver to "
                        "fill with material; close it (Edit Mode > Select All > Mesh > Clean Up > Fill Holes / "
                        "Merge by Distance, or add a Solidify modifier and apply it)")
    if float(body.mesh.volume) <= 0:
        raise UserError(f"object '{obj.name}': the closed mesh encloses no volume")
    return body, warnings + [f"object '{obj.name}': {w}" for w in body.warnings]


def _edge_defects(mesh) -> tuple[int, int]:
    """(boundary edges, edges shared by more than two faces) of a triangle mesh."""
    edges = np.sort(mesh.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int(np.sum(counts == 1)), int(np.sum(counts > 2))
