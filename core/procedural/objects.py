"""A generated object and its parts: :class:`ProceduralObject` (parts in label-priority order, the annotation,
the scenario) and :class:`Part` (named closed components and their appearance).

Owns what an object offers its users: the ``.glb`` export (one named mesh and one PBR material per part, through
:mod:`.textures`), voxel labels on a grid, solid sample points and surface points (where parts overlap, the later
part wins).  May use :mod:`.appearance`, :mod:`.textures`, the core's grid and annotation types and
:mod:`unipixie.core.lift` (imported when called).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..annotation import Annotation
from ..errors import UserError
from ..types import GridGeometry
from .appearance import Appearance
from .textures import textured_mesh

Z_UP_TO_GLTF = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
"""Our z-up metres → glTF's y-up (x, y, z) ↦ (x, z, −y); Blender's importer turns it back to z-up."""


@dataclass
class Part:
    """A named part: closed trimesh components (metres) and their appearance."""

    name: str
    components: list
    appearance: Appearance
    rest: list | None = None
    """The components' rest shapes when ``components`` are deformed (textures stay attached to the rest shape)."""

    def mesh(self):
        """All components concatenated (closed, possibly self-overlapping between components)."""
        import trimesh

        return trimesh.util.concatenate(self.components)


@dataclass
class ProceduralObject:
    """One generated object.

    object_id: ``"000007_fruit"``; semantic_class / variant: from :mod:`unipixie.core.annotation`;
    parts: in label-priority order (later parts win overlaps); annotation: the per-part ranges;
    scenario: the :class:`unipixie.solvers.scenario.Scenario` of its ground-truth clip (world metres).
    """

    object_id: str
    index: int
    seed: int
    semantic_class: str
    variant: str
    parts: list
    annotation: Annotation
    scenario: object
    meta: dict = field(default_factory=dict)

    @property
    def part_names(self) -> list:
        return [p.name for p in self.parts]

    def mesh(self):
        """Every part's components as one trimesh (for bounds and viewing; overlaps are not resolved)."""
        import trimesh

        return trimesh.util.concatenate([c for p in self.parts for c in p.components])

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 metres."""
        verts = np.concatenate([np.asarray(c.vertices) for p in self.parts for c in p.components])
        return np.stack([verts.min(0), verts.max(0)])

    # ---------------------------------------------------------------- export
    def export_glb(self, path, frame_box=None) -> Path:
        """Write the object as binary glTF (y-up as the format says; z-up again once imported into Blender):
        one mesh node named after each part, with one textured PBR material.

        frame_box: optional (2, 3) metres; two tiny tetrahedra (edge 1/2000 of the box diagonal) are added at its
        corners so that renders of differently deformed copies share one normalisation (the renderer fits
        the subject's bounding box into its cameras).
        """
        import trimesh

        scene = trimesh.Scene()
        for part in self.parts:
            mesh = textured_mesh(part, self.seed * 1000003 + self.index)
            mesh.apply_transform(Z_UP_TO_GLTF)
            scene.add_geometry(mesh, node_name=part.name, geom_name=part.name)
        if frame_box is not None:
            box = np.asarray(frame_box, dtype=np.float64).reshape(2, 3)
            edge = 5e-4 * float(np.linalg.norm(box[1] - box[0]))
            for k, corner in enumerate(box):
                tet = trimesh.creation.icosphere(subdivisions=0, radius=edge)
                tet.apply_translation(corner)
                tet.apply_transform(Z_UP_TO_GLTF)
                scene.add_geometry(tet, node_name=f"frame_marker_{k}", geom_name=f"frame_marker_{k}")
        data = trimesh.exchange.gltf.export_glb(scene, include_normals=True)
        from ..atomic_io import write_bytes

        return write_bytes(path, data)

    def vertices(self) -> np.ndarray:
        """(V, 3) float64 metres: every component's vertices, parts and components in order."""
        return np.concatenate([np.asarray(c.vertices, np.float64) for p in self.parts for c in p.components])

    def with_vertices(self, vertices: np.ndarray) -> "ProceduralObject":
        """A copy whose components have the given (V, 3) vertex positions (order of :meth:`vertices`), e.g. a
        simulated frame; faces, parts and appearance are unchanged."""
        import trimesh

        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != (sum(len(c.vertices) for p in self.parts for c in p.components), 3):
            raise UserError(f"{self.object_id}: {v.shape} vertex positions do not match the object's vertices")
        parts, at = [], 0
        for p in self.parts:
            comps = []
            for c in p.components:
                n = len(c.vertices)
                comps.append(trimesh.Trimesh(v[at:at + n], np.asarray(c.faces), process=False))
                at += n
            parts.append(Part(p.name, comps, p.appearance, p.rest or p.components))
        return ProceduralObject(self.object_id, self.index, self.seed, self.semantic_class, self.variant, parts,
                                self.annotation, self.scenario, dict(self.meta))

    # ---------------------------------------------------------------- voxels and samples
    def voxel_labels(self, geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
        """Occupancy of the union of the parts on ``geometry`` (metres) and the part of each occupied voxel.

        Each component is voxelised like the feature pipeline voxelises a closed mesh
        (:func:`unipixie.core.lift.occupancy_from_mesh`: voxel centres inside, plus the surface voxels
        of parts thinner than a voxel); later parts overwrite earlier ones.
        Returns occupancy (R, R, R) bool and part_ids (K,) int16 in ``np.argwhere(occupancy)`` order.
        """
        from ..lift import occupancy_from_mesh

        R = geometry.resolution
        label = np.full((R, R, R), -1, dtype=np.int16)
        for pid, part in enumerate(self.parts):
            for comp in part.components:
                try:
                    occ = occupancy_from_mesh(comp, geometry).occupancy
                except UserError:
                    continue  # a component too small for this grid leaves no voxel
                label[occ] = pid
        occupancy = label >= 0
        if not occupancy.any():
            raise UserError(f"object {self.object_id}: no voxel of the {R}³ grid is occupied")
        return occupancy, label[occupancy]

    def fill(self, spacing: float, jitter: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Sample points filling the object's solid on a lattice of ``spacing`` metres.

        Returns points (P, 3) float64 metres and part (P,) int16 (later parts win overlaps).
        """
        lo, hi = self.bounds
        counts = np.maximum(np.ceil((hi - lo) / spacing).astype(np.int64), 1)
        if int(np.prod(counts)) > 30_000_000:
            raise UserError(f"filling {self.object_id} at {spacing:g} m needs {int(np.prod(counts)):,} lattice points")
        axes = [lo[d] + (np.arange(counts[d]) + 0.5) * spacing for d in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        if jitter > 0:
            grid = grid + np.random.default_rng(seed).uniform(-0.5, 0.5, grid.shape) * jitter * spacing
        label = np.full(len(grid), -1, dtype=np.int16)
        for pid, part in enumerate(self.parts):
            for comp in part.components:
                blo, bhi = comp.bounds
                sel = np.nonzero(np.all((grid >= blo) & (grid <= bhi), axis=1))[0]
                if len(sel):
                    label[sel[comp.contains(grid[sel])]] = pid
        keep = label >= 0
        if not keep.any():
            raise UserError(f"no sample point of spacing {spacing:g} m falls inside {self.object_id}")
        return grid[keep], label[keep]

    def surface_points(self, count: int, seed: int = 0) -> np.ndarray:
        """(count, 3) float64 points on the object's outer surface (tracked points of the ground truth).

        Points are drawn on every component's surface, area-weighted, and those lying inside another
        component are dropped (they are not on the union's surface); drawing continues until ``count``.
        """
        import trimesh

        comps = [c for p in self.parts for c in p.components]
        rng = np.random.default_rng(seed)
        out = []
        have = 0
        for _ in range(8):
            need = count - have
            if need <= 0:
                break
            pts, _ = trimesh.sample.sample_surface(self.mesh(), max(2 * need, 64), seed=int(rng.integers(2**31)))
            pts = np.asarray(pts)
            buried = np.zeros(len(pts), dtype=bool)
            for c in comps:
                blo, bhi = c.bounds
                sel = np.nonzero(np.all((pts >= blo) & (pts <= bhi), axis=1))[0]
                if len(sel):
                    # inside another component by more than a hair: push the point slightly inwards along -n
                    buried[sel] |= _strictly_inside(c, pts[sel])
            pts = pts[~buried]
            out.append(pts)
            have += len(pts)
        pts = np.concatenate(out)
        if len(pts) < count:
            raise UserError(f"{self.object_id}: could not draw {count} surface points")
        return pts[:count]


def _strictly_inside(mesh, pts: np.ndarray) -> np.ndarray:
    """Points farther than 1e-6 m inside ``mesh`` (points on its own surface are not)."""
    from trimesh.proximity import signed_distance

    inside = mesh.contains(pts)
    if not inside.any():
        return inside
    d = signed_distance(mesh, pts[inside])  # positive inside
    res = np.zeros(len(pts), dtype=bool)
    res[np.nonzero(inside)[0][d > 1e-6 * max(1.0, float(mesh.scale))]] = True
    return res
