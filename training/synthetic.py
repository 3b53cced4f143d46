"""A tiny synthetic training set for tests and benchmarks (numpy only; no rendering).

Each object is a union of 1-3 primitive parts (box, ellipsoid, cylinder) on an R³ grid.  Every part
gets a material class from the registry and plausible ranges [min, max] of E, ν and density inside
that class's typical ranges; its voxels' features are the class's appearance vector (fixed per class)
plus a part-specific offset and a little per-voxel noise, so appearance carries the material as it
does in real data.  LBS and spring-mass targets are derived from the same ranges (LBS E = 0.8 × MPM E;
anchor stiffness k = E × voxel size at randomly chosen anchor voxels), so all three heads have
consistent labels.  Not physically fitted — for testing that the model learns, not for shipping.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.atomic_io import write_json
from ..core.types import FeatureGrid, GridGeometry
from ..solvers import materials
from ..solvers.skinning import LBS_PARAM_COUNT
from .sample_format import SPLIT_FILE, LBSTargets, MPMRanges, SpringTargets, TrainingSample

SYNTHETIC_FEATURE_MODEL = "synthetic-test"
_CLASS_CHOICES = tuple(c.id for c in materials.MATERIAL_CLASSES if c.simulated and not c.held_fixed)


def _grid_coords(R: int) -> np.ndarray:
    g = (np.arange(R) + 0.5) / R
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)  # (R, R, R, 3) in (0, 1)


def _primitive(rng: np.random.Generator, coords: np.ndarray, kind: str, centre, half) -> np.ndarray:
    d = (coords - centre) / half
    if kind == "box":
        return np.all(np.abs(d) <= 1.0, axis=-1)
    if kind == "ellipsoid":
        return np.sum(d * d, axis=-1) <= 1.0
    axis = int(rng.integers(3))  # cylinder
    others = [i for i in range(3) if i != axis]
    return (np.sum(d[..., others] ** 2, axis=-1) <= 1.0) & (np.abs(d[..., axis]) <= 1.0)


def class_appearance(class_id: int, feature_dim: int) -> np.ndarray:
    """The fixed (D,) appearance vector of a material class (seeded by the class id)."""
    return np.random.default_rng(1000 + int(class_id)).normal(size=feature_dim)


def procedural_occupancy(resolution: int, target_voxels: int) -> np.ndarray:
    """(R, R, R) bool: an ellipsoid body with a box on top and a cylindrical handle, scaled so that it
    has close to ``target_voxels`` occupied voxels (for benchmarks at 64³)."""
    R = int(resolution)
    coords = _grid_coords(R)

    def shape(s):
        body = np.sum(((coords - [0.5, 0.5, 0.42]) / (np.array([0.28, 0.24, 0.22]) * s)) ** 2, axis=-1) <= 1.0
        top = np.all(np.abs((coords - [0.5, 0.5, 0.42 + 0.26 * s]) / (np.array([0.12, 0.12, 0.08]) * s)) <= 1, axis=-1)
        d = (coords - [0.5 + 0.3 * s, 0.5, 0.42]) / (np.array([0.05, 0.05, 0.14]) * s)
        handle = (d[..., 0] ** 2 + d[..., 1] ** 2 <= 1) & (np.abs(d[..., 2]) <= 1)
        return body | top | handle

    lo, hi = 0.05, 1.6
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if shape(mid).sum() < target_voxels:
            lo = mid
        else:
            hi = mid
    return shape(0.5 * (lo + hi))


def make_sample(seed: int, resolution: int = 12, feature_dim: int = 16, anchors: int = 16,
                feature_model: str = SYNTHETIC_FEATURE_MODEL, parts: int | None = None,
                occupancy: np.ndarray | None = None) -> TrainingSample:
    """One synthetic object (see module docstring).  ``occupancy`` fixes the shape (then split into
    parts by position); otherwise 1-3 random primitives."""
    rng = np.random.default_rng(seed)
    R = int(resolution)
    coords = _grid_coords(R)
    n_parts = int(parts or rng.integers(1, 4))
    labels = np.full((R, R, R), -1, dtype=np.int64)
    if occupancy is None:
        for p in range(n_parts):
            kind = ("box", "ellipsoid", "cylinder")[int(rng.integers(3))]
            half = rng.uniform(0.15, 0.3, size=3)
            centre = rng.uniform(0.5 - 0.2, 0.5 + 0.2, size=3)
            labels[_primitive(rng, coords, kind, centre, half)] = p
        if not np.any(labels >= 0):
            labels[R // 2 - 1:R // 2 + 1, R // 2 - 1:R // 2 + 1, R // 2 - 1:R // 2 + 1] = 0
    else:
        occ = np.asarray(occupancy, bool)
        z = coords[..., 2]
        cuts = np.quantile(z[occ], np.linspace(0, 1, n_parts + 1)[1:-1]) if n_parts > 1 else []
        labels[occ] = np.searchsorted(np.asarray(cuts), z[occ])
    occ = labels >= 0
    idx = np.argwhere(occ)
    part_of = labels[occ]
    K = idx.shape[0]
    present = sorted(set(part_of.tolist()))
    part_cls, part_E, part_nu, part_rho, part_feat = {}, {}, {}, {}, {}
    for p in present:
        c = materials.BY_ID[int(rng.choice(_CLASS_CHOICES))]
        lo, hi = np.log10(c.typical_E)
        span = min(hi - lo, rng.uniform(1.0, 2.0))  # decades between the soft and the stiff end
        e0 = rng.uniform(lo, hi - span)
        e1 = e0 + span
        n0 = rng.uniform(c.typical_nu[0], c.typical_nu[1])
        n1 = min(c.typical_nu[1], n0 + rng.uniform(0.0, 0.05))
        r0 = rng.uniform(c.typical_density[0], c.typical_density[1])
        r1 = min(c.typical_density[1], r0 * rng.uniform(1.0, 1.3))
        part_cls[p], part_E[p], part_nu[p], part_rho[p] = c.id, (10 ** e0, 10 ** e1), (n0, n1), (r0, max(r0, r1))
        part_feat[p] = class_appearance(c.id, feature_dim) + 0.3 * rng.normal(size=feature_dim)

    def per_voxel(table, which):
        return np.array([table[p][which] for p in part_of], dtype=np.float32)

    feats = np.stack([part_feat[p] for p in part_of]) + 0.05 * rng.normal(size=(K, feature_dim))
    geo = GridGeometry(R, origin=[-0.5, -0.5, -0.5], voxel_size=1.0 / R)
    grid = FeatureGrid(geo, occ, feats.astype(np.float16), feature_model=feature_model)
    E_min, E_max = per_voxel(part_E, 0), per_voxel(part_E, 1)
    nu_min, nu_max = per_voxel(part_nu, 0), per_voxel(part_nu, 1)
    mpm = MPMRanges(E_min, E_max, nu_min, nu_max, per_voxel(part_rho, 0), per_voxel(part_rho, 1),
                    np.array([part_cls[p] for p in part_of], dtype=np.int16))
    lbs = LBSTargets(rng.normal(0.0, 0.5, size=LBS_PARAM_COUNT).astype(np.float32), 0.8 * E_min, 0.8 * E_max,
                     nu_min, nu_max)
    anchor_voxels = rng.choice(K, size=anchors, replace=K < anchors)
    spring = SpringTargets(E_min[anchor_voxels] * geo.voxel_size, E_max[anchor_voxels] * geo.voxel_size,
                           float(rng.uniform(0.05, 0.2)), float(rng.uniform(0.25, 0.5)))
    meta = {"parts": {str(p): materials.BY_ID[part_cls[p]].name for p in present}, "seed": int(seed), "synthetic": True}
    return TrainingSample(f"synthetic-{seed:05d}", grid, mpm, lbs, spring, meta)


def make_dataset(out_dir, count: int, resolution: int = 12, feature_dim: int = 16, anchors: int = 16,
                 seed: int = 0, feature_model: str = SYNTHETIC_FEATURE_MODEL, test_fraction: float = 0.0,
                 **kwargs) -> list[Path]:
    """Write ``count`` synthetic samples into ``out_dir`` (+ split.json); returns the sample paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(int(count)):
        s = make_sample(seed * 100003 + i, resolution, feature_dim, anchors, feature_model, **kwargs)
        paths.append(s.save(out / f"{s.object_id}.npz"))
    n_test = int(round(test_fraction * count))
    ids = [p.stem for p in paths]
    write_json(out / SPLIT_FILE, {"train": ids[: len(ids) - n_test], "val": [], "test": ids[len(ids) - n_test:]},
               indent=1)
    return paths
