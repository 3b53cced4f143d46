"""Lifting per-view image features into the model's voxel grid.

Everything here works in the *normalised* cube (:mod:`.normalise`): the mesh,
the views (rendered of the normalised object, so depths are in normalised
units) and the ``GRID_RESOLUTION``³ grid over ``[-0.5, 0.5]³``.

1. **Occupancy** (:func:`occupancy_from_mesh`).  For a closed (watertight)
   mesh a voxel is occupied when its centre lies inside (ray tests through
   embree, ``trimesh.Trimesh.contains``); parts thinner than a voxel, whose
   surface has no inside voxel within one voxel, keep the voxels their surface
   passes through.  For an open or non-manifold mesh the occupancy is the
   *surface shell* (voxels the surface passes through) with enclosed cavities
   filled, and a warning says so.
2. **Visibility.**  Surface voxels (occupied, with an empty face-neighbour) are
   projected into every view.  A voxel centre lies up to one voxel under the
   surface along the normal, i.e. up to ``h / cos θ`` along a viewing ray at
   angle θ to the normal; a view sees the voxel when the rendered depth ``d``
   at its projection (the nearest of the 2 × 2 pixels around it) satisfies
   ``-τ h ≤ z - d ≤ τ h / max(|cos θ|, COS_MIN)`` (``z`` the voxel centre's
   depth, ``h`` the voxel edge, ``τ`` = ``depth_tolerance_voxels`` = 1).
   A nearer surface (an occluder) makes ``z - d`` large, so occluded voxels are
   never painted by that view.
3. **Averaging.**  Each seeing view contributes its feature map sampled
   bilinearly at the voxel's projection, weighted by ``|cos θ|`` (θ between the
   voxel's surface normal and the direction to the camera; grazing views count
   little).  Normals are the negative gradient of the occupancy blurred with a
   Gaussian of σ = 1 voxel; where that gradient vanishes (sheets one voxel
   thick) every seeing view gets weight 1.
4. **Filling.**  Interior voxels and surface voxels no view sees take the
   features of the nearest painted surface voxel (Euclidean distance transform).
"""

from __future__ import annotations

import math
import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np

from .errors import UserError
from .normalise import unit_cube_grid
from .types import FeatureGrid, GridGeometry, Views

DEPTH_TOLERANCE_VOXELS = 1.0
"""τ: depth-test tolerance in voxel edges (scaled by 1/|cos θ| behind the surface, see module docstring)."""
COS_MIN = 0.25
"""Smallest |cos θ| used to widen the depth tolerance (at most 1/COS_MIN = 4 τ behind the surface)."""
SHELL_GAP_VOXELS = 3
"""Open meshes: gaps in the surface shell up to this many voxels are bridged to find an enclosed inside."""
SURFACE_SAMPLE_OFFSET = 0.5
"""Voxel edges outward along the normal at which pixel-accurate maps are sampled (``sample_offset_voxels``)."""
NORMAL_SIGMA_VOXELS = 1.0
"""σ of the Gaussian blur of the occupancy whose gradient gives the voxel normals, in voxels."""


@dataclass
class Occupancy:
    """occupancy: (R, R, R) bool; closed: whether the mesh was watertight; warnings: for the user."""

    occupancy: np.ndarray
    closed: bool
    warnings: list = field(default_factory=list)


def _as_trimesh(mesh):
    import trimesh

    if isinstance(mesh, trimesh.Scene):
        mesh = mesh.dump(concatenate=True)
    if not isinstance(mesh, trimesh.Trimesh):
        raise UserError(f"expected a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise UserError("the mesh has no faces: nothing to voxelise (points or edges only?)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise UserError("the mesh has NaN or infinite vertex positions")
    return mesh


def surface_points(mesh, spacing: float) -> np.ndarray:
    """(P, 3) points on the mesh surface no further than ``spacing`` apart along edges (subdivision)."""
    import trimesh

    verts, faces = trimesh.remesh.subdivide_to_size(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                                     max_edge=spacing, max_iter=64)
    return np.asarray(verts, dtype=np.float64)


def _voxels_of_points(points: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    R = geometry.resolution
    idx = geometry.index_of(points)
    # points on the grid's far faces (the normalised mesh touches +0.5) belong to the last voxel
    on_edge = np.abs(np.asarray(points) - (geometry.origin + R * geometry.voxel_size)) < 1e-9 * max(1.0, R * geometry.voxel_size)
    idx = np.where(on_edge & (idx == R), R - 1, idx)
    idx = idx[np.all((idx >= 0) & (idx < R), axis=1)]
    grid = np.zeros((R, R, R), dtype=bool)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return grid


def occupancy_from_mesh(mesh, geometry: GridGeometry | None = None) -> Occupancy:
    """Voxel occupancy of a triangle mesh given in the grid's coordinates (see module docstring).

    mesh: ``trimesh.Trimesh`` (normalised units when ``geometry`` is the default unit-cube grid).
    geometry: the grid (default :func:`~.normalise.unit_cube_grid`, 64³ over [-0.5, 0.5]³).
    """
    from scipy import ndimage

    geometry = geometry or unit_cube_grid()
    mesh = _as_trimesh(mesh).copy()
    mesh.merge_vertices()
    mesh.update_faces(mesh.unique_faces() & mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise UserError("the mesh has only zero-area faces: nothing to voxelise")
    R, h = geometry.resolution, geometry.voxel_size
    shell = _voxels_of_points(surface_points(mesh, 0.5 * h), geometry)
    warnings: list[str] = []
    edge_faces = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
    closed = bool(np.all(edge_faces % 2 == 0))          # every edge closes: inside/outside by ray parity
    if closed and np.any(edge_faces > 2):
        warnings.append("the mesh is non-manifold (edges shared by more than two faces) but closed; its inside "
                        "is taken by ray parity")
    if not closed:
        import trimesh

        repaired = mesh.copy()
        trimesh.repair.fill_holes(repaired)
        if repaired.is_watertight:
            warnings.append(f"the mesh was open; {len(repaired.faces) - len(mesh.faces)} faces were added to close "
                            "its holes for the occupancy (the object itself is unchanged)")
            mesh, closed = repaired, True
    if closed:
        # test only voxel centres inside the mesh's bounding box
        lo = np.clip(geometry.index_of(mesh.bounds[0][None])[0], 0, R - 1)
        hi = np.clip(geometry.index_of(mesh.bounds[1][None])[0], 0, R - 1)
        axes = [np.arange(lo[d], hi[d] + 1) for d in range(3)]
        ijk = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        inside = np.zeros(len(ijk), dtype=bool)
        centres = geometry.centres(ijk)
        for s in range(0, len(ijk), 100_000):
            inside[s:s + 100_000] = mesh.contains(centres[s:s + 100_000])
        occ = np.zeros((R, R, R), dtype=bool)
        occ[tuple(ijk[inside].T)] = True
        near_inside = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3), bool))
        thin = shell & ~near_inside
        if thin.any():
            occ |= thin
        if not occ.any():
            raise UserError("the mesh encloses no voxel centre of the 64³ grid and has no surface in it")
    else:
        reason = ("open and non-manifold (edges shared by more than two faces)" if np.any(edge_faces > 2)
                  else "open (has boundary edges)")
        warnings.append(f"the mesh is {reason}; its occupancy is taken from the surface shell (voxels the surface "
                        "passes through, enclosed cavities filled), which may thicken thin parts or miss an "
                        "inside that the shell does not close")
        # fill the cavity the shell encloses, closing gaps of up to SHELL_GAP_VOXELS voxels first
        occ = shell
        for gap in range(1, SHELL_GAP_VOXELS + 1):
            closed_shell = shell | ndimage.binary_closing(shell, structure=np.ones((3, 3, 3), bool), iterations=gap)
            filled = ndimage.binary_fill_holes(closed_shell)
            if filled.sum() > closed_shell.sum():
                occ = filled
                if gap > 1:
                    warnings.append(f"gaps of up to {gap} voxels in the surface shell were bridged to fill its inside")
                break
        if not occ.any():
            raise UserError("the mesh's surface does not pass through the grid")
    return Occupancy(occupancy=occ, closed=closed, warnings=warnings)


def surface_mask(occupancy: np.ndarray) -> np.ndarray:
    """(R, R, R) bool: occupied voxels with at least one empty face-neighbour (or on the grid's boundary)."""
    from scipy import ndimage

    occ = np.asarray(occupancy, dtype=bool)
    interior = ndimage.binary_erosion(occ, structure=ndimage.generate_binary_structure(3, 1), border_value=0)
    return occ & ~interior


def voxel_normals(occupancy: np.ndarray, indices: np.ndarray, sigma: float = NORMAL_SIGMA_VOXELS):
    """Outward unit normals at voxels: -∇(Gaussian-blurred occupancy).

    Returns (normals (K, 3) float32, valid (K,) bool); ``valid`` is False where the gradient vanishes.
    """
    from scipy import ndimage

    blurred = ndimage.gaussian_filter(np.asarray(occupancy, dtype=np.float32), sigma=sigma, mode="constant")
    i, j, k = np.asarray(indices).T
    grads = np.stack([ndimage.correlate1d(blurred, np.array([-0.5, 0.0, 0.5], np.float32), axis=a, mode="constant")[i, j, k]
                      for a in range(3)], axis=1)
    norm = np.linalg.norm(grads, axis=1)
    valid = norm > 1e-3
    normals = np.zeros_like(grads)
    normals[valid] = -grads[valid] / norm[valid, None]
    return normals.astype(np.float32), valid


@dataclass
class LiftResult:
    """features: (K, D) float16 for the K occupied voxels (argwhere order); views_per_voxel: (K,) int32,
    how many views painted each voxel (0 for interior / unseen voxels, filled from the nearest painted)."""

    features: np.ndarray
    views_per_voxel: np.ndarray
    painted_fraction_of_surface: float
    surface_voxels: int


# ----------------------------------------------------------------------------- cameras
def fibonacci_directions(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly on the sphere (Fibonacci lattice, z from +1 to -1, never at a pole)."""
    i = np.arange(count, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / count
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def look_at_origin(position: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world of a Blender camera at ``position`` looking at the origin, world +Z up."""
    pos = np.asarray(position, dtype=np.float64)
    z_axis = pos / np.linalg.norm(pos)                         # the camera looks along -Z
    up = np.array([0.0, 0.0, 1.0]) if abs(z_axis[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    x_axis = np.cross(up, z_axis)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x_axis, y_axis, z_axis, pos
    return m


def camera_rig(count: int, radius: float, resolution: int, fov_degrees: float):
    """Cameras on a Fibonacci sphere around a subject of bounding radius ``radius`` (normalised units).

    Returns (cam_to_world (V, 4, 4), intrinsics (V, 3, 3), distance, lens_mm, sensor_mm).
    """
    half = math.radians(fov_degrees) / 2.0
    distance = 1.05 * radius / math.sin(half)
    sensor = 36.0
    lens = sensor / (2.0 * math.tan(half))
    f_px = lens / sensor * resolution
    K = np.array([[f_px, 0.0, resolution / 2.0], [0.0, f_px, resolution / 2.0], [0.0, 0.0, 1.0]])
    c2w = np.stack([look_at_origin(d * distance) for d in fibonacci_directions(count)])
    return c2w, np.repeat(K[None], count, axis=0), distance, lens, sensor


def project(views: Views, points: np.ndarray):
    """Project (S, 3) points into every view.

    Returns (u, v, z) each (V, S) float64: pixel coordinates (x right, y down, origin at the image's
    top-left corner; pixel (r, c) spans [c, c+1) × [r, r+1)) and depth along the viewing axis.
    """
    w2c = np.linalg.inv(views.cam_to_world)                          # (V, 4, 4)
    p = np.asarray(points, dtype=np.float64)
    cam = np.einsum("vij,sj->vsi", w2c[:, :3, :3], p) + w2c[:, None, :3, 3]
    x, y, z = cam[..., 0], -cam[..., 1], -cam[..., 2]                # OpenCV camera: x right, y down, z forward
    K = views.intrinsics
    zs = np.where(z > 1e-9, z, np.nan)
    u = K[:, None, 0, 0] * x / zs + K[:, None, 0, 1] * y / zs + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * y / zs + K[:, None, 1, 2]
    return u, v, z


def visibility(views: Views, points: np.ndarray, cos_theta: np.ndarray, voxel_size: float,
               depth_tolerance_voxels: float = DEPTH_TOLERANCE_VOXELS):
    """Which views see which points (see module docstring).

    points: (S, 3) voxel centres; cos_theta: (V, S) cosine between normal and direction to each camera.
    Returns (visible (V, S) bool, u (V, S), v (V, S)).
    """
    u, v, z = project(views, points)
    V, H, W = views.depth.shape
    depth = views.depth
    inb = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < W) & (v >= 0) & (v < H) & (z > 0)
    uu = np.where(inb, u, 0.0)
    vv = np.where(inb, v, 0.0)
    # the 2 x 2 pixels whose centres surround the projection; keep the depth closest to the voxel's
    c0 = np.clip(np.floor(uu - 0.5).astype(np.int64), 0, W - 1)
    r0 = np.clip(np.floor(vv - 0.5).astype(np.int64), 0, H - 1)
    vi = np.arange(V)[:, None]
    best = np.full(u.shape, np.inf)
    for dr in (0, 1):
        for dc in (0, 1):
            d = depth[vi, np.minimum(r0 + dr, H - 1), np.minimum(c0 + dc, W - 1)].astype(np.float64)
            diff = np.where(np.isfinite(d), z - d, np.inf)
            best = np.where(np.abs(diff) < np.abs(best), diff, best)
    tol = depth_tolerance_voxels * voxel_size
    behind_tol = tol / np.maximum(np.abs(cos_theta), COS_MIN)
    visible = inb & (best >= -tol) & (best <= behind_tol)
    return visible, u, v


def lift_features(views: Views, feature_maps, occupancy: np.ndarray, geometry: GridGeometry | None = None,
                  depth_tolerance_voxels: float = DEPTH_TOLERANCE_VOXELS, device: str = "cpu",
                  sample_offset_voxels: float = 0.0) -> LiftResult:
    """Lift per-view feature maps onto the occupied voxels (see module docstring).

    views: the rendered views of the normalised object (depths in normalised units).
    feature_maps: (V, g_h, g_w, D) float (numpy or torch) covering each whole image (token grid or
        full resolution; sampled bilinearly with ``align_corners=False``), or a list of such maps of any
        sizes (e.g. full-resolution render passes and a ViT's token grid): each is sampled at its own
        resolution and the lifted features are concatenated in order (D = sum of the D_i).
    occupancy: (R, R, R) bool over ``geometry`` (default: 64³ unit-cube grid).
    device: torch device for the sampling and accumulation (``"cpu"`` or ``"cuda"``).
    sample_offset_voxels: sample the maps at the projection of the voxel centre moved this many voxel edges
        outwards along its normal (visibility still tests the centre).  0 (the default) samples at the centre.
        A surface voxel's centre lies 0–1 voxel under the surface, half a voxel on average, so 0.5 samples
        near the surface point itself; from an oblique view the centre's projection lands up to
        ``0.5 tan θ`` voxels beside it — what pixel-accurate maps (:data:`SURFACE_SAMPLE_OFFSET`) need to
        keep part boundaries sharp, and below the resolution of a 16-pixel token grid.
    """
    import torch
    from scipy import ndimage

    geometry = geometry or unit_cube_grid()
    occ = np.asarray(occupancy, dtype=bool)
    R = geometry.resolution
    if occ.shape != (R, R, R):
        raise UserError(f"occupancy must be {(R, R, R)}, got {occ.shape}")
    if not occ.any():
        raise UserError("the occupancy grid is empty: nothing to lift features onto")
    fmaps = []
    for m in (feature_maps if isinstance(feature_maps, (list, tuple)) else [feature_maps]):
        m = m if isinstance(m, torch.Tensor) else torch.as_tensor(np.asarray(m))
        m = m.to(device=device, dtype=torch.float32)
        if m.ndim != 4 or m.shape[0] != views.count:
            raise UserError(f"feature maps must be (V={views.count}, h, w, D), got {tuple(m.shape)}")
        fmaps.append(m)
    if not fmaps:
        raise UserError("no feature maps to lift")
    V, H, W = views.depth.shape

    surf = surface_mask(occ)
    sidx = np.argwhere(surf)
    centres = geometry.centres(sidx)
    normals, valid = voxel_normals(occ, sidx)
    cam_pos = views.cam_to_world[:, :3, 3]                                   # (V, 3)
    to_cam = cam_pos[:, None, :] - centres[None]                             # (V, S, 3)
    to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
    cos = np.einsum("vsc,sc->vs", to_cam, normals)
    cos = np.where(valid[None], cos, 1.0)
    visible, u, v = visibility(views, centres, cos, geometry.voxel_size, depth_tolerance_voxels)
    if sample_offset_voxels:
        outward = np.where(valid[:, None], normals, 0.0) * (float(sample_offset_voxels) * geometry.voxel_size)
        u, v, _ = project(views, centres + outward)
        u = np.where(visible, u, 0.0)
        v = np.where(visible, v, 0.0)
    weight = np.where(visible, np.maximum(np.abs(cos), 1e-3), 0.0)

    S = len(sidx)
    wsum = weight.sum(axis=0)
    painted = wsum > 0
    if not painted.any():
        raise UserError("no view sees any surface voxel: the views do not show this object (wrong cameras, "
                        "empty renders, or depth in other units than the occupancy grid)")
    # Bilinear sampling (align_corners=False, border) of every seeing view, weighted and summed (per map)
    surf_i, view_i = np.nonzero(visible.T)                                    # sorted by voxel (CSR rows)
    w = weight[view_i, surf_i] / wsum[surf_i]
    crow = np.zeros(S + 1, dtype=np.int64)
    crow[1:] = np.cumsum(4 * np.bincount(surf_i, minlength=S))
    surf_all = torch.cat([_sample_weighted(fmap, u[view_i, surf_i] / W, v[view_i, surf_i] / H, view_i, w, crow, S,
                                           device) for fmap in fmaps], dim=1)          # (S, D); weights sum to 1
    surf_feats = surf_all[torch.as_tensor(painted, device=device)].to(torch.float16).cpu().numpy()

    # interior and unseen voxels: features of the nearest painted surface voxel
    painted_grid = np.zeros((R, R, R), dtype=bool)
    pidx = sidx[painted]
    painted_grid[tuple(pidx.T)] = True
    row = np.full((R, R, R), -1, dtype=np.int64)
    row[tuple(pidx.T)] = np.arange(len(pidx))
    nearest = ndimage.distance_transform_edt(~painted_grid, return_distances=False, return_indices=True)
    oidx = np.argwhere(occ)
    src = row[nearest[0][tuple(oidx.T)], nearest[1][tuple(oidx.T)], nearest[2][tuple(oidx.T)]]
    features = surf_feats[src]                                                  # (K, D) float16
    count_grid = np.zeros((R, R, R), dtype=np.int32)
    count_grid[tuple(sidx.T)] = visible.sum(axis=0)
    return LiftResult(features=features, views_per_voxel=count_grid[tuple(oidx.T)],
                      painted_fraction_of_surface=float(painted.mean()), surface_voxels=int(S))


def _sample_weighted(fmap, ux, vy, view_i, w, crow, S: int, device: str):
    """Row s: the weighted sum over its seeing views of ``fmap`` (V, gh, gw, D) sampled bilinearly
    (``align_corners=False``, border) at image fractions (``ux``, ``vy``) — one sparse (S, V·gh·gw) ×
    dense (V·gh·gw, D) product with 4 taps per (voxel, view) pair, rows in CSR order ``crow``."""
    import torch

    V, gh, gw, D = (int(n) for n in fmap.shape)
    x = np.clip(ux * gw - 0.5, 0.0, gw - 1.0)
    y = np.clip(vy * gh - 0.5, 0.0, gh - 1.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, gw - 1), np.minimum(y0 + 1, gh - 1)
    base = view_i * (gh * gw)
    cols = np.stack([base + y0 * gw + x0, base + y0 * gw + x1, base + y1 * gw + x0, base + y1 * gw + x1], axis=1)
    vals = np.stack([w * (1 - fx) * (1 - fy), w * fx * (1 - fy), w * (1 - fx) * fy, w * fx * fy], axis=1)
    with _warnings.catch_warnings():
        _warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        taps = torch.sparse_csr_tensor(torch.as_tensor(crow, device=device),
                                       torch.as_tensor(cols.reshape(-1), device=device),
                                       torch.as_tensor(vals.reshape(-1), dtype=torch.float32, device=device),
                                       size=(S, V * gh * gw), device=device)
        return taps @ fmap.reshape(V * gh * gw, D)


def feature_grid(views: Views, feature_maps, occupancy: np.ndarray, feature_model: str,
                 geometry: GridGeometry | None = None, meta: dict | None = None, device: str = "cpu",
                 sample_offset_voxels: float = 0.0) -> FeatureGrid:
    """:func:`lift_features` packed as a :class:`~.types.FeatureGrid` (float16 features)."""
    geometry = geometry or unit_cube_grid()
    res = lift_features(views, feature_maps, occupancy, geometry, device=device,
                        sample_offset_voxels=sample_offset_voxels)
    m = dict(meta or {})
    m.update(painted_fraction_of_surface=res.painted_fraction_of_surface, surface_voxels=res.surface_voxels,
             mean_views_per_surface_voxel=float(res.views_per_voxel[res.views_per_voxel > 0].mean())
             if np.any(res.views_per_voxel > 0) else 0.0)
    return FeatureGrid(geometry=geometry, occupancy=np.asarray(occupancy, bool), features=res.features,
                       feature_model=feature_model, meta=m)
