"""The closed primitives procedural objects are built from (trimesh, metres): solids of revolution, displaced
ellipsoids, rods, boxes, cones, and a radial displacement that keeps a solid of revolution closed.

Used by the classes' geometry (:mod:`.geometry`); needs only numpy (and trimesh, imported when called).
"""

from __future__ import annotations

import math

import numpy as np


def revolve(profile, sections: int = 40):
    """Closed solid of revolution about +z from a (r, z) profile running from the axis back to the axis."""
    import trimesh

    prof = np.asarray(profile, dtype=np.float64)
    prof[0, 0] = 0.0
    prof[-1, 0] = 0.0
    m = trimesh.creation.revolve(prof, sections=sections)
    if m.volume < 0:
        m.invert()
    return m


def blob(centre, radii, rng, noise: float = 0.0, subdivisions: int = 3, waves: int = 4):
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


def rod(p0, p1, radius, sections: int = 14):
    import trimesh

    return trimesh.creation.cylinder(radius=float(radius), segment=np.array([p0, p1], dtype=np.float64), sections=sections)


def box(centre, extents, rotz: float = 0.0):
    import trimesh

    T = trimesh.transformations.rotation_matrix(rotz, [0, 0, 1])
    T[:3, 3] = centre
    return trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64), transform=T)


def cone(base_centre, direction, radius, height, sections: int = 16):
    import trimesh

    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    m = trimesh.creation.cone(radius=float(radius), height=float(height), sections=sections)
    T = trimesh.geometry.align_vectors([0, 0, 1], d)
    T[:3, 3] = base_centre
    m.apply_transform(T)
    return m


def displace_radial(mesh, rng, amp: float, waves: int = 5):
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


def rotation_about_z(a):
    import trimesh

    return trimesh.transformations.rotation_matrix(a, [0, 0, 1])
