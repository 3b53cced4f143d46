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


def farthest_point_sampling(points: np.ndarray, count: int, start: int | None = None) -> np.ndarray:
    """Indices of ``count`` points chosen by farthest-point sampling (deterministic).

    The first point is ``start`` or, by default, the point farthest from the centroid
    (so the order does not depend on the input order for symmetric clouds beyond ties).
    Returns (min(count, N),) int64 indices in selection order.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n == 0:
        raise UserError("farthest-point sampling of an empty point set")
    count = min(int(count), n)
    if start is None:
        start = int(np.argmax(np.sum((pts - pts.mean(0)) ** 2, axis=1)))
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = start
    dist = np.sum((pts - pts[start]) ** 2, axis=1)
    for i in range(1, count):
        nxt = int(np.argmax(dist))
        chosen[i] = nxt
        dist = np.minimum(dist, np.sum((pts - pts[nxt]) ** 2, axis=1))
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
