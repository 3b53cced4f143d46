"""Point sampling shared by the solvers, the model and the dataset.

* :func:`fill_mesh` — material sample points inside a closed mesh on a jittered
  lattice (MPM particles, spring-mass anchor candidates, cubature candidates).
* :func:`farthest_point_sampling` — deterministic FPS (LBS cubature points,
  spring-mass anchors; the model's spring head relies on its order).
"""

from __future__ import annotations

import numpy as np

from ..core.errors import UserError


def inside_mesh(mesh, points: np.ndarray, batch: int = 200_000) -> np.ndarray:
    """(N, 3) points -> (N,) bool inside the mesh (ray tests with embree; generalised winding
    number fallback for open meshes is trimesh's ``contains`` behaviour)."""
    pts = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(pts), dtype=bool)
    for i in range(0, len(pts), batch):
        out[i:i + batch] = mesh.contains(pts[i:i + batch])
    return out


def fill_mesh(mesh, spacing: float, jitter: float = 0.0, seed: int = 0, max_points: int = 20_000_000) -> np.ndarray:
    """Points filling the inside of a closed mesh.

    Parameters
    ----------
    mesh: ``trimesh.Trimesh``, metres.
    spacing: lattice spacing in metres (e.g. grid dx / 2 for 8 particles per cell).
    jitter: random offset as a fraction of ``spacing`` (0 = regular lattice).
    Returns
    -------
    (P, 3) float64 metres, lattice points at cell centres that lie inside the mesh.
    """
    if spacing <= 0:
        raise UserError(f"fill spacing must be positive, got {spacing}")
    lo, hi = np.asarray(mesh.bounds[0], float), np.asarray(mesh.bounds[1], float)
    counts = np.maximum(np.ceil((hi - lo) / spacing).astype(np.int64), 1)
    if int(np.prod(counts)) > max_points:
        raise UserError(f"filling this mesh at spacing {spacing:g} m needs {int(np.prod(counts)):,} lattice points "
                        f"(limit {max_points:,}); use a coarser spacing")
    axes = [lo[d] + (np.arange(counts[d]) + 0.5) * spacing for d in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if jitter > 0:
        grid = grid + np.random.default_rng(seed).uniform(-0.5, 0.5, grid.shape) * jitter * spacing
    pts = grid[inside_mesh(mesh, grid)]
    if len(pts) == 0:
        raise UserError(f"no sample points fall inside the mesh at spacing {spacing:g} m: the mesh is too thin, "
                        "open, or the spacing too coarse")
    return pts


def farthest_point_sampling(points: np.ndarray, count: int, start: int | None = None,
                            spacing: np.ndarray | None = None) -> np.ndarray:
    """Indices of ``count`` points chosen by farthest-point sampling (deterministic).

    The first point is ``start`` or, by default, the point farthest from the centroid
    (so the order does not depend on the input order for symmetric clouds beyond ties).
    spacing: optional (N,) relative spacing wanted at each point (> 0): distances to the chosen set are measured
    in units of it, so regions of small spacing get proportionally more points (adaptive sampling).
    Returns (min(count, N),) int64 indices in selection order.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n == 0:
        raise UserError("farthest-point sampling of an empty point set")
    count = min(int(count), n)
    if start is None:
        start = int(np.argmax(np.sum((pts - pts.mean(0)) ** 2, axis=1)))
    inv2 = 1.0 if spacing is None else 1.0 / np.asarray(spacing, dtype=np.float64).reshape(-1) ** 2
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = start
    dist = np.sum((pts - pts[start]) ** 2, axis=1) * inv2
    for i in range(1, count):
        nxt = int(np.argmax(dist))
        chosen[i] = nxt
        dist = np.minimum(dist, np.sum((pts - pts[nxt]) ** 2, axis=1) * inv2)
    return chosen


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one representative point (closest to its cell centre) per occupied voxel of size ``voxel``."""
    pts = np.asarray(points, dtype=np.float64)
    keys = np.floor(pts / voxel).astype(np.int64)
    centre_dist = np.sum((pts - (keys + 0.5) * voxel) ** 2, axis=1)
    order = np.lexsort((centre_dist, keys[:, 2], keys[:, 1], keys[:, 0]))
    k_sorted = keys[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(k_sorted[1:] != k_sorted[:-1], axis=1)
    return np.sort(order[first])



THICKNESS_SAMPLES = 100_000
"""Lattice points of the provisional fill that :func:`thinnest_part` measures a mesh with."""

THICKNESS_REFINED_SAMPLES = 256
"""Medial samples of :func:`thinnest_part` measured on the mesh's surface (a closest point and a ray each)."""


def medial_thickness(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The medial samples of a filled solid and its thickness there.

    points: (N, 3) m, the solid's points on a lattice of pitch ``spacing`` (m) (:func:`fill_mesh`).
    Returns ((K, 3) m positions, (K,) m thicknesses) of the medial samples: lattice points whose distance to the
    solid's boundary is a maximum among their 26 neighbours (the spine of a bar, the mid-sheet of a plate), with
    twice that distance plus one spacing (the inscribed ball's centre lies between lattice points).  A bar of
    0.04 × 0.02 m section gives 0.02 along its spine; a plant the thicknesses of its trunk and its leaves.
    """
    from scipy import ndimage

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    lo = pts.min(0)
    idx = np.round((pts - lo) / spacing).astype(np.int64) + 1  # one empty layer around
    solid = np.zeros(tuple(int(v) for v in idx.max(0) + 2), dtype=bool)
    solid[tuple(idx.T)] = True
    # distance of an occupied cell's centre to the boundary: to the nearest empty cell centre, less half a cell
    depth = ndimage.distance_transform_edt(solid) * spacing - 0.5 * spacing
    medial = solid & (depth >= ndimage.maximum_filter(depth, size=3) - 1e-12)
    cells = np.argwhere(medial)
    return lo + (cells - 1) * spacing, 2.0 * depth[medial] + spacing


def thickness_at(points: np.ndarray, spacing: float) -> np.ndarray:
    """(N,) m: the thickness of the part of the solid each of its lattice points (N, 3) m belongs to - that of the
    nearest medial sample (:func:`medial_thickness`), so the corners of a bar's section have the bar's."""
    from scipy.spatial import cKDTree

    pos, thick = medial_thickness(points, spacing)
    if len(pos) == 0:
        return np.zeros(len(points))
    return thick[cKDTree(pos).query(np.asarray(points, dtype=np.float64))[1]]


def thinnest_part(mesh, percentile: float = 10.0) -> float:
    """Thickness (m) of the thinnest parts of a closed mesh (a bar of 0.04 × 0.02 m section: 0.02; a plant: its
    leaves or trunk).

    The ``percentile`` of :func:`medial_thickness` over a provisional fill of about :data:`THICKNESS_SAMPLES`
    points locates the thinnest parts, to within two lattice spacings (about 1.6 mm each on the bar: 0.0222 m).
    Up to :data:`THICKNESS_REFINED_SAMPLES` medial samples at that thickness are then measured on the mesh
    itself: the chord through the sample along the inward normal at its closest surface point (a slab's or a
    bar's thickness, a trunk's diameter, wherever the sample lies between the faces); the median of them.
    MPM's automatic cell size divides this thickness, so that the particles' lattice fits the part and its
    bending stiffness is the solid's (docs/fidelity.md)."""
    volume = float(mesh.volume) if getattr(mesh, "is_watertight", False) and mesh.volume > 0 else float(
        np.prod(np.maximum(mesh.extents, 1e-9)))
    spacing = (volume / THICKNESS_SAMPLES) ** (1.0 / 3.0)
    pts = fill_mesh(mesh, spacing)
    for _ in range(3):  # very thin solids: refine until a few hundred points fill them
        if len(pts) >= 500:
            break
        spacing *= 0.5
        pts = fill_mesh(mesh, spacing)
    centres, thickness = medial_thickness(pts, spacing)
    lattice_estimate = float(np.percentile(thickness, percentile))
    near = np.flatnonzero(np.abs(thickness - lattice_estimate) <= 0.5 * spacing)
    if len(near) > THICKNESS_REFINED_SAMPLES:
        near = np.random.default_rng(0).choice(near, THICKNESS_REFINED_SAMPLES, replace=False)
    import trimesh

    probes = centres[near]
    surface, distance, _ = trimesh.proximity.closest_point(mesh, probes)
    ok = distance > 1e-9 * max(float(np.max(mesh.extents)), 1e-9)
    inward = (probes[ok] - surface[ok]) / distance[ok, None]
    origins = surface[ok] + inward * (1e-6 * spacing)
    hits, ray, _ = mesh.ray.intersects_location(origins, inward, multiple_hits=False)
    chord = np.linalg.norm(hits - origins[ray], axis=1)
    # the chord along the surface's inward normal: a slab's or a bar's thickness, a trunk's diameter; a sample
    # near a sharp corner or a ray through a gap measures something else: keep the lattice's figure there
    chord = chord[np.abs(chord - lattice_estimate) <= 2.0 * spacing]
    return float(np.median(chord)) if len(chord) else lattice_estimate
