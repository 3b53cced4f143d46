"""Procedural objects for the dataset: ten semantic classes made of named, textured parts.

Every object is built with trimesh from closed primitives (solids of
revolution, displaced ellipsoids, rods, boxes, annuli), in metres at a
realistic size, standing on (or lying on) the plane z = 0.  Its **parts**
(``"pot"``, ``"soil"``, ``"trunk"``, ``"leaves"``, ...) are the parts of the
class prior in :mod:`.annotation`; each part is one or more closed
*components* (a crown of leaf blobs, four chair legs).  The solid of the
object is the union of its parts; where parts overlap, the **later part in
the list wins** (a ball's core inside its cover, a trunk entering the crown).

Appearance carries information about the material: every part gets an
*appearance code* u ∈ [0, 1] that sets its colour between the palette's
"soft-looking" and "stiff-looking" colours and its texture's contrast and
frequency, and the same u places the part's stiffness range inside the prior
(:func:`.annotation.sample_annotation`).  Textures are procedural images
(noise, speckle, stripes, wood grain, brushed metal, panels, fur) baked into
one PNG per part and mapped with spherical, cylindrical or box UVs; the object
is exported as ``.glb`` with one named mesh and one PBR material per part, so
Blender renders it as it is.

Everything is a function of ``(seed, index)``: :func:`generate` is
deterministic.

    obj = generate(index=7, seed=0)                   # class by index, everything else seeded
    obj.export_glb("object.glb")
    occ, part_ids = obj.voxel_labels(geometry_world)   # union occupancy and part id per occupied voxel
    points, part_of_point = obj.fill(spacing=0.01)      # solid sample points (MPM particles)
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import UserError
from .types import GridGeometry
from . import annotation as ann_mod
from .annotation import Annotation

TEXTURE_SIZE = 128
"""Edge of each part's baked texture image in pixels."""
Z_UP_TO_GLTF = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
"""Our z-up metres → glTF's y-up (x, y, z) ↦ (x, z, −y); Blender's importer turns it back to z-up."""


# =========================================================================== parts and objects
@dataclass
class Appearance:
    """How one part looks.

    pattern: texture pattern name (see :data:`PATTERNS`).
    colour / secondary: sRGB in [0, 1] (base colour and the pattern's second colour).
    frequency: pattern features across the texture; contrast: 0 (plain) .. 1 (full).
    roughness / metallic: glTF PBR factors.  code: the appearance code u ∈ [0, 1].
    uv: ``"spherical"``, ``"cylindrical"`` or ``"box"`` projection.
    """

    pattern: str
    colour: tuple
    secondary: tuple
    frequency: float
    contrast: float
    roughness: float
    metallic: float
    code: float
    uv: str = "spherical"

    def to_dict(self) -> dict:
        return {"pattern": self.pattern, "colour": list(self.colour), "secondary": list(self.secondary),
                "frequency": self.frequency, "contrast": self.contrast, "roughness": self.roughness,
                "metallic": self.metallic, "code": self.code, "uv": self.uv}


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

    object_id: ``"000007_fruit"``; semantic_class / variant: from :mod:`.annotation`;
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
            mesh = _textured_mesh(part, self.seed * 1000003 + self.index)
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
        from .atomic_io import write_bytes

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
        from .lift import occupancy_from_mesh

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


# =========================================================================== geometry helpers
def _revolve(profile, sections: int = 40):
    """Closed solid of revolution about +z from a (r, z) profile running from the axis back to the axis."""
    import trimesh

    prof = np.asarray(profile, dtype=np.float64)
    prof[0, 0] = 0.0
    prof[-1, 0] = 0.0
    m = trimesh.creation.revolve(prof, sections=sections)
    if m.volume < 0:
        m.invert()
    return m


def _blob(centre, radii, rng, noise: float = 0.0, subdivisions: int = 3, waves: int = 4):
    """An ellipsoid (icosphere scaled by ``radii``) with smooth radial noise of relative amplitude ``noise``."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(m.vertices, dtype=np.float64)
    if noise > 0:
        d = np.zeros(len(v))
        for _ in range(waves):
            k = rng.normal(size=3)
            k *= rng.uniform(1.5, 3.5) / np.linalg.norm(k)
            d += np.sin(v @ k + rng.uniform(0, 2 * np.pi))
        v = v * (1.0 + noise * d / math.sqrt(waves))[:, None]
    v = v * np.asarray(radii, dtype=np.float64) + np.asarray(centre, dtype=np.float64)
    return trimesh.Trimesh(v, m.faces, process=False)


def _rod(p0, p1, radius, sections: int = 14):
    import trimesh

    return trimesh.creation.cylinder(radius=float(radius), segment=np.array([p0, p1], dtype=np.float64), sections=sections)


def _box(centre, extents, rotz: float = 0.0):
    import trimesh

    T = trimesh.transformations.rotation_matrix(rotz, [0, 0, 1])
    T[:3, 3] = centre
    return trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64), transform=T)


def _cone(base_centre, direction, radius, height, sections: int = 16):
    import trimesh

    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    m = trimesh.creation.cone(radius=float(radius), height=float(height), sections=sections)
    T = trimesh.geometry.align_vectors([0, 0, 1], d)
    T[:3, 3] = base_centre
    m.apply_transform(T)
    return m


def _displace_radial(mesh, rng, amp: float, waves: int = 5):
    """Scale x, y of each vertex by 1 + smooth noise of its angle and height (keeps a solid of revolution closed)."""
    import trimesh

    v = np.asarray(mesh.vertices, dtype=np.float64).copy()
    theta = np.arctan2(v[:, 1], v[:, 0])
    h = (v[:, 2] - v[:, 2].min()) / max(np.ptp(v[:, 2]), 1e-9)
    d = np.zeros(len(v))
    for _ in range(waves):
        d += np.sin(int(rng.integers(1, 6)) * theta + rng.uniform(0, 2 * np.pi) + rng.uniform(-3, 3) * h)
    v[:, :2] *= (1.0 + amp * d / math.sqrt(waves))[:, None]
    return trimesh.Trimesh(v, mesh.faces, process=False)


def _rest_on_ground(parts: dict) -> dict:
    """Translate every component so the whole object's lowest point is at z = 0 and it is centred in x, y."""
    verts = np.concatenate([np.asarray(c.vertices) for comps in parts.values() for c in comps])
    shift = np.array([-(verts[:, 0].min() + verts[:, 0].max()) / 2, -(verts[:, 1].min() + verts[:, 1].max()) / 2,
                      -verts[:, 2].min()])
    for comps in parts.values():
        for c in comps:
            c.apply_translation(shift)
    return parts


# =========================================================================== class geometry
def _potted_plant(rng, variant):
    H = rng.uniform(0.3, 1.0)
    hp = rng.uniform(0.2, 0.32) * H
    rt = rng.uniform(0.12, 0.2) * H
    rb = rng.uniform(0.6, 0.9) * rt
    lip = rng.uniform(1.0, 1.1)
    pot = _revolve([(0, 0), (rb, 0), (rt, 0.88 * hp), (rt * lip, 0.9 * hp), (rt * lip, hp), (0, hp)])
    ts = rng.uniform(0.02, 0.04) * H
    soil = _revolve([(0, hp - ts), (0.93 * rt, hp - ts), (0.93 * rt, hp + 0.4 * ts), (0, hp + 0.7 * ts)])
    z0 = hp
    leaves = []
    if variant == "succulent":
        rr = rng.uniform(0.03, 0.05) * H
        trunk = [_rod([0, 0, z0 - ts], [0, 0, z0 + 0.12 * H], rr)]
        n = int(rng.integers(6, 11))
        for i in range(n):
            a = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
            length = rng.uniform(0.18, 0.3) * H
            tilt = rng.uniform(0.5, 1.1)
            d = np.array([np.cos(a) * np.sin(tilt), np.sin(a) * np.sin(tilt), np.cos(tilt)])
            c = np.array([0, 0, z0 + 0.1 * H]) + d * length * 0.5
            m = _blob([0, 0, 0], [0.5 * length, 0.16 * length, 0.1 * length], rng, 0.05, 2)
            import trimesh

            R = trimesh.geometry.align_vectors([1, 0, 0], d)
            m.apply_transform(R)
            m.apply_translation(c)
            leaves.append(m)
    else:
        top = H
        crown_r = rng.uniform(0.18, 0.3) * H if variant == "shrub" else rng.uniform(0.12, 0.2) * H
        crown_z = top - crown_r
        rr = (rng.uniform(0.025, 0.045) if variant == "shrub" else rng.uniform(0.015, 0.03)) * H
        bend = rng.normal(0, 0.04, 2) * H
        mid = np.array([bend[0], bend[1], 0.5 * (z0 + crown_z)])
        tipz = crown_z + 0.3 * crown_r
        trunk = [_rod([0, 0, z0 - ts], mid, rr), _rod(mid, [bend[0] * 0.5, bend[1] * 0.5, tipz], rr * 0.8)]
        n = int(rng.integers(3, 8)) if variant == "shrub" else int(rng.integers(2, 5))
        centre = np.array([bend[0] * 0.5, bend[1] * 0.5, crown_z])
        for i in range(n):
            off = rng.normal(0, 0.45, 3) * crown_r * np.array([1, 1, 0.6])
            r = crown_r * rng.uniform(0.45, 0.75)
            leaves.append(_blob(centre + off, [r, r * rng.uniform(0.8, 1.2), r * rng.uniform(0.6, 0.9)], rng, 0.12, 2))
    return {"pot": [pot], "soil": [soil], "leaves": leaves, "trunk": trunk}


def _sport_ball(rng, variant):
    R = {"soccer": 0.11, "basketball": 0.12, "tennis": 0.0335, "volleyball": 0.105}[variant] * rng.uniform(0.95, 1.05)
    t = rng.uniform(0.1, 0.16) if variant == "tennis" else rng.uniform(0.06, 0.1)
    squash = rng.uniform(0.97, 1.0)
    cover = _blob([0, 0, 0], [R, R, R * squash], rng, 0.0, 3)
    core = _blob([0, 0, 0], [R * (1 - t), R * (1 - t), R * squash * (1 - t)], rng, 0.0, 3)
    return {"cover": [cover], "core": [core]}


def _stuffed_toy(rng, variant):
    S = rng.uniform(0.15, 0.45)
    bw = rng.uniform(0.22, 0.3) * S
    body = _blob([0, 0, 0.28 * S], [bw, bw * rng.uniform(0.8, 0.95), 0.28 * S], rng, 0.03, 3)
    hr = rng.uniform(0.17, 0.22) * S
    hz = 0.56 * S + 0.8 * hr
    head = _blob([0, 0, hz], [hr, hr * 0.95, hr * 0.92], rng, 0.03, 3)
    limbs = []
    lr = rng.uniform(0.06, 0.085) * S
    for s in (-1, 1):
        limbs.append(_blob([s * (bw + 0.3 * lr), 0.02 * S, 0.38 * S], [lr * 1.1, lr, 0.17 * S], rng, 0.02, 2))
        limbs.append(_blob([s * 0.45 * bw, -0.6 * bw, 0.07 * S], [lr * 1.1, 0.19 * S, lr * 1.0], rng, 0.02, 2))
    ears = []
    for s in (-1, 1):
        if variant == "bunny":
            ears.append(_blob([s * 0.45 * hr, 0, hz + hr * 1.4], [0.28 * hr, 0.14 * hr, 0.8 * hr], rng, 0.02, 2))
        elif variant == "cat":
            ears.append(_cone([s * 0.55 * hr, 0, hz + 0.6 * hr], [s * 0.3, 0, 1], 0.35 * hr, 0.6 * hr))
        else:
            ears.append(_blob([s * 0.7 * hr, 0, hz + 0.75 * hr], [0.3 * hr, 0.15 * hr, 0.3 * hr], rng, 0.0, 2))
    er = rng.uniform(0.08, 0.12) * hr
    eyes = [_blob([s * 0.38 * hr, -0.86 * hr, hz + 0.2 * hr], [er, er, er], rng, 0.0, 2) for s in (-1, 1)]
    eyes.append(_blob([0, -0.97 * hr, hz - 0.12 * hr], [1.3 * er, er, er], rng, 0.0, 2))
    return {"body": [body], "limbs": limbs, "head": [head], "ears": ears, "eyes": eyes}


def _rubber_duck(rng, variant):
    L = rng.uniform(0.07, 0.2)
    bh = rng.uniform(0.26, 0.32) * L
    body = _blob([0, 0, bh], [0.5 * L, 0.38 * L, bh], rng, 0.04, 3)
    tail = _blob([0.42 * L, 0, 1.45 * bh], [0.12 * L, 0.12 * L, 0.14 * L], rng, 0.0, 2)
    hr = rng.uniform(0.2, 0.25) * L
    hc = np.array([-0.22 * L, 0, 1.75 * bh + 0.6 * hr])
    head = _blob(hc, [hr, hr, hr], rng, 0.02, 3)
    beak = _blob(hc + np.array([-0.95 * hr, 0, -0.15 * hr]), [0.45 * hr, 0.4 * hr, 0.15 * hr], rng, 0.0, 2)
    er = 0.12 * hr
    eyes = [_blob(hc + np.array([-0.7 * hr, s * 0.45 * hr, 0.35 * hr]), [er, er, er], rng, 0.0, 1) for s in (-1, 1)]
    return {"body": [body, tail], "head": [head], "beak": [beak], "eyes": eyes}


def _jelly_pudding(rng, variant):
    h = rng.uniform(0.05, 0.12)
    rb = rng.uniform(0.45, 0.7) * h
    rt = rb * (rng.uniform(0.6, 0.85) if variant != "panna_cotta" else rng.uniform(0.85, 1.0))
    Rp = rb * rng.uniform(1.5, 2.1)
    tp = rng.uniform(0.05, 0.1) * h
    plate = _revolve([(0, 0), (0.8 * Rp, 0), (Rp, tp), (0.95 * Rp, 1.2 * tp), (0, 1.0 * tp)])
    z0 = 0.95 * tp
    jelly = _revolve([(0, z0), (rb, z0), (0.5 * (rb + rt) * 1.03, z0 + 0.5 * h), (rt, z0 + 0.95 * h),
                      (0.6 * rt, z0 + h), (0, z0 + h)], 48)
    if variant == "gelatin":
        jelly = _displace_radial(jelly, rng, 0.05, 4)
        top = _blob([0, 0, z0 + h], [0.45 * rt, 0.45 * rt, 0.3 * rt], rng, 0.1, 2)
    else:
        th = rng.uniform(0.08, 0.15) * h
        top = _revolve([(0, z0 + h - th), (rt * 1.02, z0 + h - th), (rt * 1.04, z0 + h + 0.2 * th), (0, z0 + h + 0.3 * th)], 48)
    return {"plate": [plate], "jelly": [jelly], "topping": [top]}


def _metal_tool(rng, variant):
    if variant == "hammer":
        Lh = rng.uniform(0.25, 0.35)
        r = rng.uniform(0.012, 0.018)
        handle = _rod([0, 0, r], [Lh, 0, r], r, 16)
        hl = rng.uniform(0.09, 0.13)
        hw = rng.uniform(0.022, 0.03)
        head = _box([Lh + 0.3 * hw, 0, hw / 2], [hw * 1.6, hl, hw])
        face = _rod([Lh + 0.3 * hw, -0.5 * hl, hw / 2], [Lh + 0.3 * hw, -0.62 * hl, hw / 2], 0.45 * hw, 16)
        return {"handle": [handle], "body": [head, face]}
    if variant == "can":
        R = rng.uniform(0.028, 0.042)
        H = R * rng.uniform(2.5, 4.0)
        t = rng.uniform(0.08, 0.12) * R
        body = _revolve([(0, 0), (0.9 * R, 0), (R, 0.06 * H), (R, 0.94 * H), (0.9 * R, H), (0, H)], 40)
        contents = _revolve([(0, t), (0.9 * R - t, t), (R - t, 0.07 * H), (R - t, 0.93 * H), (0.9 * R - t, H - t),
                             (0, H - t)], 40)
        return {"body": [body], "contents": [contents]}
    L = rng.uniform(0.15, 0.25)
    w = rng.uniform(0.13, 0.17) * L
    th = rng.uniform(0.07, 0.1) * L
    import trimesh

    shaft = _box([0, 0, th / 2], [L, w, th])
    ring = trimesh.creation.annulus(r_min=0.7 * w, r_max=1.25 * w, height=th, sections=24)
    ring.apply_translation([-L / 2 - w, 0, th / 2])
    jaw = _box([L / 2 + w, 0, th / 2], [2.2 * w, 2.2 * w, th])
    return {"body": [shaft, ring, jaw]}


def _sand_pile(rng, variant):
    R = rng.uniform(0.1, 0.35)
    h = rng.uniform(0.3, 0.6) * R
    zs = np.linspace(0, h, 9)
    rs = R * np.sqrt(np.clip(-np.log(np.clip(zs / h, 1e-3, 1.0)) / 5.0, 0, 1)) + 1e-4
    prof = [(0, 0)] + [(float(r), float(z)) for r, z in zip(rs, zs)][:-1] + [(0, h)]
    sand = _displace_radial(_revolve(prof, 48), rng, 0.06, 5)
    pebbles = []
    if variant != "fine":
        for _ in range(int(rng.integers(2, 6))):
            a = rng.uniform(0, 2 * np.pi)
            rr = rng.uniform(0.2, 0.75) * R
            z = np.interp(rr, rs[::-1], zs[::-1])
            pr = rng.uniform(0.05, 0.1) * R
            pebbles.append(_blob([rr * np.cos(a), rr * np.sin(a), max(z - 0.3 * pr, pr * 0.6)],
                                 [pr, pr * rng.uniform(0.7, 1.0), pr * 0.7], rng, 0.1, 2))
    return {"sand": [sand], "pebbles": pebbles} if pebbles else {"sand": [sand]}


def _snow_pile(rng, variant):
    if variant == "snowman":
        S = rng.uniform(0.5, 1.2)
        r1, r2, r3 = S * rng.uniform(0.19, 0.23), S * rng.uniform(0.14, 0.17), S * rng.uniform(0.1, 0.12)
        z1 = 0.9 * r1
        z2 = z1 + 0.85 * (r1 + r2)
        z3 = z2 + 0.85 * (r2 + r3)
        snow = [_blob([0, 0, z1], [r1, r1, 0.92 * r1], rng, 0.03, 3), _blob([0, 0, z2], [r2, r2, r2], rng, 0.03, 3),
                _blob([0, 0, z3], [r3, r3, r3], rng, 0.02, 3)]
        nose = [_cone([0, -0.85 * r3, z3], [0, -1, -0.1], 0.18 * r3, rng.uniform(0.6, 1.0) * r3)]
        arms = []
        for s in (-1, 1):
            p0 = np.array([s * 0.6 * r2, 0, z2 + 0.2 * r2])
            p1 = p0 + np.array([s * rng.uniform(0.9, 1.3) * r2, rng.normal(0, 0.2) * r2, rng.uniform(0.3, 0.8) * r2])
            arms.append(_rod(p0, p1, 0.06 * r2, 10))
        return {"snow": snow, "nose": nose, "arms": arms}
    R = rng.uniform(0.15, 0.5)
    h = rng.uniform(0.35, 0.7) * R
    snow = _blob([0, 0, 0.0], [R, R * rng.uniform(0.75, 1.0), h], rng, 0.08, 3, waves=6)
    v = np.asarray(snow.vertices).copy()
    v[:, 2] = np.maximum(v[:, 2], 0.0)  # flat base: squash the lower half onto the ground
    import trimesh

    snow = trimesh.Trimesh(v, snow.faces, process=True)
    snow.update_faces(snow.nondegenerate_faces())
    snow.remove_unreferenced_vertices()
    if not snow.is_watertight:
        snow = _revolve([(0, 0), (R, 0), (0.7 * R, 0.6 * h), (0, h)], 40)
    ice = []
    for _ in range(int(rng.integers(1, 4))):
        a = rng.uniform(0, 2 * np.pi)
        rr = rng.uniform(0.2, 0.6) * R
        cr = rng.uniform(0.1, 0.18) * R
        ice.append(_blob([rr * np.cos(a), rr * np.sin(a), max(0.6 * h * (1 - (rr / R) ** 2), cr)], [cr, 0.8 * cr, 0.7 * cr],
                         rng, 0.2, 1))
    return {"snow": [snow], "ice": ice}


def _fruit(rng, variant):
    if variant == "orange":
        R = rng.uniform(0.035, 0.05)
        flesh = _blob([0, 0, R * 0.95], [R, R, 0.95 * R], rng, 0.015, 3)
        H = 1.9 * R
    elif variant == "plum":
        R = rng.uniform(0.022, 0.03)
        flesh = _blob([0, 0, R * 1.1], [R, 0.9 * R, 1.1 * R], rng, 0.01, 3)
        H = 2.2 * R
    else:
        R = rng.uniform(0.035, 0.05)
        H = R * (rng.uniform(1.7, 1.9) if variant == "apple" else rng.uniform(2.3, 2.7))
        zs = np.linspace(0, 1, 12)
        if variant == "apple":
            rs = R * np.sin(np.pi * np.clip(zs * 0.96 + 0.02, 0, 1)) ** 0.6 * (1 + 0.08 * zs)
        else:
            rs = R * (0.55 + 0.45 * np.exp(-((zs - 0.3) / 0.3) ** 2)) * np.sin(np.pi * np.clip(zs * 0.96 + 0.02, 0, 1)) ** 0.5
        prof = [(0, 0.04 * H)] + [(float(r), float(z * H)) for r, z in zip(rs[1:-1], zs[1:-1])] + [(0, H * 0.96)]
        flesh = _displace_radial(_revolve(prof, 40), rng, 0.02, 3)
    cz = 0.5 * flesh.bounds[1][2]
    cr = rng.uniform(0.25, 0.35) * R
    core = _blob([0, 0, cz], [cr, cr, 1.4 * cr], rng, 0.0, 2)
    top = flesh.bounds[1][2]
    sl = rng.uniform(0.2, 0.35) * R
    lean = rng.normal(0, 0.25, 2) * sl
    stem = _rod([0, 0, top - 0.3 * sl], [lean[0], lean[1], top + sl], rng.uniform(0.05, 0.08) * R, 10)
    out = {"flesh": [flesh], "core": [core], "stem": [stem]}
    if variant in ("apple", "pear"):
        ll = rng.uniform(0.5, 0.8) * R
        a = rng.uniform(0, 2 * np.pi)
        c = np.array([np.cos(a) * 0.5 * ll, np.sin(a) * 0.5 * ll, top + 0.6 * sl])
        leaf = _blob([0, 0, 0], [0.5 * ll, 0.22 * ll, 0.06 * ll], rng, 0.0, 2)
        leaf.apply_transform(_rotz(a))
        leaf.apply_translation(c)
        out["leaf"] = [leaf]
    return out


def _rotz(a):
    import trimesh

    return trimesh.transformations.rotation_matrix(a, [0, 0, 1])


def _wooden_furniture(rng, variant):
    W = rng.uniform(0.36, 0.5)
    D = W * rng.uniform(0.85, 1.05)
    hs = rng.uniform(0.42, 0.48) if variant != "stool" else rng.uniform(0.45, 0.7)
    ts = rng.uniform(0.025, 0.045)
    lw = rng.uniform(0.03, 0.045)
    round_legs = rng.uniform() < 0.5
    legs = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (W / 2 - lw), sy * (D / 2 - lw)
            if round_legs:
                legs.append(_rod([x, y, 0], [x, y, hs - ts * 0.5], lw / 2, 12))
            else:
                legs.append(_box([x, y, (hs - ts * 0.5) / 2], [lw, lw, hs - ts * 0.5]))
    seat = _box([0, 0, hs - ts / 2], [W, D, ts])
    out = {"legs": legs, "seat": [seat]}
    if variant != "stool":
        hb = rng.uniform(0.35, 0.5)
        posts = [_box([sx * (W / 2 - lw), D / 2 - lw / 2, hs + hb / 2 - ts / 2], [lw, lw, hb]) for sx in (-1, 1)]
        rail = _box([0, D / 2 - lw / 2, hs + hb - rng.uniform(0.05, 0.12)], [W, lw * 0.8, rng.uniform(0.08, 0.15)])
        out["backrest"] = posts + [rail]
    ct = rng.uniform(0.03, 0.07) if variant != "stool" else rng.uniform(0.025, 0.045)
    cushion = _blob([0, 0, hs + ct / 2 - 0.002], [0.45 * W, 0.45 * D, ct / 2 + 0.002], rng, 0.02, 3)
    v = np.asarray(cushion.vertices).copy()  # flatten towards a pillow: push the sides out
    import trimesh

    rxy = np.abs(v[:, :2] - v[:, :2].mean(0)) / np.array([0.45 * W, 0.45 * D])
    v[:, :2] = v[:, :2].mean(0) + (v[:, :2] - v[:, :2].mean(0)) * (1 + 0.25 * (1 - rxy ** 2))
    cushion = trimesh.Trimesh(v, cushion.faces, process=False)
    out["cushion"] = [cushion]
    return out


GEOMETRY: dict[str, Callable] = {
    "potted_plant": _potted_plant, "sport_ball": _sport_ball, "stuffed_toy": _stuffed_toy,
    "rubber_duck": _rubber_duck, "jelly_pudding": _jelly_pudding, "metal_tool": _metal_tool,
    "sand_pile": _sand_pile, "snow_pile": _snow_pile, "fruit": _fruit, "wooden_furniture": _wooden_furniture,
}
"""Semantic class -> geometry generator ``(rng, variant) -> {part: [closed trimesh components]}``."""


# =========================================================================== appearance (data)
def _rgb(h: str) -> tuple:
    return tuple(int(h[i:i + 2], 16) / 255.0 for i in (1, 3, 5))


@dataclass(frozen=True)
class Look:
    """Palette entry: pattern, colour of a soft-looking (u = 0) and a stiff-looking (u = 1) part, secondary colour."""

    pattern: str
    soft: str
    stiff: str
    secondary: str
    roughness: float = 0.7
    metallic: float = 0.0
    uv: str = "spherical"
    frequency: float = 6.0


PALETTES: dict = {
    ("potted_plant", "pot"): Look("noise", "#c9825a", "#8a4b32", "#6f3a25", 0.8, 0.0, "cylindrical", 3),
    ("potted_plant", "soil"): Look("speckle", "#5a4030", "#2e2018", "#9a7b5a", 0.95, 0.0, "cylindrical", 20),
    ("potted_plant", "trunk"): Look("grain", "#9b7a55", "#5b3a22", "#3c2616", 0.9, 0.0, "cylindrical", 8),
    ("potted_plant", "leaves"): Look("noise", "#8fd16a", "#2f6a2a", "#1f4a1c", 0.7, 0.0, "spherical", 10),
    ("potted_plant", "succulent", "leaves"): Look("stripes", "#a8d8b0", "#4f8f6a", "#d8e8c8", 0.5, 0.0, "spherical", 4),
    ("sport_ball", "soccer", "cover"): Look("panels", "#f4f4f0", "#d8d8d0", "#1a1a1a", 0.5, 0.0, "spherical", 5),
    ("sport_ball", "basketball", "cover"): Look("stripes", "#f08a3c", "#b5501e", "#1c1410", 0.8, 0.0, "spherical", 4),
    ("sport_ball", "tennis", "cover"): Look("fur", "#e6f55a", "#b9cc2e", "#f8f8f0", 0.95, 0.0, "spherical", 24),
    ("sport_ball", "volleyball", "cover"): Look("stripes", "#f6f2e0", "#e8d070", "#2856a8", 0.6, 0.0, "spherical", 3),
    ("sport_ball", "core"): Look("plain", "#e8e0d0", "#b8b0a0", "#a09888", 0.8, 0.0, "spherical", 2),
    ("stuffed_toy", "bear", "*"): Look("fur", "#d9b27c", "#8a5a32", "#f2dcb8", 0.95, 0.0, "spherical", 28),
    ("stuffed_toy", "bunny", "*"): Look("fur", "#f4eee8", "#b8aea6", "#f0c0c8", 0.95, 0.0, "spherical", 28),
    ("stuffed_toy", "cat", "*"): Look("stripes", "#f0b060", "#9a6a40", "#5a3a20", 0.95, 0.0, "spherical", 7),
    ("stuffed_toy", "eyes"): Look("plain", "#303030", "#050505", "#ffffff", 0.15, 0.0, "spherical", 2),
    ("rubber_duck", "*"): Look("plain", "#ffe45a", "#f0b800", "#ffffff", 0.25, 0.0, "spherical", 2),
    ("rubber_duck", "squeaky_soft", "*"): Look("noise", "#fff08a", "#f5cc30", "#ffffff", 0.5, 0.0, "spherical", 4),
    ("rubber_duck", "beak"): Look("plain", "#ffa040", "#e05010", "#ffffff", 0.3, 0.0, "spherical", 2),
    ("rubber_duck", "eyes"): Look("plain", "#202020", "#000000", "#ffffff", 0.1, 0.0, "spherical", 2),
    ("jelly_pudding", "plate"): Look("bands", "#f4f4f4", "#d8dde8", "#3050a0", 0.2, 0.0, "cylindrical", 2),
    ("jelly_pudding", "gelatin", "jelly"): Look("noise", "#ff6a8a", "#b0102a", "#ffffff", 0.1, 0.0, "cylindrical", 4),
    ("jelly_pudding", "panna_cotta", "jelly"): Look("noise", "#fff6e6", "#eadcc0", "#ffffff", 0.3, 0.0, "cylindrical", 3),
    ("jelly_pudding", "flan", "jelly"): Look("noise", "#ffe08a", "#e0b040", "#c07020", 0.2, 0.0, "cylindrical", 3),
    ("jelly_pudding", "topping"): Look("noise", "#fffaf0", "#8a3a10", "#c02040", 0.2, 0.0, "spherical", 5),
    ("metal_tool", "handle"): Look("grain", "#d8b080", "#7a4a28", "#5a3418", 0.7, 0.0, "cylindrical", 10),
    ("metal_tool", "body"): Look("brushed", "#c8ccd2", "#50545a", "#8a8e94", 0.35, 1.0, "box", 20),
    ("metal_tool", "can", "body"): Look("label", "#d8dde2", "#9aa0a8", "#c01820", 0.3, 1.0, "cylindrical", 3),
    ("metal_tool", "contents"): Look("plain", "#402010", "#200800", "#603010", 0.3, 0.0, "cylindrical", 2),
    ("sand_pile", "sand"): Look("speckle", "#f0dca0", "#b89060", "#806040", 0.95, 0.0, "cylindrical", 30),
    ("sand_pile", "pebbles"): Look("noise", "#b0aca8", "#5a5654", "#3a3634", 0.8, 0.0, "spherical", 6),
    ("snow_pile", "snow"): Look("speckle", "#ffffff", "#dce6f0", "#b8c8e0", 0.8, 0.0, "spherical", 30),
    ("snow_pile", "ice"): Look("noise", "#d8f0ff", "#7ab8e0", "#ffffff", 0.05, 0.0, "spherical", 4),
    ("snow_pile", "nose"): Look("stripes", "#ff9a40", "#d05a10", "#a04008", 0.6, 0.0, "cylindrical", 6),
    ("snow_pile", "arms"): Look("grain", "#8a6a4a", "#4a3020", "#2a1a10", 0.9, 0.0, "cylindrical", 6),
    ("fruit", "apple", "flesh"): Look("stripes", "#e8d050", "#b01818", "#f0e080", 0.35, 0.0, "spherical", 12),
    ("fruit", "orange", "flesh"): Look("speckle", "#ffb040", "#e07010", "#ffd080", 0.6, 0.0, "spherical", 40),
    ("fruit", "pear", "flesh"): Look("speckle", "#d8e070", "#98a030", "#7a6030", 0.5, 0.0, "spherical", 30),
    ("fruit", "plum", "flesh"): Look("noise", "#a05090", "#401040", "#8070a0", 0.3, 0.0, "spherical", 4),
    ("fruit", "core"): Look("plain", "#f4ecc0", "#d8c890", "#604020", 0.8, 0.0, "spherical", 2),
    ("fruit", "stem"): Look("grain", "#8a7040", "#4a3018", "#2a1a08", 0.9, 0.0, "cylindrical", 4),
    ("fruit", "leaf"): Look("stripes", "#9ad060", "#3a7a28", "#c0e090", 0.6, 0.0, "box", 6),
    ("wooden_furniture", "cushion"): Look("fur", "#d0c8e8", "#803040", "#f0e8f0", 0.95, 0.0, "box", 16),
    ("wooden_furniture", "*"): Look("grain", "#e0c090", "#6a4020", "#4a2a10", 0.6, 0.0, "box", 8),
    ("wooden_furniture", "padded_chair", "*"): Look("grain", "#c8a070", "#5a3418", "#3a2008", 0.4, 0.0, "box", 8),
}
"""(class, part) / (class, variant, part) / (class, "*") / (class, variant, "*") -> :class:`Look` (most specific wins)."""


def look_for(semantic_class: str, variant: str, part: str) -> Look:
    for key in ((semantic_class, variant, part), (semantic_class, part), (semantic_class, variant, "*"),
                (semantic_class, "*")):
        if key in PALETTES:
            return PALETTES[key]
    raise KeyError(f"no palette entry for {semantic_class}/{variant}/{part}")


def _appearance(look: Look, u: float, rng) -> Appearance:
    a, b = np.array(_rgb(look.soft)), np.array(_rgb(look.stiff))
    colour = np.clip((1 - u) * a + u * b + rng.normal(0, 0.03, 3), 0, 1)
    return Appearance(look.pattern, tuple(float(x) for x in colour), _rgb(look.secondary),
                      float(look.frequency * rng.uniform(0.8, 1.25)), float(np.clip(0.35 + 0.5 * u + rng.normal(0, 0.05), 0.1, 1.0)),
                      float(np.clip(look.roughness + 0.15 * (0.5 - u) + rng.normal(0, 0.03), 0.02, 1.0)), look.metallic,
                      float(u), look.uv)


# =========================================================================== textures
def _periodic_noise(rng, size: int, freq: float, aniso: tuple = (1.0, 1.0)) -> np.ndarray:
    """Tileable smooth noise in [0, 1], feature size ≈ size / freq (Gaussian-filtered white noise via FFT)."""
    white = rng.normal(size=(size, size))
    ky = np.fft.fftfreq(size)[:, None] * size
    kx = np.fft.fftfreq(size)[None, :] * size
    sigma = max(freq, 0.5)
    filt = np.exp(-0.5 * ((kx / (sigma * aniso[1])) ** 2 + (ky / (sigma * aniso[0])) ** 2))
    n = np.real(np.fft.ifft2(np.fft.fft2(white) * filt))
    n -= n.min()
    return n / max(n.max(), 1e-12)


def _pattern_mask(app: Appearance, rng, size: int) -> np.ndarray:
    """(size, size) float in [0, 1]: 0 = base colour, 1 = secondary colour (before contrast)."""
    f = app.frequency
    v, u = np.meshgrid(np.arange(size) / size, np.arange(size) / size, indexing="ij")  # v rows, u columns
    p = app.pattern
    if p == "plain":
        return 0.15 * _periodic_noise(rng, size, 3)
    if p == "noise":
        return _periodic_noise(rng, size, f)
    if p == "speckle":
        return (rng.random((size, size)) < 0.12).astype(float) * rng.uniform(0.5, 1.0, (size, size))
    if p == "fur":
        return 0.6 * rng.random((size, size)) + 0.4 * _periodic_noise(rng, size, f)
    if p == "stripes":
        warp = 0.08 * (_periodic_noise(rng, size, 3) - 0.5)
        return (np.sin(2 * np.pi * (round(f) * u + warp)) > 0.75).astype(float)
    if p == "grain":
        warp = 0.5 * _periodic_noise(rng, size, 2)
        return 0.5 + 0.5 * np.sin(2 * np.pi * (round(f) * u + 2.0 * warp) + 3 * _periodic_noise(rng, size, 8))
    if p == "brushed":
        return _periodic_noise(rng, size, f, aniso=(4.0, 0.25))
    if p == "bands":
        return ((v > 0.8) & (v < 0.9)).astype(float)
    if p == "label":
        return ((v > 0.25) & (v < 0.75)).astype(float) * (0.7 + 0.3 * (np.sin(2 * np.pi * round(f) * u) > 0))
    if p == "panels":
        n = max(int(f * f), 6)
        seeds = rng.random((n, 2))
        d = np.full((size, size), np.inf)
        lab = np.zeros((size, size), dtype=int)
        for i, (sv, su) in enumerate(seeds):  # periodic Voronoi cells
            dv = np.minimum(np.abs(v - sv), 1 - np.abs(v - sv))
            du = np.minimum(np.abs(u - su), 1 - np.abs(u - su))
            di = dv ** 2 + du ** 2
            lab = np.where(di < d, i, lab)
            d = np.minimum(d, di)
        dark = rng.random(n) < 0.35
        return dark[lab].astype(float)
    raise KeyError(f"unknown texture pattern {p!r}")


PATTERNS = ("plain", "noise", "speckle", "fur", "stripes", "grain", "brushed", "bands", "label", "panels")


def texture_image(app: Appearance, rng, size: int = TEXTURE_SIZE) -> np.ndarray:
    """(size, size, 3) uint8 sRGB texture of a part: base colour, pattern towards the secondary colour."""
    m = np.clip(_pattern_mask(app, rng, size) * app.contrast, 0, 1)[..., None]
    img = (1 - m) * np.asarray(app.colour)[None, None] + m * np.asarray(app.secondary)[None, None]
    img = img * (1.0 + 0.06 * (_periodic_noise(rng, size, 10)[..., None] - 0.5))
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _uv(part: Part):
    """Unmerged per-face vertices (F*3, 3), smooth normals (F*3, 3) and UVs (F*3, 2) of a part's components."""
    verts, norms, uvs = [], [], []
    for comp, rest in zip(part.components, part.rest or part.components):
        F = np.asarray(comp.faces)
        N = np.asarray(comp.vertex_normals, dtype=np.float64)
        verts.append(np.asarray(comp.vertices, dtype=np.float64)[F].reshape(-1, 3))
        V = np.asarray(rest.vertices, dtype=np.float64)      # UVs from the rest shape
        comp = rest
        P = V[F]                                   # (F, 3, 3)
        c = V.mean(0)
        lo, hi = V.min(0), V.max(0)
        size = max(float(np.max(hi - lo)), 1e-9)
        mode = part.appearance.uv
        if mode == "box":
            fn = np.asarray(comp.face_normals)
            ax = np.argmax(np.abs(fn), axis=1)
            other = np.array([[1, 2], [0, 2], [0, 1]])[ax]    # (F, 2)
            q = (P - lo) / size
            uv = np.stack([np.take_along_axis(q, other[:, None, 0:1].repeat(3, 1), 2)[..., 0],
                           np.take_along_axis(q, other[:, None, 1:2].repeat(3, 1), 2)[..., 0]], axis=-1)
        else:
            d = P - c
            u = np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi) + 0.5
            if mode == "cylindrical":
                v = (P[..., 2] - lo[2]) / max(hi[2] - lo[2], 1e-9)
            else:
                r = np.linalg.norm(d, axis=-1)
                v = np.arccos(np.clip(d[..., 2] / np.maximum(r, 1e-12), -1, 1)) / np.pi
            # faces across the seam: move their small-u corners by one turn (textures repeat)
            span = u.max(1) - u.min(1)
            wrap = span > 0.5
            u = np.where(wrap[:, None] & (u < 0.5), u + 1.0, u)
            # corners on the axis have no azimuth: take the mean of the face's other corners
            rxy = np.linalg.norm(d[..., :2], axis=-1)
            pole = rxy < 1e-9 * size
            if pole.any():
                fill = (u * ~pole).sum(1) / np.maximum((~pole).sum(1), 1)
                u = np.where(pole, fill[:, None], u)
            uv = np.stack([u, v], axis=-1)
        norms.append(N[F].reshape(-1, 3))
        uvs.append(uv.reshape(-1, 2))
    return np.concatenate(verts), np.concatenate(norms), np.concatenate(uvs)


def _textured_mesh(part: Part, seed: int):
    import trimesh
    from PIL import Image

    V, N, UV = _uv(part)
    faces = np.arange(len(V)).reshape(-1, 3)
    rng = np.random.default_rng([seed, _stable_hash(part.name)])
    img = Image.fromarray(texture_image(part.appearance, rng))
    app = part.appearance
    mat = trimesh.visual.material.PBRMaterial(name=part.name, baseColorTexture=img, metallicFactor=app.metallic,
                                              roughnessFactor=app.roughness)
    visual = trimesh.visual.TextureVisuals(uv=UV, material=mat)
    return trimesh.Trimesh(V, faces, vertex_normals=N, visual=visual, process=False)


def _stable_hash(text: str) -> int:
    h = 2166136261
    for ch in text.encode():
        h = ((h ^ ch) * 16777619) & 0x7FFFFFFF
    return h


# =========================================================================== scenarios
def make_scenario(prior: ann_mod.ScenarioPrior, parts: dict, part_names: list, rng):
    """The ground-truth clip's :class:`~unipixie.solvers.scenario.Scenario` (metres, z up, ground below)."""
    from ..solvers.scenario import Scenario

    verts = np.concatenate([np.asarray(c.vertices) for comps in parts.values() for c in comps])
    height = float(np.ptp(verts[:, 2]))
    size = float(np.max(np.ptp(verts, axis=0)))
    if prior.kind == "drop":
        h = rng.uniform(*prior.drop_height) * max(height, 0.3 * size)
        axis = rng.normal(size=3)
        axis[2] = 0.0
        axis /= max(np.linalg.norm(axis), 1e-9)
        omega = axis * rng.uniform(0.5, 2.0)
        return Scenario(ground_height=-float(h), initial_angular_velocity=omega,
                        notes=f"drop from {h:.4f} m with a tilt of {np.linalg.norm(omega):.2f} rad/s")
    if prior.kind == "anchored":
        comps = parts[prior.pinned_part]
        pv = np.concatenate([np.asarray(c.vertices) for c in comps])
        margin = 1e-3 * size
        box = np.stack([pv.min(0) - margin, pv.max(0) + margin])
        a = rng.uniform(0, 2 * np.pi)
        speed = rng.uniform(*prior.push_speed)
        return Scenario(ground_height=-margin, pinned_box=box,
                        initial_velocity=[speed * np.cos(a), speed * np.sin(a), 0.0],
                        notes=f"{prior.pinned_part} clamped; the rest pushed sideways at {speed:.2f} m/s")
    raise UserError(f"unknown scenario kind {prior.kind!r}")


# =========================================================================== generation
def class_of_index(index: int, classes=None) -> str:
    """The semantic class of object ``index``: the classes in turn (balanced counts)."""
    classes = tuple(classes or ann_mod.SEMANTIC_CLASSES)
    return classes[int(index) % len(classes)]


def object_id(index: int, semantic_class: str) -> str:
    return f"{int(index):06d}_{semantic_class}"


def generate(index: int, seed: int = 0, semantic_class: str | None = None, classes=None) -> ProceduralObject:
    """Object ``index`` of the dataset with base ``seed`` (deterministic; independent of other objects)."""
    semantic_class = semantic_class or class_of_index(index, classes)
    prior = ann_mod.class_prior(semantic_class)
    if semantic_class not in GEOMETRY:
        raise UserError(f"no geometry generator for class {semantic_class!r}")
    rng = np.random.default_rng([int(seed), int(index), _stable_hash(semantic_class)])
    variant = ann_mod.choose_variant(prior, rng)
    names = ann_mod.parts_of(prior, variant)
    raw = GEOMETRY[semantic_class](rng, variant)
    missing = [p for p in names if p not in raw or not raw[p]]
    extra = [p for p in raw if p not in names]
    if missing or extra:
        raise RuntimeError(f"{semantic_class}/{variant}: generator parts {sorted(raw)} differ from prior parts {names}")
    for p in names:
        for c in raw[p]:
            if not c.is_watertight:
                raise RuntimeError(f"{semantic_class}/{variant}: a component of part {p!r} is not closed")
            if c.volume < 0:
                c.invert()
    raw = _rest_on_ground({p: raw[p] for p in names})
    codes = {p: float(rng.uniform()) for p in names}
    parts = [Part(p, raw[p], _appearance(look_for(semantic_class, variant, p), codes[p], rng)) for p in names]
    annotation = ann_mod.sample_annotation(semantic_class, variant, codes, rng)
    scenario = make_scenario(prior.scenario, raw, names, rng)
    oid = object_id(index, semantic_class)
    annotation.meta.update({"object_id": oid, "index": int(index), "seed": int(seed)})
    return ProceduralObject(oid, int(index), int(seed), semantic_class, variant, parts, annotation, scenario,
                            {"appearance": {p.name: p.appearance.to_dict() for p in parts}})
