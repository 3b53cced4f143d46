"""Building, describing and reading a PixieMultiVerse-style dataset.

Layout of a dataset directory (everything per object, so shards never write the same file)::

    DATASET/
      build.json                 the build settings (every shard and resume must use the same)
      split.json                 {"train": [ids], "val": [...], "test": [...]} of the finished objects
      dataset.json, CARD.md      the dataset card (counts per class, ranges, split, settings, timings)
      samples/<id>.npz           the training sample (training/sample_format.py, unipixie.training_sample/1)
      objects/<id>/object.glb    the mesh: one named node + textured material per part (y-up glTF)
      objects/<id>/annotation.json   per-part ranges and constraints (core/annotation.py)
      objects/<id>/labels.npz    part id of every occupied voxel, part names, normalisation
      objects/<id>/ground_truth.npz  MPM motions at α = 0, 1 (and 0.5 for test objects), fitted LBS and
                                 spring-mass parameters, tracked vertices (see :func:`save_ground_truth`)
      objects/<id>/record.json   status ("done" / "failed"), timings per stage, fit results — written last

An object is *finished* when its ``record.json`` says ``"done"``; a build skips
finished objects (resumable), and every file is written to a temporary name and
renamed (atomic).  Object ``i`` belongs to shard ``i mod n`` (``--shard i/n``), its
class is the classes in turn, its split comes from a low-discrepancy sequence
(:func:`split_of`), and everything about it is a function of ``(seed, i)``.

A *user-supplied* set in the same layout (at least ``samples/`` and ``split.json``;
``objects/<id>/`` for the solver comparison) is read with :class:`DatasetDir`.
"""

from __future__ import annotations

import json
import math
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from ..core.atomic_io import json_default, save_npz, write_text
from ..core.errors import CancelledError, UserError, read_json
from ..core.progress import Progress
from ..core import annotation as ann_mod
from .ground_truth import GroundTruthSettings

BUILD_FORMAT = "unipixie.dataset_build/1"
CARD_FORMAT = "unipixie.dataset_card/1"
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
SPLITS = ("train", "val", "test")
STAGES = ("generate", "voxels", "render", "features", "mpm", "lbs_fit", "spring_fit", "write")
"""Build stages timed per object (seconds in record.json)."""


# =========================================================================== settings
@dataclass
class BuildSettings:
    """Everything a build depends on (saved as build.json; shards and resumes must agree).

    seed: base seed of every object.  classes: semantic classes cycled through (default all ten).
    resolution: voxels per side of the grid (64; the model's input).
    views / render_resolution / engine / samples: rendering for the features (Workbench by default).
    offline_features: the seeded, untrained offline ViT (``offline-random-vit-w32``, *not* CLIP); otherwise
    CLIP from ``clip_weights`` (file or folder).  extractor: a feature extractor by name
    (:data:`unipixie.core.extractors.EXTRACTORS`, e.g. ``"appearance"`` or ``"appearance+vit"``, which read
    Cycles' render passes: ``engine="cycles"``); empty: as ``offline_features`` says.  feature_device: torch
    device of features and lifting.
    split: fractions of train / val / test.  ground_truth: :class:`~.ground_truth.GroundTruthSettings`
    (as a dict).  test_alphas: extra α at which test objects are simulated with MPM (for the evaluation).
    """

    seed: int = 0
    classes: tuple = ann_mod.SEMANTIC_CLASSES
    resolution: int = 64
    views: int = 8
    render_resolution: int = 224
    engine: str = "workbench"
    samples: int = 8
    offline_features: bool = True
    clip_weights: Optional[str] = None
    feature_device: str = "cpu"
    split: tuple = (0.8, 0.1, 0.1)
    extractor: str = ""
    ground_truth: dict = field(default_factory=lambda: GroundTruthSettings().to_dict())
    test_alphas: tuple = (0.5,)

    def __post_init__(self):
        self.classes = tuple(self.classes)
        for c in self.classes:
            ann_mod.class_prior(c)
        if not self.classes:
            raise UserError("a dataset needs at least one semantic class")
        self.split = tuple(float(x) for x in self.split)
        if len(self.split) != 3 or any(x < 0 for x in self.split) or abs(sum(self.split) - 1.0) > 1e-6:
            raise UserError(f"split fractions must be three non-negative numbers summing to 1 (train, val, test), "
                            f"got {self.split}")
        if int(self.resolution) < 4 or int(self.resolution) % 4:
            raise UserError(f"grid resolution must be a multiple of 4 (the model downsamples by 4), got {self.resolution}")
        self.resolution = int(self.resolution)
        if int(self.views) < 1:
            raise UserError(f"views must be at least 1, got {self.views}")
        self.views = int(self.views)
        self.test_alphas = tuple(float(a) for a in self.test_alphas)
        if isinstance(self.ground_truth, GroundTruthSettings):
            self.ground_truth = self.ground_truth.to_dict()
        GroundTruthSettings.from_dict(self.ground_truth)  # validates
        if self.extractor:
            from ..core.extractors import NEEDS_PASSES, PASSES_NEED_CYCLES, check_name

            self.extractor = check_name(self.extractor)
            if self.extractor in NEEDS_PASSES and str(self.engine).lower() != "cycles":
                raise UserError(PASSES_NEED_CYCLES)

    @property
    def extractor_name(self) -> str:
        """The extractor the build uses (``extractor``, else ``"offline"`` / ``"clip"`` by ``offline_features``)."""
        return self.extractor or ("offline" if self.offline_features else "clip")

    def gt_settings(self, split: str) -> GroundTruthSettings:
        gt = GroundTruthSettings.from_dict(self.ground_truth)
        if split == "test":
            gt.extra_alphas = tuple(sorted(set(gt.extra_alphas) | set(self.test_alphas)))
        return gt

    def to_dict(self) -> dict:
        d = asdict(self)
        d["classes"] = list(self.classes)
        d["split"] = list(self.split)
        d["test_alphas"] = list(self.test_alphas)
        d["format"] = BUILD_FORMAT
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "BuildSettings":
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)

    def compatible(self, other: "BuildSettings") -> list[str]:
        """Names of the settings that differ from ``other`` (device choices excluded)."""
        a, b = self.to_dict(), other.to_dict()
        ga, gb = dict(a.pop("ground_truth")), dict(b.pop("ground_truth"))
        for d in (a, b):
            d.pop("feature_device", None)
        for d in (ga, gb):
            d.pop("device", None)
        diff = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        diff += [f"ground_truth.{k}" for k in sorted(set(ga) | set(gb)) if ga.get(k) != gb.get(k)]
        return diff


def split_of(index: int, fractions=(0.8, 0.1, 0.1)) -> str:
    """The split of object ``index``: test when frac(i·φ) < f_test, val when < f_test + f_val, else train.

    Independent of the dataset size (a dataset can grow) and evenly spread over the index sequence
    (so over the classes, which cycle with the index).
    """
    r = (int(index) * GOLDEN + 0.5 * GOLDEN) % 1.0
    f_train, f_val, f_test = fractions
    if r < f_test:
        return "test"
    if r < f_test + f_val:
        return "val"
    return "train"


SPLITS = ("train", "val", "test")


def shard_indices(count: int, shard: tuple[int, int] = (0, 1), splits=None, fractions=(0.8, 0.1, 0.1)) -> list[int]:
    """Object indices ``0..count-1`` of shard ``i/n`` (index ≡ i mod n); with ``splits`` (names of
    :data:`SPLITS`), only those whose :func:`split_of` under ``fractions`` is one of them (e.g. the test objects, to
    build them alone with the full ground truth for Table 2)."""
    i, n = shard
    if not (n >= 1 and 0 <= i < n):
        raise UserError(f"shard {i}/{n}: need 0 <= i < n")
    if splits is not None:
        unknown = sorted(set(splits) - set(SPLITS))
        if unknown or not splits:
            raise UserError(f"splits {', '.join(unknown) or '(none)'}: the splits are {', '.join(SPLITS)}")
    return [k for k in range(int(count)) if k % n == i and (splits is None or split_of(k, fractions) in splits)]


# =========================================================================== atomic files
def _atomic_write_text(path: Path, text: str) -> None:
    write_text(path, text)


def _atomic_savez(path: Path, **arrays) -> None:
    save_npz(path, **arrays)


# =========================================================================== per-object data
def voxel_part_labels(obj, resolution: int):
    """(normalisation, occupancy (R, R, R) bool, part ids (K,) int16) of an object on the unit-cube grid."""
    from ..core.normalise import Normalisation, unit_cube_grid

    verts = np.concatenate([np.asarray(c.vertices) for p in obj.parts for c in p.components])
    norm = Normalisation.from_points(verts)
    occ, part = obj.voxel_labels(norm.geometry_to_world(unit_cube_grid(resolution)))
    return norm, occ, part


def per_voxel_ranges(ann, part_ids: np.ndarray) -> dict:
    """Annotated ranges expanded to the occupied voxels: ``E_min`` ... ``density_max`` (K,) and ``material``."""
    t = ann_mod.part_table(ann)
    out = {k: v[part_ids] for k, v in t.items()}
    return out


def make_training_sample(object_id: str, grid, ann, part_ids: np.ndarray, gt=None, meta: Optional[dict] = None):
    """The :class:`~.sample_format.TrainingSample` of an object (MPM ranges from the annotation; LBS and
    spring-mass targets from the ground truth when given)."""
    from .sample_format import MPMRanges, TrainingSample

    r = per_voxel_ranges(ann, part_ids)
    mpm = MPMRanges(r["E_min"], r["E_max"], r["nu_min"], r["nu_max"], r["density_min"], r["density_max"], r["material"])
    lbs, spring = solver_targets(gt, part_ids, mpm) if gt is not None else (None, None)
    return TrainingSample(object_id, grid, mpm, lbs, spring, meta or {})


def solver_targets(gt, part_ids: np.ndarray, mpm):
    """(LBSTargets, SpringTargets) of a ground truth for the voxels' part ids (K,); ν ranges from ``mpm``
    (:class:`~.sample_format.MPMRanges`).  ``gt``: a :class:`~.ground_truth.GroundTruth` or
    :class:`StoredTargets`."""
    from .sample_format import LBSTargets, SpringTargets

    e0, e1 = gt.lbs_voxel_E(part_ids)
    lbs = LBSTargets(gt.lbs_params, e0, e1, mpm.nu_min, mpm.nu_max)
    spring = SpringTargets(gt.spring_stiffness[0.0], gt.spring_stiffness[1.0], gt.spring_softness, gt.spring_softness)
    return lbs, spring


@dataclass
class StoredTargets:
    """The training targets read back from a ``ground_truth.npz`` (:func:`load_training_targets`).

    lbs_params: (650,); lbs_part_E: (2, P) Pa, LBS E per part at α = 0 and 1; spring_stiffness: {0.0, 1.0} →
    (N_a,) N; spring_softness: η.
    """

    lbs_params: np.ndarray
    lbs_part_E: np.ndarray
    spring_stiffness: dict
    spring_softness: float

    def lbs_voxel_E(self, part_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.lbs_part_E[0][part_ids], self.lbs_part_E[1][part_ids]


def load_training_targets(path: Path) -> StoredTargets:
    """The LBS and spring-mass targets stored in a ``ground_truth.npz`` (written since 2026-11-28 with
    ``lbs_part_E``)."""
    with np.load(path, allow_pickle=False) as z:
        if "lbs_part_E" not in z.files:
            raise UserError(f"{path}: this ground truth predates the stored per-part LBS E ('lbs_part_E'); "
                            "rebuild it (unipixie dataset ground-truth)")
        k = np.asarray(z["spring_stiffness"], np.float64)
        return StoredTargets(np.asarray(z["lbs_params"], np.float32), np.asarray(z["lbs_part_E"], np.float64),
                             {0.0: k[0], 1.0: k[1]}, float(z["spring_softness"]))


def save_ground_truth(path: Path, gt, keep_trajectories: bool = True, extra: Optional[dict] = None) -> None:
    """Write a :class:`~.ground_truth.GroundTruth` as ``ground_truth.npz``.

    Keys: ``frame_times`` (T,) s; ``tracked_index`` (N,) indices into the object's vertices (parts and
    components in order); ``tracked_rest`` (N, 3) m; ``mpm_alphas`` (A,); ``mpm_positions`` (A, T, N, 3) float32 m;
    ``lbs_params`` (650,); ``lbs_E_scale`` (2,); ``lbs_part_E`` (2, P) Pa, the LBS E of each part at α = 0, 1;
    ``spring_stiffness`` (2, N_a) N; ``spring_softness`` (); ``anchors`` (N_a, 3) m; ``info`` (JSON: MPM info
    per α, fits, solid sizes); ``trajectories_kept`` (bool).  Without ``keep_trajectories`` the tracked
    points and the MPM motions are left out (the training targets and ``info`` stay).  ``extra``: more keys.
    """
    alphas = sorted(gt.mpm)
    info = {"mpm": {str(a): gt.mpm_info[a] for a in alphas}, "fits": gt.fits, "dx": gt.solid.dx,
            "spacing": gt.solid.spacing, "size": gt.solid.size, "wave_speed_cap": gt.solid.wave_speed_cap,
            "particles": int(len(gt.solid.points)), "scenario": gt.solid.scenario.to_dict()}
    arrays = dict(mpm_alphas=np.asarray(alphas, np.float64), lbs_params=np.asarray(gt.lbs_params, np.float32),
                  lbs_E_scale=np.asarray(gt.lbs_E_scale, np.float64),
                  lbs_part_E=gt.lbs_part_E().astype(np.float64),
                  spring_stiffness=np.stack([gt.spring_stiffness[0.0], gt.spring_stiffness[1.0]]).astype(np.float64),
                  spring_softness=np.float64(gt.spring_softness), anchors=np.asarray(gt.anchors, np.float64),
                  info=json.dumps(info, default=json_default), trajectories_kept=np.bool_(keep_trajectories))
    if keep_trajectories:
        arrays.update(frame_times=gt.solid.frame_times, tracked_index=gt.solid.tracked_index.astype(np.int64),
                      tracked_rest=gt.solid.tracked.astype(np.float64),
                      mpm_positions=np.stack([gt.mpm[a].positions for a in alphas]).astype(np.float32))
    _atomic_savez(path, **arrays, **(extra or {}))



# =========================================================================== building
class Renderer:
    """Renders objects' views in Blender and turns them into feature grids (one extractor per build)."""

    def __init__(self, settings: BuildSettings):
        self.settings = settings
        self._extractor = None

    @property
    def extractor(self):
        if self._extractor is None:
            from ..core import extractors

            self._extractor = extractors.make(self.settings.extractor_name, clip_weights=self.settings.clip_weights,
                                              device=self.settings.feature_device)
        return self._extractor

    def views(self, glb_path: Path):
        # the extractor (open_clip → torch._dynamo → triton) must be imported before Blender's first render:
        # importing triton after a Workbench render (EGL context) crashes the process
        self.extractor  # noqa: B018
        from ..core.blender_io import render
        from ..core.blender_io.scene_import import loaded_objects
        from ..core.jobs import run_job

        s = self.settings
        rs = render.RenderSettings(view_count=s.views, resolution=s.render_resolution, engine=s.engine,
                                   samples=s.samples, device="cpu" if s.engine == "workbench" else "auto",
                                   passes=getattr(self.extractor, "needs_passes", False))
        with loaded_objects(glb_path) as objects:
            return run_job(render.render_job(objects, rs))

    def feature_grid(self, views, occupancy: np.ndarray, meta: dict):
        from ..core.extractors import feature_maps
        from ..core.lift import feature_grid
        from ..core.normalise import unit_cube_grid

        maps = feature_maps(self.extractor, views)      # images (ViT) or render passes (appearance): never labels
        return feature_grid(views, maps, occupancy, self.extractor.name, unit_cube_grid(occupancy.shape[0]),
                            meta=meta, device=self.extractor.device,
                            sample_offset_voxels=getattr(self.extractor, "sample_offset_voxels", 0.0))


def _check_normalisation(views, norm) -> None:
    from ..core.normalise import Normalisation

    rendered = Normalisation.from_matrix(views.normalisation)
    if (abs(rendered.scale - norm.scale) > 1e-5 * norm.scale
            or np.max(np.abs(np.asarray(rendered.centre) - np.asarray(norm.centre))) > 1e-5 * norm.scale):
        raise RuntimeError(f"Blender's normalisation of the imported object ({rendered}) differs from the "
                           f"object's own ({norm}): the glb was not imported as written")


def build_object(root: Path, index: int, settings: BuildSettings, renderer: Renderer,
                 progress: Optional[Progress] = None) -> dict:
    """Build object ``index`` into ``root`` (all files, record.json last); returns its record."""
    from . import ground_truth
    from ..core import procedural

    timings: dict = {}
    t = time.perf_counter()
    obj = procedural.generate(index, settings.seed, classes=settings.classes)
    split = split_of(index, settings.split)
    odir = root / "objects" / obj.object_id
    odir.mkdir(parents=True, exist_ok=True)
    glb = odir / "object.glb"
    obj.export_glb(glb)  # atomic (core/atomic_io.py)
    _atomic_write_text(odir / "annotation.json", obj.annotation.to_json())
    timings["generate"] = time.perf_counter() - t

    t = time.perf_counter()
    norm, occ, part_ids = voxel_part_labels(obj, settings.resolution)
    timings["voxels"] = time.perf_counter() - t
    if progress is not None:
        progress.set_status(f"{obj.object_id}: rendering")

    t = time.perf_counter()
    views = renderer.views(glb)
    _check_normalisation(views, norm)
    timings["render"] = time.perf_counter() - t

    t = time.perf_counter()
    meta = {"normalisation": norm.to_dict(), "space": "normalised", "view_count": views.count,
            "resolution": int(views.images.shape[1]), "engine": settings.engine, "is_clip": bool(renderer.extractor.is_clip),
            "source": f"procedural:{obj.object_id}"}
    grid = renderer.feature_grid(views, occ, meta)
    timings["features"] = time.perf_counter() - t
    if progress is not None:
        progress.set_status(f"{obj.object_id}: ground truth")

    gt_timings: dict = {}
    gt = ground_truth.compute(obj, settings.gt_settings(split), progress=progress, timings=gt_timings)
    timings.update(gt_timings)

    t = time.perf_counter()
    sample_meta = {"semantic_class": obj.semantic_class, "variant": obj.variant, "part_names": obj.part_names,
                   "split": split, "index": index, "seed": settings.seed, "source": "procedural",
                   "normalisation": norm.to_dict(), "size_m": gt.solid.size}
    sample = make_training_sample(obj.object_id, grid, obj.annotation, part_ids, gt, sample_meta)
    (root / "samples").mkdir(exist_ok=True)
    sample.save(root / "samples" / f"{obj.object_id}.npz")
    _atomic_savez(odir / "labels.npz", part_ids=part_ids.astype(np.int16), part_names=np.array(obj.part_names),
                  occupancy=np.packbits(occ.ravel()), resolution=np.int64(settings.resolution),
                  normalisation=json.dumps(norm.to_dict()))
    save_ground_truth(odir / "ground_truth.npz", gt)
    timings["write"] = time.perf_counter() - t
    record = {"object_id": obj.object_id, "index": index, "status": "done", "split": split,
              "semantic_class": obj.semantic_class, "variant": obj.variant, "parts": obj.part_names,
              "voxels": int(occ.sum()), "size_m": gt.solid.size, "feature_model": grid.feature_model,
              "feature_dim": grid.dim, "painted_fraction_of_surface": grid.meta.get("painted_fraction_of_surface"),
              "timings": timings, "total_seconds": float(sum(timings.values())),
              "mpm": {str(a): gt.mpm_info[a] for a in sorted(gt.mpm_info)}, "fits": gt.fits,
              "spring_anchors": int(len(gt.anchors)), "sample_bytes": (root / "samples" / f"{obj.object_id}.npz").stat().st_size}
    _atomic_write_text(odir / "record.json", json.dumps(record, indent=1, default=json_default))
    return record


def read_record(root: Path, object_id: str) -> Optional[dict]:
    p = Path(root) / "objects" / object_id / "record.json"
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError:
        return None


def init_build(root, settings: BuildSettings) -> BuildSettings:
    """Create ``root`` with build.json, or check an existing build.json matches ``settings``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / "build.json"
    if path.is_file():
        try:
            old = BuildSettings.from_dict(json.loads(path.read_text()))
        except (json.JSONDecodeError, TypeError) as exc:
            raise UserError(f"{path}: unreadable build settings ({exc}); use a fresh directory") from None
        diff = settings.compatible(old)
        if diff:
            raise UserError(f"{root} was built with other settings ({', '.join(diff)}); build into a fresh directory "
                            "or repeat the original options")
        _write_feature_recipe(root, old)
        return old
    _atomic_write_text(path, json.dumps(settings.to_dict(), indent=1))
    _write_feature_recipe(root, settings)
    return settings


def _write_feature_recipe(root: Path, settings: BuildSettings) -> None:
    """``feature_recipe.json``: how the objects' views are rendered; training copies it into the checkpoint so the
    pipeline renders new objects the same way (core.model.checkpoint.read_feature_recipe)."""
    recipe = {"engine": str(settings.engine).lower(), "view_count": int(settings.views),
              "resolution": int(settings.render_resolution), "samples": int(settings.samples)}
    if settings.extractor:          # named explicitly: the checkpoint's pipeline extracts the same features
        from ..core.extractors import feature_model

        recipe["extractor"] = feature_model(settings.extractor)
    _atomic_write_text(root / "feature_recipe.json", json.dumps(recipe, indent=1))


def build(root, count: int, settings: BuildSettings | None = None, shard: tuple[int, int] = (0, 1),
          retry_failed: bool = False, progress: Optional[Progress] = None, log=None, splits=None) -> dict:
    """Build objects ``0..count-1`` of this shard into ``root`` (skipping finished ones), then refresh the card.
    ``splits``: build only the objects of these splits (:func:`shard_indices`).

    Returns a summary: ``built``, ``skipped``, ``failed`` (ids), ``seconds``.  An object that raises a
    :class:`UserError` or a simulation failure is recorded as failed (``record.json`` with the error)
    and the build goes on; ``retry_failed`` builds failed objects again.  Cancelling stops after the
    current stage; the unfinished object is built again next time.
    """
    from ..core import procedural

    root = Path(root)
    settings = init_build(root, settings or BuildSettings())
    indices = shard_indices(count, shard, splits, settings.split)
    progress = progress or Progress(total=len(indices), description=f"dataset shard {shard[0]}/{shard[1]}")
    renderer = Renderer(settings)
    summary = {"built": [], "skipped": [], "failed": [], "seconds": 0.0}
    t0 = time.perf_counter()
    for k, index in enumerate(indices):
        cls = procedural.class_of_index(index, settings.classes)
        oid = procedural.object_id(index, cls)
        rec = read_record(root, oid)
        if rec is not None and (rec.get("status") == "done" or (rec.get("status") == "failed" and not retry_failed)):
            summary["skipped"].append(oid)
            progress.step(1.0, f"{oid} already {rec.get('status')}")
            continue
        try:
            rec = build_object(root, index, settings, renderer, progress)
            summary["built"].append(oid)
            msg = f"{oid} done in {rec['total_seconds']:.1f} s"
        except CancelledError:
            raise
        except Exception as exc:  # noqa: BLE001 - recorded per object, the build goes on
            odir = root / "objects" / oid
            odir.mkdir(parents=True, exist_ok=True)
            (root / "samples" / f"{oid}.npz").unlink(missing_ok=True)
            err = {"object_id": oid, "index": index, "status": "failed", "semantic_class": cls,
                   "split": split_of(index, settings.split), "error": f"{type(exc).__name__}: {exc}",
                   "traceback": traceback.format_exc(limit=6) if not isinstance(exc, UserError) else ""}
            _atomic_write_text(odir / "record.json", json.dumps(err, indent=1))
            summary["failed"].append(oid)
            msg = f"{oid} FAILED: {err['error']}"
        if log is not None:
            log(msg)
        progress.step(1.0, msg)
    summary["seconds"] = time.perf_counter() - t0
    write_card(root)
    return summary


# =========================================================================== the card
def _stats(values) -> dict:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"n": 0}
    return {"n": int(v.size), "mean": float(v.mean()), "median": float(np.median(v)), "min": float(v.min()),
            "max": float(v.max()), "total": float(v.sum())}


def write_card(root) -> dict:
    """Scan the finished objects of ``root``; write split.json, dataset.json and CARD.md; return the card."""
    root = Path(root)
    if not (root / "objects").is_dir():
        raise UserError(f"{root} holds no objects/ folder: not a dataset directory")
    settings = None
    if (root / "build.json").is_file():
        settings = json.loads((root / "build.json").read_text())
    records = []
    for d in sorted((root / "objects").iterdir()):
        rec = read_record(root, d.name) if d.is_dir() else None
        if rec is not None:
            records.append(rec)
    done = [r for r in records if r.get("status") == "done" and (root / "samples" / f"{r['object_id']}.npz").is_file()]
    failed = [r for r in records if r.get("status") == "failed"]
    split = {s: sorted(r["object_id"] for r in done if r.get("split") == s) for s in SPLITS}
    _atomic_write_text(root / "split.json", json.dumps(split, indent=1))
    per_class: dict = {}
    for r in done:
        c = per_class.setdefault(r["semantic_class"], {"objects": 0, "variants": {}, "splits": {s: 0 for s in SPLITS}})
        c["objects"] += 1
        c["variants"][r["variant"]] = c["variants"].get(r["variant"], 0) + 1
        c["splits"][r["split"]] += 1
    ranges: dict = {}
    for r in done:
        try:
            ann = json.loads((root / "objects" / r["object_id"] / "annotation.json").read_text())
        except (OSError, json.JSONDecodeError):
            continue
        for part, pr in ann["parts"].items():
            key = f"{r['semantic_class']}.{part}"
            e = ranges.setdefault(key, {"material": pr["material"], "log10_E_min": [], "log10_E_max": [], "nu_min": [],
                                        "nu_max": [], "density_min": [], "density_max": []})
            e["log10_E_min"].append(math.log10(pr["E"][0]))
            e["log10_E_max"].append(math.log10(pr["E"][1]))
            e["nu_min"].append(pr["nu"][0])
            e["nu_max"].append(pr["nu"][1])
            e["density_min"].append(pr["density"][0])
            e["density_max"].append(pr["density"][1])
    range_summary = {k: {"material": v["material"], "objects": len(v["log10_E_min"]),
                         **{q: [float(np.min(v[q])), float(np.median(v[q])), float(np.max(v[q]))]
                            for q in v if q != "material"}} for k, v in sorted(ranges.items())}
    timings = {s: _stats([r["timings"].get(s) for r in done]) for s in STAGES}
    timings["total"] = _stats([r.get("total_seconds") for r in done])
    capped = {str(a): _stats([r["mpm"].get(str(a), {}).get("capped_mass_fraction") for r in done]) for a in (0.0, 1.0)}
    fits = {"lbs_rmse_m": _stats([x for r in done for x in r["fits"]["lbs"]["rmse"]]),
            "lbs_E_scale": _stats([x for r in done for x in r["fits"]["lbs"]["E_scale"]]),
            "spring_rmse_m": _stats([x for r in done for x in r["fits"]["spring_mass"]["rmse"]]),
            "spring_scale": _stats([x for r in done for x in r["fits"]["spring_mass"]["scale"]]),
            "relative_lbs_rmse": _stats([x / r["size_m"] for r in done for x in r["fits"]["lbs"]["rmse"]]),
            "relative_spring_rmse": _stats([x / r["size_m"] for r in done for x in r["fits"]["spring_mass"]["rmse"]]),
            "lbs_ends_crossed": int(sum(bool(r["fits"]["lbs"]["crossed"]) for r in done)),
            "spring_ends_crossed": int(sum(bool(r["fits"]["spring_mass"]["crossed"]) for r in done))}
    card = {"format": CARD_FORMAT, "objects": len(done), "failed": len(failed),
            "failures": [{"object_id": r["object_id"], "error": r.get("error", "")} for r in failed],
            "split_counts": {s: len(v) for s, v in split.items()}, "classes": per_class,
            "feature_model": sorted({r.get("feature_model", "") for r in done}),
            "feature_dim": sorted({r.get("feature_dim", 0) for r in done}),
            "spring_anchors": sorted({r.get("spring_anchors", 0) for r in done}),
            "ground_truth_settings": ground_truth_mixture(done),
            "ranges": range_summary, "timings_s": timings, "capped_mass_fraction": capped, "fits": fits,
            "sample_bytes": _stats([r.get("sample_bytes") for r in done]), "settings": settings}
    _atomic_write_text(root / "dataset.json", json.dumps(card, indent=1, default=json_default))
    _atomic_write_text(root / "CARD.md", card_markdown(card))
    return card


def ground_truth_mixture(done: list) -> list:
    """[{"settings": dict or None (= build.json's), "objects": n}] over the finished records, most frequent first."""
    counts: dict = {}
    for r in done:
        gt = r.get("ground_truth")
        if gt is not None:
            gt = {k: v for k, v in gt.items() if k != "extra_alphas"}
        key = json.dumps(gt, sort_keys=True)
        counts[key] = counts.get(key, 0) + 1
    return [{"settings": json.loads(k), "objects": n} for k, n in sorted(counts.items(), key=lambda kv: -kv[1])]


def card_markdown(card: dict) -> str:
    """The dataset card as Markdown (what CARD.md holds)."""
    L = [f"# Dataset card", "", f"- objects: **{card['objects']}** finished, {card['failed']} failed",
         f"- split: " + ", ".join(f"{k} {v}" for k, v in card["split_counts"].items()),
         f"- features: {', '.join(card['feature_model'])} (D = {', '.join(map(str, card['feature_dim']))})"
         + ("  — the offline extractor is an untrained, seeded ViT, **not CLIP**"
            if any(m.startswith('offline-') for m in card['feature_model']) else ""),
         f"- spring-mass anchors N_a: {', '.join(map(str, card['spring_anchors']))}", ""]
    s = card.get("settings") or {}
    if s:
        gt = s.get("ground_truth", {})
        L += ["## Generation settings", "",
              f"- seed {s.get('seed')}, grid {s.get('resolution')}³, {s.get('views')} views at {s.get('render_resolution')} px "
              f"({s.get('engine')}), offline features: {s.get('offline_features')}"
              + (f", extractor: {s['extractor']}" if s.get("extractor") else ""),
              f"- ground truth: {gt.get('frames')} frames at {gt.get('fps')} fps, MPM {gt.get('cells_across')} cells across, "
              f"{gt.get('particles_per_cell_axis')}³ particles per cell, wave speed ≤ {gt.get('wave_speed_per_size')} × size per s, "
              f"{gt.get('tracked_points')} tracked vertices, LBS {gt.get('lbs_cubature_points')} cubature points, "
              f"fits: ≤ {gt.get('fit_evaluations')} simulations per end", ""]
    mixture = card.get("ground_truth_settings") or []
    if len(mixture) > 1:
        L += ["**The objects' ground truth is mixed** (a `dataset ground-truth` rebuild under way):", ""]
        for m in mixture:
            g = m["settings"]
            L.append(f"- {m['objects']} objects: " + ("the build's settings above" if g is None else
                     f"{g.get('cells_across')} MPM cells across, {g.get('frames')} frames, "
                     f"{g.get('spring_anchors')} anchors, {g.get('tracked_points')} tracked vertices"))
        L.append("")
    L += ["## Classes", "", "| class | objects | train | val | test | variants |", "|---|---|---|---|---|---|"]
    for c, v in sorted(card["classes"].items()):
        sp = v["splits"]
        L.append(f"| {c} | {v['objects']} | {sp['train']} | {sp['val']} | {sp['test']} | "
                 + ", ".join(f"{k} {n}" for k, n in sorted(v["variants"].items())) + " |")
    L += ["", "## Annotated ranges per part (min / median / max over objects)", "",
          "| part | class | log10 E_min | log10 E_max | ν_min | ν_max | ρ_min kg/m³ | ρ_max kg/m³ |",
          "|---|---|---|---|---|---|---|---|"]
    fmt = lambda v, f: " / ".join(format(x, f) for x in v)  # noqa: E731
    for k, v in card["ranges"].items():
        L.append(f"| {k} | {v['material']} | {fmt(v['log10_E_min'], '.2f')} | {fmt(v['log10_E_max'], '.2f')} | "
                 f"{fmt(v['nu_min'], '.3f')} | {fmt(v['nu_max'], '.3f')} | {fmt(v['density_min'], '.0f')} | "
                 f"{fmt(v['density_max'], '.0f')} |")
    L += ["", "## Build time per object (seconds)", "", "| stage | mean | median | max | total |", "|---|---|---|---|---|"]
    for k, v in card["timings_s"].items():
        if v.get("n"):
            L.append(f"| {k} | {v['mean']:.2f} | {v['median']:.2f} | {v['max']:.2f} | {v['total']:.1f} |")
    f = card["fits"]
    L += ["", "## Ground truth", "",
          f"- mass fraction simulated at the wave-speed cap: α = 0 mean {card['capped_mass_fraction']['0.0'].get('mean', float('nan')):.2f}, "
          f"α = 1 mean {card['capped_mass_fraction']['1.0'].get('mean', float('nan')):.2f}",
          f"- LBS fit RMSE / size: median {f['relative_lbs_rmse'].get('median', float('nan')):.3f}; E scale median "
          f"{f['lbs_E_scale'].get('median', float('nan')):.3g}; ends crossed (set to their geometric mean) {f['lbs_ends_crossed']}",
          f"- spring-mass fit RMSE / size: median {f['relative_spring_rmse'].get('median', float('nan')):.3f}; scale median "
          f"{f['spring_scale'].get('median', float('nan')):.3g}; ends crossed {f['spring_ends_crossed']}",
          f"- training sample size: mean {card['sample_bytes'].get('mean', 0) / 1e6:.2f} MB", ""]
    if card["failures"]:
        L += ["## Failed objects", ""] + [f"- {x['object_id']}: {x['error']}" for x in card["failures"]] + [""]
    return "\n".join(L)


# =========================================================================== reading
class DatasetDir:
    """A built (or user-supplied) dataset in the layout of the module docstring.

    Needs ``samples/<id>.npz`` and ``split.json``; ``objects/<id>/`` files are needed only by what uses
    them (part labels, ground truth, the object itself).
    """

    def __init__(self, root):
        self.root = Path(root)
        if not self.root.is_dir():
            raise UserError(f"dataset directory {self.root} not found")
        sp = self.root / "split.json"
        if not sp.is_file():
            raise UserError(f"{self.root}: no split.json; run 'unipixie dataset card {self.root}' after building, or "
                            "write {\"train\": [...], \"val\": [...], \"test\": [...]} yourself")
        self.splits = read_json(sp)
        if not isinstance(self.splits, dict) or not all(isinstance(v, list) for v in self.splits.values()):
            raise UserError(f"{sp}: must map split names to lists of object ids")
        bj = self.root / "build.json"
        self.settings = BuildSettings.from_dict(json.loads(bj.read_text())) if bj.is_file() else None

    def ids(self, split: str) -> list[str]:
        if split == "all":
            return sorted({i for v in self.splits.values() for i in v})
        if split not in self.splits:
            raise UserError(f"{self.root}/split.json has no split {split!r} (has {', '.join(self.splits)})")
        return list(self.splits[split])

    def sample_path(self, object_id: str) -> Path:
        p = self.root / "samples" / f"{object_id}.npz"
        if not p.is_file():
            raise UserError(f"{self.root}: sample of {object_id!r} missing ({p})")
        return p

    def sample(self, object_id: str):
        from .sample_format import TrainingSample

        return TrainingSample.load(self.sample_path(object_id))

    def samples(self, split: str) -> Iterable:
        for oid in self.ids(split):
            yield self.sample(oid)

    def annotation(self, object_id: str):
        return ann_mod.Annotation.load(self.root / "objects" / object_id / "annotation.json")

    def part_labels(self, object_id: str) -> tuple[np.ndarray, list]:
        """(part id per occupied voxel (K,), part names)."""
        p = self.root / "objects" / object_id / "labels.npz"
        if not p.is_file():
            raise UserError(f"{self.root}: part labels of {object_id!r} missing ({p})")
        with np.load(p, allow_pickle=False) as z:
            return z["part_ids"].astype(np.int64), [str(x) for x in z["part_names"]]

    def ground_truth(self, object_id: str, need_motion: bool = False) -> dict:
        """The arrays of ``ground_truth.npz`` (see :func:`save_ground_truth`), ``info`` parsed.  ``need_motion``:
        refuse a ground truth whose MPM motions were not kept (a portable rebuild's, for training only)."""
        p = self.root / "objects" / object_id / "ground_truth.npz"
        if not p.is_file():
            raise UserError(f"{self.root}: ground truth of {object_id!r} missing ({p})")
        with np.load(p, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        d["info"] = json.loads(str(d["info"]))
        if need_motion and "mpm_positions" not in d:
            raise UserError(f"{p}: this ground truth keeps the fitted targets but not the MPM motions (it was "
                            f"computed elsewhere without --keep-trajectories); rebuild it here with 'unipixie dataset "
                            f"ground-truth {self.root}' to compare solvers against it")
        return d

    def ground_truth_settings(self, object_id: str, split: str) -> GroundTruthSettings:
        """The settings ``object_id``'s ground truth was made with: its record's since a rebuild
        (:mod:`.ground_truth_rebuild`), else the build's for ``split``."""
        rec = read_record(self.root, object_id) or {}
        if rec.get("ground_truth"):
            return GroundTruthSettings.from_dict(rec["ground_truth"])
        return self.settings.gt_settings(split) if self.settings else GroundTruthSettings()

    def record(self, object_id: str) -> dict:
        rec = read_record(self.root, object_id)
        if rec is None:
            raise UserError(f"{self.root}: record of {object_id!r} missing")
        return rec

    def object(self, object_id: str):
        """The object itself (parts, annotation, scenario): regenerated for a procedural build (deterministic)."""
        from ..core import procedural

        rec = self.record(object_id)
        if self.settings is None or rec.get("index") is None:
            raise UserError(f"{self.root}: {object_id!r} is not a procedural object of a build (no build.json/index)")
        obj = procedural.generate(int(rec["index"]), self.settings.seed, classes=self.settings.classes)
        if obj.object_id != object_id:
            raise UserError(f"{self.root}: regenerating {object_id!r} gave {obj.object_id!r}; build.json does not match")
        return obj
