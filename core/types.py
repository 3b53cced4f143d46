"""The shared data types of the pipeline, each defined once.

Units are SI throughout: metres, seconds, kilograms, pascals.  Arrays are
numpy.  Every type validates its shapes on construction and round-trips
through a compressed ``.npz`` file (no pickle).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .errors import UserError, read_npz

FORMATS = {
    "views": "unipixie.views/1",
    "feature_grid": "unipixie.feature_grid/1",
    "material_field": "unipixie.material_field/1",
    "trajectory": "unipixie.trajectory/1",
}


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise UserError(msg)


def check_alpha(alpha) -> float:
    """α, the soft-to-stiff control, as a float in [0, 1] (0 = the softest plausible material, 1 = the stiffest).

    The one check of α: every entry point calls it where α comes in (a bake's :class:`~unipixie.core.bake.
    BakeOptions` — the panel's, the command line's and manifests' bakes and the Python API's —, the command line's
    ``--alpha``, the panel's Refine), and everything below trusts the float it returns.  A value outside [0, 1],
    NaN or not a number is a :class:`UserError`.
    """
    try:
        value = float(alpha)
    except (TypeError, ValueError):
        raise UserError(f"α must be a number in [0, 1], got {alpha!r}") from None
    if not 0.0 <= value <= 1.0:
        raise UserError(f"α must lie in [0, 1], got {value:g}")
    return value


REQUIRED_KEYS = {
    "views": ("images", "depth", "intrinsics", "cam_to_world", "normalisation", "meta"),
    "feature_grid": ("occupancy", "features", "geometry", "feature_model", "meta"),
    "material_field": ("occupancy", "geometry", "E", "nu", "density", "material", "alpha", "meta"),
    "trajectory": ("times", "positions", "solver", "meta"),
}
"""The keys each archive format must hold (besides ``format``)."""


def _load_npz(path, fmt_key: str) -> dict:
    path = Path(path)
    data = read_npz(path)
    fmt = str(data.get("format", ""))
    _check(fmt == FORMATS[fmt_key], f"{path}: key 'format' is {fmt!r}, expected {FORMATS[fmt_key]!r}")
    missing = [k for k in REQUIRED_KEYS[fmt_key] if k not in data]
    _check(not missing, f"{path}: key(s) {', '.join(repr(k) for k in missing)} missing (a {FORMATS[fmt_key]} file holds "
                        f"{', '.join(REQUIRED_KEYS[fmt_key])}); the file is damaged or not made by UniPixie")
    return data


def _json_key(d: dict, key: str, path, kind=dict):
    """The JSON held in archive key ``key`` (a 0-d string array), checked to be a ``kind``."""
    try:
        v = json.loads(str(d[key]))
    except (ValueError, RecursionError) as exc:
        raise UserError(f"{path}: key '{key}' is not valid JSON ({exc})") from None
    _check(isinstance(v, kind), f"{path}: key '{key}' must hold a JSON {kind.__name__}")
    return v


def _save_npz(path, **arrays) -> Path:
    from .atomic_io import save_npz

    return save_npz(path, **arrays)


# --------------------------------------------------------------------------- Views
_PASS_PREFIX = "pass_"
"""Archive keys of a views file's optional render passes (``pass_<name>``)."""

@dataclass
class Views:
    """Rendered views of one object (normalised into the unit cube).

    images: (V, H, W, 3) float32 in [0, 1], linear-to-display sRGB as rendered.
    depth: (V, H, W) float32, metres along the camera's viewing axis (z-depth), ``inf`` for background.
    intrinsics: (V, 3, 3) float64 pinhole matrices in pixels (x right, y down, origin at the
        top-left pixel corner).
    cam_to_world: (V, 4, 4) float64, Blender camera convention (camera looks along -Z, +Y up).
    normalisation: (4, 4) float64, the matrix that maps the object's world space into the
        normalised unit cube the views were rendered in.
    passes: optional render passes of the same views, name -> (V, H, W, C) float32 (Cycles G-buffer:
        ``base_color`` C = 3 linear, ``roughness`` / ``metallic`` C = 1 in [0, 1], ``normal`` C = 3 unit
        vectors in the normalised cube's frame; NaN for background pixels and pixels less than half covered by
        the object); empty when not rendered.
        Saved as float16.
    """

    images: np.ndarray
    depth: np.ndarray
    intrinsics: np.ndarray
    cam_to_world: np.ndarray
    normalisation: np.ndarray = field(default_factory=lambda: np.eye(4))
    meta: dict = field(default_factory=dict)
    passes: dict = field(default_factory=dict)

    def __post_init__(self):
        self.images = np.asarray(self.images, dtype=np.float32)
        self.depth = np.asarray(self.depth, dtype=np.float32)
        self.intrinsics = np.asarray(self.intrinsics, dtype=np.float64)
        self.cam_to_world = np.asarray(self.cam_to_world, dtype=np.float64)
        self.normalisation = np.asarray(self.normalisation, dtype=np.float64)
        _check(self.images.ndim == 4 and self.images.shape[-1] == 3, f"Views.images must be (V, H, W, 3), got {self.images.shape}")
        V, H, W, _ = self.images.shape
        _check(self.depth.shape == (V, H, W), f"Views.depth must be {(V, H, W)}, got {self.depth.shape}")
        _check(self.intrinsics.shape == (V, 3, 3), f"Views.intrinsics must be {(V, 3, 3)}, got {self.intrinsics.shape}")
        _check(self.cam_to_world.shape == (V, 4, 4), f"Views.cam_to_world must be {(V, 4, 4)}, got {self.cam_to_world.shape}")
        _check(self.normalisation.shape == (4, 4), "Views.normalisation must be (4, 4)")
        passes = {}
        for name, arr in dict(self.passes or {}).items():
            a = np.asarray(arr, dtype=np.float32)
            if a.ndim == 3:
                a = a[..., None]
            _check(a.ndim == 4 and a.shape[:3] == (V, H, W),
                   f"Views.passes[{name!r}] must be {(V, H, W)} + (C,), got {a.shape}")
            passes[str(name)] = a
        self.passes = passes

    @property
    def count(self) -> int:
        return self.images.shape[0]

    def save(self, path) -> Path:
        path = Path(path)
        _save_npz(path, format=FORMATS["views"], images=(np.clip(self.images, 0, 1) * 65535).astype(np.uint16),
                            depth=self.depth, intrinsics=self.intrinsics, cam_to_world=self.cam_to_world,
                            normalisation=self.normalisation, meta=json.dumps(self.meta),
                            **{f"{_PASS_PREFIX}{k}": v.astype(np.float16) for k, v in self.passes.items()})
        return path

    @classmethod
    def load(cls, path) -> "Views":
        d = _load_npz(path, "views")
        passes = {k[len(_PASS_PREFIX):]: v for k, v in d.items() if k.startswith(_PASS_PREFIX)}
        return cls(images=d["images"].astype(np.float32) / 65535.0, depth=d["depth"], intrinsics=d["intrinsics"],
                   cam_to_world=d["cam_to_world"], normalisation=d["normalisation"], meta=_json_key(d, "meta", path),
                   passes=passes)


# --------------------------------------------------------------------------- grids
@dataclass
class GridGeometry:
    """A cubic voxel grid: ``resolution``³ cells of edge ``voxel_size`` metres from ``origin``.

    Voxel (i, j, k) covers ``origin + [i, i+1) * voxel_size`` along x (and j, k along y, z);
    its centre is ``origin + (index + 0.5) * voxel_size``.
    """

    resolution: int
    origin: np.ndarray
    voxel_size: float

    def __post_init__(self):
        self.resolution = int(self.resolution)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.voxel_size = float(self.voxel_size)
        _check(self.resolution > 0 and self.voxel_size > 0, "grid resolution and voxel size must be positive")

    def centres(self, indices: np.ndarray) -> np.ndarray:
        """(K, 3) int voxel indices -> (K, 3) float64 voxel centres in metres."""
        return self.origin + (np.asarray(indices, dtype=np.float64) + 0.5) * self.voxel_size

    def index_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in metres -> (N, 3) int64 voxel indices (may lie outside the grid)."""
        return np.floor((np.asarray(points, dtype=np.float64) - self.origin) / self.voxel_size).astype(np.int64)

    def to_dict(self) -> dict:
        return {"resolution": self.resolution, "origin": self.origin.tolist(), "voxel_size": self.voxel_size}


def unpack_occupancy(packed, resolution: int, path) -> np.ndarray:
    """(R, R, R) bool occupancy from its ``numpy.packbits`` form; a file whose packed bits cannot hold R³ voxels (a
    resolution that does not match the archive) is a :class:`UserError` naming ``path``."""
    packed = np.asarray(packed)
    R = int(resolution)
    if packed.dtype != np.uint8 or packed.ndim != 1:
        raise UserError(f"{path}: key 'occupancy' must be packed bits (uint8, 1-D), got {packed.dtype} {packed.shape}")
    if packed.size * 8 < R ** 3 or packed.size > (R ** 3 + 7) // 8:
        raise UserError(f"{path}: key 'occupancy' holds {packed.size * 8} voxel bits, the geometry's resolution {R} "
                        f"needs {R ** 3}; the file is damaged or was edited")
    return np.unpackbits(packed)[: R ** 3].astype(bool).reshape(R, R, R)


def _load_grid(d: dict, path) -> tuple[GridGeometry, np.ndarray]:
    """The grid geometry (JSON key ``geometry``) and the (R, R, R) bool occupancy (packed key ``occupancy``) of a
    loaded feature-grid or material-field archive ``d``; a geometry that is no grid geometry, or packed bits that do
    not fit it, is a :class:`UserError` naming ``path``."""
    try:
        geo = GridGeometry(**_json_key(d, "geometry", path))
    except TypeError as exc:
        raise UserError(f"{path}: key 'geometry' is not a grid geometry ({exc})") from None
    return geo, unpack_occupancy(d["occupancy"], geo.resolution, path)


@dataclass
class FeatureGrid:
    """Per-voxel visual features of one object (the model's input).

    geometry: the voxel grid (``resolution`` 64 by default, over the normalised unit cube).
    occupancy: (R, R, R) bool, True inside the solid.
    features: (K, D) float16, one row per occupied voxel in C order of ``np.argwhere(occupancy)``.
    feature_model: name of the extractor that made the features (``"ViT-B-16"``, or
        ``"offline-random-vit-..."`` for the untrained offline extractor).
    """

    geometry: GridGeometry
    occupancy: np.ndarray
    features: np.ndarray
    feature_model: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.occupancy = np.asarray(self.occupancy, dtype=bool)
        self.features = np.asarray(self.features, dtype=np.float16)
        R = self.geometry.resolution
        _check(self.occupancy.shape == (R, R, R), f"FeatureGrid.occupancy must be {(R, R, R)}, got {self.occupancy.shape}")
        K = int(self.occupancy.sum())
        _check(self.features.ndim == 2 and self.features.shape[0] == K,
               f"FeatureGrid.features must be (K={K}, D), got {self.features.shape}")

    @property
    def indices(self) -> np.ndarray:
        """(K, 3) int64 indices of the occupied voxels, in feature-row order."""
        return np.argwhere(self.occupancy)

    @property
    def dim(self) -> int:
        return int(self.features.shape[1])

    def save(self, path) -> Path:
        path = Path(path)
        _save_npz(path, format=FORMATS["feature_grid"], occupancy=np.packbits(self.occupancy.ravel()),
                            features=self.features, geometry=json.dumps(self.geometry.to_dict()),
                            feature_model=self.feature_model, meta=json.dumps(self.meta))
        return path

    @classmethod
    def load(cls, path) -> "FeatureGrid":
        d = _load_npz(path, "feature_grid")
        geo, occ = _load_grid(d, path)
        return cls(geometry=geo, occupancy=occ, features=d["features"], feature_model=str(d["feature_model"]),
                   meta=_json_key(d, "meta", path))


@dataclass
class MaterialField:
    """Physical material per occupied voxel, for one value of the soft-to-stiff control ``alpha``.

    geometry / occupancy: as in :class:`FeatureGrid` (K = occupancy.sum()).
    E: (K,) float32 Young's modulus, Pa.
    nu: (K,) float32 Poisson's ratio.
    density: (K,) float32, kg/m³.
    material: (K,) int16 material-class ids from :mod:`unipixie.solvers.materials`.
    alpha: the control value in [0, 1] this field was predicted for (NaN when not predicted).
    """

    geometry: GridGeometry
    occupancy: np.ndarray
    E: np.ndarray
    nu: np.ndarray
    density: np.ndarray
    material: np.ndarray
    alpha: float = float("nan")
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.occupancy = np.asarray(self.occupancy, dtype=bool)
        K = int(self.occupancy.sum())
        self.E = np.asarray(self.E, dtype=np.float32).reshape(-1)
        self.nu = np.asarray(self.nu, dtype=np.float32).reshape(-1)
        self.density = np.asarray(self.density, dtype=np.float32).reshape(-1)
        self.material = np.asarray(self.material, dtype=np.int16).reshape(-1)
        for name in ("E", "nu", "density", "material"):
            arr = getattr(self, name)
            _check(arr.shape == (K,), f"MaterialField.{name} must have one value per occupied voxel ({K}), got {arr.shape}")
        _check(bool(np.all(np.isfinite(self.E)) and np.all(self.E > 0)), "MaterialField.E must be finite and positive (Pa)")
        _check(bool(np.all(np.isfinite(self.density)) and np.all(self.density > 0)), "MaterialField.density must be finite and positive (kg/m³)")
        _check(bool(np.all((self.nu > -1.0) & (self.nu < 0.5))), "MaterialField.nu must lie in (-1, 0.5)")

    @property
    def indices(self) -> np.ndarray:
        return np.argwhere(self.occupancy)

    @classmethod
    def homogeneous(cls, geometry: GridGeometry, occupancy: np.ndarray, E: float, nu: float, density: float,
                    material: int = 0, alpha: float = float("nan")) -> "MaterialField":
        K = int(np.asarray(occupancy, bool).sum())
        return cls(geometry, occupancy, np.full(K, E), np.full(K, nu), np.full(K, density), np.full(K, material), alpha)

    def save(self, path) -> Path:
        path = Path(path)
        _save_npz(path, format=FORMATS["material_field"], occupancy=np.packbits(self.occupancy.ravel()),
                            geometry=json.dumps(self.geometry.to_dict()), E=self.E, nu=self.nu, density=self.density,
                            material=self.material, alpha=np.float64(self.alpha), meta=json.dumps(self.meta))
        return path

    @classmethod
    def load(cls, path) -> "MaterialField":
        d = _load_npz(path, "material_field")
        geo, occ = _load_grid(d, path)
        return cls(geo, occ, d["E"], d["nu"], d["density"], d["material"], float(d["alpha"]), _json_key(d, "meta", path))


# --------------------------------------------------------------------------- Trajectory
@dataclass
class Trajectory:
    """Simulated motion.

    times: (T,) float64 seconds, strictly increasing; ``times[0]`` is the initial state.
    positions: (T, N, 3) float32 metres, the tracked points (mesh vertices or given points).
    particle_positions: optional (T, P, 3) float32 metres, the solver's own particles/anchors/
        cubature points for baking and viewing.
    particle_attributes: optional per-particle arrays (e.g. ``"E"`` (P,), ``"material"`` (P,),
        ``"velocity"`` (T, P, 3)).
    handle_transforms: optional (T, H, 3, 4) float32 affine handle transforms (LBS solver only).
    solver: name of the solver that made it; ``meta`` holds free-form details (time step, ...).
    """

    times: np.ndarray
    positions: np.ndarray
    solver: str = ""
    particle_positions: Optional[np.ndarray] = None
    particle_attributes: dict = field(default_factory=dict)
    handle_transforms: Optional[np.ndarray] = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        self.positions = np.asarray(self.positions, dtype=np.float32)
        T = self.times.shape[0]
        _check(self.positions.ndim == 3 and self.positions.shape[0] == T and self.positions.shape[2] == 3,
               f"Trajectory.positions must be (T={T}, N, 3), got {self.positions.shape}")
        _check(T == 1 or bool(np.all(np.diff(self.times) > 0)), "Trajectory.times must be strictly increasing")
        if self.particle_positions is not None:
            self.particle_positions = np.asarray(self.particle_positions, dtype=np.float32)
            _check(self.particle_positions.ndim == 3 and self.particle_positions.shape[0] == T,
                   f"Trajectory.particle_positions must be (T={T}, P, 3)")
        if self.handle_transforms is not None:
            self.handle_transforms = np.asarray(self.handle_transforms, dtype=np.float32)
            _check(self.handle_transforms.ndim == 4 and self.handle_transforms.shape[0] == T
                   and self.handle_transforms.shape[2:] == (3, 4), "Trajectory.handle_transforms must be (T, H, 3, 4)")

    @property
    def frame_count(self) -> int:
        return int(self.times.shape[0])

    @property
    def point_count(self) -> int:
        return int(self.positions.shape[1])

    def save(self, path) -> Path:
        path = Path(path)
        extra: dict[str, Any] = {}
        if self.particle_positions is not None:
            extra["particle_positions"] = self.particle_positions
        if self.handle_transforms is not None:
            extra["handle_transforms"] = self.handle_transforms
        for k, v in self.particle_attributes.items():
            extra[f"attr__{k}"] = np.asarray(v)
        _save_npz(path, format=FORMATS["trajectory"], times=self.times, positions=self.positions,
                            solver=self.solver, meta=json.dumps(self.meta, default=str), **extra)
        return path

    @classmethod
    def load(cls, path) -> "Trajectory":
        d = _load_npz(path, "trajectory")
        attrs = {k[len("attr__"):]: v for k, v in d.items() if k.startswith("attr__")}
        return cls(times=d["times"], positions=d["positions"], solver=str(d["solver"]),
                   particle_positions=d.get("particle_positions"), particle_attributes=attrs,
                   handle_transforms=d.get("handle_transforms"), meta=_json_key(d, "meta", path))
