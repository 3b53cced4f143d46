"""On-disk format of one training object (``unipixie.training_sample/1``) and of a dataset directory.

One object is one ``.npz`` file (numpy, no pickle), K = occupied voxels, N_a = spring anchors:

=====================  ==================  ==========================================================
key                    dtype, shape        meaning
=====================  ==================  ==========================================================
format                 str                 ``"unipixie.training_sample/1"``
object_id              str                 unique name of the object
geometry               str (JSON)          :class:`~unipixie.core.types.GridGeometry` (resolution, origin, voxel_size)
occupancy              uint8 packbits      (R, R, R) bool occupancy, ``np.packbits(occ.ravel())``
features               float16 (K, D)      per-voxel features, rows in ``np.argwhere(occupancy)`` order
feature_model          str                 extractor name (must match the model's ``feature_model``)
mpm_E_min, mpm_E_max   float32 (K,)        Young's modulus range per voxel, Pa (α = 0 -> min, α = 1 -> max)
mpm_nu_min, mpm_nu_max float32 (K,)        Poisson's ratio range
mpm_density_min/_max   float32 (K,)        density range, kg/m³
mpm_material           int16 (K,)          material-class id (:mod:`unipixie.solvers.materials`); -1 = unknown
lbs_params             float32 (650,)      LBS skinning parameters (:mod:`unipixie.solvers.skinning` layout),
                                           one set for all α (fitted at the soft end, as the paper does)
lbs_E_min, lbs_E_max   float32 (K,)        the LBS solver's E range per voxel, Pa (cubature-point values
                                           assigned to the voxels they fall in / nearest)
lbs_nu_min, lbs_nu_max float32 (K,)        the LBS solver's ν range per voxel
spring_stiffness_min   float32 (N_a,)      spring-mass per-anchor stiffness at α = 0 (solver units, N/m); N_a is
                                           the object's own anchor count (fewer on a solid too small for the
                                           network's, :func:`unipixie.training.train.check_spring_anchors`)
spring_stiffness_max   float32 (N_a,)      ... at α = 1
spring_softness_min    float32 ()          global softness η at α = 0 (dimensionless)
spring_softness_max    float32 ()          ... at α = 1
meta                   str (JSON)          free-form (semantic class, part names, source, ...)
=====================  ==================  ==========================================================

The MPM group is required; the LBS group (``lbs_*``) and the spring group (``spring_*``) are optional
(all keys of a group or none): the trainer gives a missing head no loss for that object.  Every range
needs min <= max, E, ρ, stiffness > 0 and ν in (-1, 0.5).

A dataset directory holds the sample files (``*.npz``, any sub-folders) and optionally
``split.json`` = ``{"train": [object ids or relative paths], "val": [...], "test": [...]}``; without
it every sample is training data.  :func:`data_fingerprint` identifies a set of files (names, sizes
and the first MiB of each) so a resumed run can tell it is training on the same data.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.atomic_io import is_temporary, save_npz
from ..core.errors import UserError, read_json, read_npz
from ..core.types import FeatureGrid, GridGeometry
from ..solvers.materials import NUM_CLASSES
from ..solvers.skinning import LBS_PARAM_COUNT

SAMPLE_FORMAT = "unipixie.training_sample/1"
SPLIT_FILE = "split.json"


@dataclass
class MPMRanges:
    """Per occupied voxel (K,): E_min/E_max Pa, nu_min/nu_max, density_min/density_max kg/m³, material ids."""

    E_min: np.ndarray
    E_max: np.ndarray
    nu_min: np.ndarray
    nu_max: np.ndarray
    density_min: np.ndarray
    density_max: np.ndarray
    material: np.ndarray


@dataclass
class LBSTargets:
    """params (650,) skinning parameters; E_min/E_max Pa and nu_min/nu_max per occupied voxel (K,)."""

    params: np.ndarray
    E_min: np.ndarray
    E_max: np.ndarray
    nu_min: np.ndarray
    nu_max: np.ndarray


@dataclass
class SpringTargets:
    """stiffness_min/stiffness_max (N_a,) per anchor (N/m); softness_min/softness_max scalars."""

    stiffness_min: np.ndarray
    stiffness_max: np.ndarray
    softness_min: float
    softness_max: float


@dataclass
class TrainingSample:
    object_id: str
    grid: FeatureGrid
    mpm: MPMRanges
    lbs: Optional[LBSTargets] = None
    spring: Optional[SpringTargets] = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.validate()

    @property
    def voxel_count(self) -> int:
        return int(self.grid.features.shape[0])

    # ------------------------------------------------------------------ checks
    def validate(self, where: str = "") -> None:
        where = where or f"training sample {self.object_id!r}"
        K = self.voxel_count

        def need(cond, msg):
            if not cond:
                raise UserError(f"{where}: {msg}")

        def per_voxel(name, arr):
            need(arr.shape == (K,), f"{name} must have one value per occupied voxel ({K}), got shape {arr.shape}")
            need(bool(np.all(np.isfinite(arr))), f"{name} contains NaN/inf")

        need(bool(np.all(np.isfinite(self.grid.features))), "features contain NaN/inf")
        m = self.mpm
        for name in ("E_min", "E_max", "nu_min", "nu_max", "density_min", "density_max"):
            setattr(m, name, np.asarray(getattr(m, name), dtype=np.float32).reshape(-1))
            per_voxel(f"mpm_{name}", getattr(m, name))
        m.material = np.asarray(m.material, dtype=np.int16).reshape(-1)
        need(m.material.shape == (K,), f"mpm_material must have {K} entries, got {m.material.shape}")
        need(bool(np.all((m.material >= -1) & (m.material < NUM_CLASSES))),
             f"mpm_material ids must be -1 (unknown) or 0..{NUM_CLASSES - 1}")
        need(bool(np.all(m.E_min > 0)) and bool(np.all(m.density_min > 0)), "E and density must be positive")
        self._ranges(need, "mpm_E", m.E_min, m.E_max)
        self._ranges(need, "mpm_nu", m.nu_min, m.nu_max)
        self._ranges(need, "mpm_density", m.density_min, m.density_max)
        need(bool(np.all((m.nu_min > -1) & (m.nu_max < 0.5))), "mpm_nu must lie in (-1, 0.5)")
        if self.lbs is not None:
            b = self.lbs
            b.params = np.asarray(b.params, dtype=np.float32).reshape(-1)
            need(b.params.shape == (LBS_PARAM_COUNT,), f"lbs_params must have {LBS_PARAM_COUNT} values, got {b.params.shape}")
            need(bool(np.all(np.isfinite(b.params))), "lbs_params contains NaN/inf")
            for name in ("E_min", "E_max", "nu_min", "nu_max"):
                setattr(b, name, np.asarray(getattr(b, name), dtype=np.float32).reshape(-1))
                per_voxel(f"lbs_{name}", getattr(b, name))
            need(bool(np.all(b.E_min > 0)), "lbs_E must be positive")
            self._ranges(need, "lbs_E", b.E_min, b.E_max)
            self._ranges(need, "lbs_nu", b.nu_min, b.nu_max)
            need(bool(np.all((b.nu_min > -1) & (b.nu_max < 0.5))), "lbs_nu must lie in (-1, 0.5)")
        if self.spring is not None:
            s = self.spring
            s.stiffness_min = np.asarray(s.stiffness_min, dtype=np.float32).reshape(-1)
            s.stiffness_max = np.asarray(s.stiffness_max, dtype=np.float32).reshape(-1)
            need(s.stiffness_min.size > 0 and s.stiffness_min.shape == s.stiffness_max.shape,
                 "spring_stiffness_min and _max must be non-empty and of equal length")
            need(bool(np.all(np.isfinite(s.stiffness_min)) and np.all(np.isfinite(s.stiffness_max))),
                 "spring stiffness contains NaN/inf")
            need(bool(np.all(s.stiffness_min > 0)), "spring stiffness must be positive")
            self._ranges(need, "spring_stiffness", s.stiffness_min, s.stiffness_max)
            s.softness_min, s.softness_max = float(s.softness_min), float(s.softness_max)
            need(np.isfinite(s.softness_min) and np.isfinite(s.softness_max), "spring softness is NaN/inf")
            need(s.softness_min <= s.softness_max, "spring_softness_min must be <= spring_softness_max")

    @staticmethod
    def _ranges(need, name, lo, hi):
        bad = int(np.sum(lo > hi))
        need(bad == 0, f"{name}_min > {name}_max in {bad} voxel(s)/entries (ranges must be [min, max])")

    # ------------------------------------------------------------------ files
    def save(self, path, compress: bool = True) -> Path:
        path = Path(path)
        g = self.grid
        d = dict(format=SAMPLE_FORMAT, object_id=self.object_id, geometry=json.dumps(g.geometry.to_dict()),
                 occupancy=np.packbits(g.occupancy.ravel()), features=g.features.astype(np.float16),
                 feature_model=g.feature_model, meta=json.dumps(self.meta, default=str))
        m = self.mpm
        d.update(mpm_E_min=m.E_min, mpm_E_max=m.E_max, mpm_nu_min=m.nu_min, mpm_nu_max=m.nu_max,
                 mpm_density_min=m.density_min, mpm_density_max=m.density_max, mpm_material=m.material)
        if self.lbs is not None:
            b = self.lbs
            d.update(lbs_params=b.params, lbs_E_min=b.E_min, lbs_E_max=b.E_max, lbs_nu_min=b.nu_min, lbs_nu_max=b.nu_max)
        if self.spring is not None:
            s = self.spring
            d.update(spring_stiffness_min=s.stiffness_min, spring_stiffness_max=s.stiffness_max,
                     spring_softness_min=np.float32(s.softness_min), spring_softness_max=np.float32(s.softness_max))
        save_npz(path, compressed=compress, **d)  # atomic, unique temporary name (hidden: .NAME.XXXX.tmp.npz)
        return path

    @classmethod
    def load(cls, path) -> "TrainingSample":
        path = Path(path)
        d = read_npz(path, "training sample")
        fmt = str(d.get("format", ""))
        if fmt != SAMPLE_FORMAT:
            raise UserError(f"{path}: key 'format' is {fmt!r}, expected {SAMPLE_FORMAT!r}")

        def key(k):
            if k not in d:
                raise UserError(f"{path}: missing key {k!r}")
            return d[k]

        try:
            geo = GridGeometry(**json.loads(str(key("geometry"))))
        except (TypeError, json.JSONDecodeError) as exc:
            raise UserError(f"{path}: bad 'geometry' ({exc})") from None
        R = geo.resolution
        occ = np.unpackbits(key("occupancy"))[: R ** 3].astype(bool).reshape(R, R, R)
        grid = FeatureGrid(geo, occ, key("features"), feature_model=str(key("feature_model")))
        mpm = MPMRanges(key("mpm_E_min"), key("mpm_E_max"), key("mpm_nu_min"), key("mpm_nu_max"),
                        key("mpm_density_min"), key("mpm_density_max"), key("mpm_material"))
        lbs = spring = None
        groups = {"lbs": ("lbs_params", "lbs_E_min", "lbs_E_max", "lbs_nu_min", "lbs_nu_max"),
                  "spring": ("spring_stiffness_min", "spring_stiffness_max", "spring_softness_min", "spring_softness_max")}
        for name, keys in groups.items():
            present = [k for k in keys if k in d]
            if present and len(present) != len(keys):
                raise UserError(f"{path}: incomplete {name} group: has {present}, needs all of {list(keys)}")
        if "lbs_params" in d:
            lbs = LBSTargets(d["lbs_params"], d["lbs_E_min"], d["lbs_E_max"], d["lbs_nu_min"], d["lbs_nu_max"])
        if "spring_stiffness_min" in d:
            spring = SpringTargets(d["spring_stiffness_min"], d["spring_stiffness_max"],
                                   float(d["spring_softness_min"]), float(d["spring_softness_max"]))
        meta = json.loads(str(d.get("meta", "{}")))
        sample = cls.__new__(cls)
        sample.object_id, sample.grid, sample.mpm, sample.lbs, sample.spring, sample.meta = (
            str(key("object_id")), grid, mpm, lbs, spring, meta)
        sample.validate(where=str(path))
        return sample


# ---------------------------------------------------------------------------- dataset directories
def list_samples(data_dir, split: str = "train") -> list[Path]:
    """Sample files of ``split`` in ``data_dir`` (all ``*.npz`` when there is no split.json), sorted."""
    root = Path(data_dir)
    if not root.is_dir():
        raise UserError(f"dataset directory {root} not found")
    files = sorted(p for p in root.rglob("*.npz") if not p.name.endswith(".tmp.npz") and not is_temporary(p.name))
    split_path = root / SPLIT_FILE
    if split_path.is_file():
        splits = read_json(split_path)
        if split not in splits:
            raise UserError(f"{split_path}: no split {split!r} (has {', '.join(splits)})")
        wanted = set(str(x) for x in splits[split])
        files = [p for p in files if p.stem in wanted or p.relative_to(root).as_posix() in wanted]
        if len(files) < len(wanted):
            found = {p.stem for p in files} | {p.relative_to(root).as_posix() for p in files}
            missing = sorted(wanted - found)
            raise UserError(f"{split_path}: split {split!r} names {len(missing)} missing sample(s), e.g. {missing[:3]}")
    if not files:
        raise UserError(f"dataset directory {root} has no training samples (*.npz, format {SAMPLE_FORMAT})")
    return files


def data_fingerprint(paths) -> str:
    """Identify a list of sample files by relative name, size and the first MiB of content."""
    h = hashlib.sha256()
    for p in sorted(Path(x) for x in paths):
        h.update(p.name.encode())
        h.update(str(p.stat().st_size).encode())
        with open(p, "rb") as f:
            h.update(f.read(1 << 20))
    return h.hexdigest()[:32]
