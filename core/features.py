"""From an object to its feature grid: render → dense features → lift, with caching and pictures.

    from unipixie.core.features import FeatureOptions, compute_features, features_for_file
    result = features_for_file("chair.glb", options=FeatureOptions(offline=True))
    result.grid            # FeatureGrid: 64³ occupancy over the normalised cube, (K, D) float16 features
    Normalisation.of(result.grid)   # the way back to the object's world space (metres)

Steps (each a stage of :attr:`FeatureResult.timings`):

1. ``geometry`` — the subject's world-space triangles and a fingerprint of
   geometry, UVs, colour attributes, materials and textures (Blender).
2. ``render`` — ``view_count`` views of the normalised object
   (:mod:`.blender_io.render`), cached under ``<cache>/views/<key>.npz``.
3. ``occupancy`` — the 64³ occupancy of the normalised mesh (:mod:`.lift`).
4. ``features`` — patch features of every view (:mod:`.clip_features`).
5. ``lift`` — features onto the occupied voxels (:mod:`.lift`).

The grid is cached under ``<cache>/features/<key>.npz`` where the key covers
the fingerprint, the render settings, the feature model (weights identity or
offline seed) and the lifting version, so running again is instant.  Steps
2–5 need Blender only for 1–2; :func:`features_from_views` does 3–5 from saved
views and a mesh without Blender.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Generator, Optional

import numpy as np

from .clip_features import CLIP_MODEL
from .errors import UserError
from .jobs import run_job
from .normalise import Normalisation, unit_cube_grid
from .render_defaults import DEFAULT_RESOLUTION, DEFAULT_SAMPLES, DEFAULT_VIEW_COUNT  # noqa: F401 - re-exported
from .types import FeatureGrid, Views

LIFT_VERSION = 1
"""Bumped when occupancy or lifting changes (part of the feature-grid cache key)."""


def rescaled(job, start: float, span: float):
    """A job whose fractions ``f`` are reported as ``start + span * f`` (for use with ``yield from``);
    closing it closes ``job``."""
    try:
        while True:
            try:
                fraction, status = next(job)
            except StopIteration as stop:
                return stop.value
            yield start + span * float(fraction), status
    finally:
        job.close()


@dataclass
class FeatureOptions:
    """What to compute.

    view_count, resolution, engine, samples, render_device: see :class:`.blender_io.render.RenderSettings`.
    extractor: which feature extractor (:data:`.extractors.EXTRACTORS`: ``"clip"``, ``"offline"``,
    ``"appearance"``, ``"appearance+vit"``); empty: ``"offline"`` when ``offline`` is set, else ``"clip"``.
    The appearance extractors render Cycles' passes with the views (:mod:`.appearance_features`).
    offline: use the untrained offline ViT (``offline-random-vit-w32``, not CLIP) instead of CLIP (the same
    as ``extractor="offline"``).
    clip_weights: local CLIP weights (file or folder); ``None``: ``$UNIPIXIE_CLIP_WEIGHTS`` or the default folder.
    clip_model: the OpenCLIP architecture of the CLIP weights (default ViT-B-16, the paper's).
    device: torch device for features and lifting (``"cpu"``, ``"cuda"``, ``"auto"``).
    use_cache: read and write the caches.
    """

    view_count: int = DEFAULT_VIEW_COUNT
    resolution: int = DEFAULT_RESOLUTION
    engine: str = "cycles"
    samples: int = DEFAULT_SAMPLES
    render_device: str = "auto"
    offline: bool = False
    clip_weights: Optional[str] = None
    clip_model: str = CLIP_MODEL
    device: str = "cpu"
    use_cache: bool = True
    extractor: str = ""

    def __post_init__(self):
        from .extractors import check_name

        if self.extractor:
            self.extractor = check_name(self.extractor)
            if self.offline and self.extractor != "offline":
                raise UserError(f"the offline features and the {self.extractor!r} extractor were both asked for; "
                                "choose one")
        if self.needs_passes and str(self.engine).lower() != "cycles":
            from .extractors import PASSES_NEED_CYCLES

            raise UserError(PASSES_NEED_CYCLES)

    @property
    def extractor_name(self) -> str:
        """The extractor these options ask for (see ``extractor``)."""
        return self.extractor or ("offline" if self.offline else "clip")

    @property
    def needs_passes(self) -> bool:
        from .extractors import NEEDS_PASSES

        return self.extractor_name in NEEDS_PASSES

    def render_settings(self):
        from .blender_io.render import RenderSettings

        return RenderSettings(view_count=self.view_count, resolution=self.resolution, engine=self.engine,
                              samples=self.samples, device=self.render_device, passes=self.needs_passes)


@dataclass
class FeatureResult:
    """grid: the feature grid (normalised cube; ``Normalisation.of(grid)`` maps to world metres).
    grid_path / views_path: the cached files.  cache_hit: the grid came from the cache.
    timings: seconds per stage.  views: the rendered views (``None`` on a cache hit; load ``views_path``)."""

    grid: FeatureGrid
    grid_path: Path
    views_path: Optional[Path]
    cache_hit: bool
    timings: dict = field(default_factory=dict)
    views: Optional[Views] = None

    @property
    def warnings(self) -> list:
        return list(self.grid.meta.get("warnings", []))

    @property
    def normalisation(self) -> Normalisation:
        return Normalisation.of(self.grid)


# --------------------------------------------------------------------------- Blender-free part
def occupancy_of(vertices_normalised: np.ndarray, faces: np.ndarray):
    """:class:`.lift.Occupancy` of a triangle mesh in normalised units (64³ over the unit cube)."""
    import trimesh

    from .lift import occupancy_from_mesh

    mesh = trimesh.Trimesh(np.asarray(vertices_normalised, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                           process=False)
    return occupancy_from_mesh(mesh, unit_cube_grid())


def features_from_views(views: Views, occupancy: np.ndarray, extractor, device: str = "cpu",
                        meta: dict | None = None, timings: dict | None = None) -> FeatureGrid:
    """Steps 4–5 without Blender: features of ``views`` by ``extractor`` lifted onto ``occupancy``
    (an appearance extractor needs ``views.passes``)."""
    from .extractors import feature_maps
    from .lift import feature_grid

    timings = timings if timings is not None else {}
    t = time.perf_counter()
    maps = feature_maps(extractor, views)
    _sync(device)
    timings["features"] = time.perf_counter() - t
    t = time.perf_counter()
    grid = feature_grid(views, maps, occupancy, extractor.name, unit_cube_grid(), meta=meta, device=device,
                        sample_offset_voxels=getattr(extractor, "sample_offset_voxels", 0.0))
    _sync(device)
    timings["lift"] = time.perf_counter() - t
    return grid


def _sync(device: str) -> None:
    if str(device).startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def extractor_identity(options: FeatureOptions) -> dict:
    """What determines the features, without loading a model (cheap; for cache keys)."""
    from .extractors import identity

    return identity(options.extractor_name, options.clip_weights, options.clip_model)


def views_cache_path(fingerprint: str, settings) -> Path:
    from .paths import cache_dir, content_key

    return cache_dir("views") / f"{content_key('views', fingerprint, settings.key())}.npz"


def grid_cache_path(views_path: Path, identity: dict) -> Path:
    from .lift import COS_MIN, DEPTH_TOLERANCE_VOXELS
    from .paths import cache_dir, content_key

    key = content_key("feature-grid", views_path.stem, identity, LIFT_VERSION, DEPTH_TOLERANCE_VOXELS, COS_MIN,
                      unit_cube_grid().to_dict())
    return cache_dir("features") / f"{key}.npz"


# --------------------------------------------------------------------------- with Blender
def render_stage(objects, options: FeatureOptions, fingerprint: str | None = None,
                 ) -> Generator[tuple[float, str], None, tuple[Views, Path]]:
    """Render (or load from the cache) the subject's views; returns (views, cached views path)."""
    from .blender_io import render

    settings = options.render_settings()
    fingerprint = fingerprint or render.subject_fingerprint(objects)
    path = views_cache_path(fingerprint, settings)
    if options.use_cache and path.is_file():
        try:
            yield 1.0, "views from the cache"
            return Views.load(path), path
        except UserError:
            path.unlink(missing_ok=True)       # unreadable cache entry: render again
    views = yield from render.render_job(objects, settings)
    views.meta["fingerprint"] = fingerprint
    if options.use_cache:
        views.save(path)  # atomic, with a unique temporary name
    return views, path


def features_job(objects, options: FeatureOptions | None = None, extractor=None,
                 ) -> Generator[tuple[float, str], None, FeatureResult]:
    """The whole pipeline for Blender objects as a job: yields (fraction, status), returns a
    :class:`FeatureResult` (see module docstring).  ``extractor`` (optional) replaces the one
    ``options`` names (e.g. to reuse a loaded model)."""
    from . import extractors
    from .blender_io import render

    options = options or FeatureOptions()
    if extractor is not None and getattr(extractor, "needs_passes", False) and not options.needs_passes:
        options = replace(options, offline=False, extractor=extractors.name_of(extractor.name))
    settings = options.render_settings()
    timings: dict = {}
    t = time.perf_counter()
    yield 0.0, "reading the object"
    subject = render.describe_subject(objects)
    verts, faces, fingerprint = subject.vertices, subject.faces, subject.fingerprint
    identity = extractor.identity if extractor is not None else extractor_identity(options)
    vpath = views_cache_path(fingerprint, settings)
    gpath = grid_cache_path(vpath, identity)
    timings["geometry"] = time.perf_counter() - t
    if options.use_cache and gpath.is_file():
        try:
            grid = FeatureGrid.load(gpath)
            yield 1.0, "feature grid from the cache"
            return FeatureResult(grid=grid, grid_path=gpath, views_path=vpath if vpath.is_file() else None,
                                 cache_hit=True, timings=timings)
        except UserError:
            gpath.unlink(missing_ok=True)

    # the model first: missing weights fail before any rendering, and torch / open_clip (with triton's LLVM)
    # are loaded before Blender initialises OpenGL for Workbench (the other order crashes, see render.py)
    yield 0.02, "loading the feature model"
    if extractor is None:
        t = time.perf_counter()
        extractor = extractors.make(options.extractor_name, clip_weights=options.clip_weights, device=options.device,
                                    clip_model=options.clip_model)
        timings["load_model"] = time.perf_counter() - t

    t = time.perf_counter()
    views, vpath = yield from rescaled(render_stage(objects, options, fingerprint), 0.05, 0.75)
    timings["render"] = time.perf_counter() - t

    yield 0.82, "occupancy"
    t = time.perf_counter()
    norm = Normalisation.from_matrix(views.normalisation)
    occ = occupancy_of(norm.to_normalised(verts), faces)
    timings["occupancy"] = time.perf_counter() - t

    yield 0.9, f"features ({extractor.name}) and lifting"
    meta = {"normalisation": norm.to_dict(), "space": "normalised", "objects": views.meta.get("objects", []),
            "view_count": views.count, "resolution": int(views.images.shape[1]), "engine": settings.engine,
            "fingerprint": fingerprint, "views_file": vpath.name, "occupancy_closed": occ.closed,
            "warnings": list(occ.warnings), "is_clip": bool(extractor.is_clip)}
    grid = features_from_views(views, occ.occupancy, extractor, device=extractor.device, meta=meta, timings=timings)
    grid.meta["seconds"] = {k: round(v, 4) for k, v in timings.items()}
    if options.use_cache:
        grid.save(gpath)  # atomic, with a unique temporary name
    yield 1.0, f"{int(occ.occupancy.sum())} voxels, D = {grid.dim}"
    return FeatureResult(grid=grid, grid_path=gpath, views_path=vpath if vpath.is_file() else None, cache_hit=False,
                         timings=timings, views=views)


def features_file_job(path, object_name: str | None = None, options: FeatureOptions | None = None, extractor=None):
    """:func:`features_job` for an object in a file (``.glb``/``.gltf``/``.obj``/``.ply``/``.stl``/``.blend``),
    imported into a temporary scene and removed afterwards."""
    from .blender_io.scene_import import loaded_objects

    with loaded_objects(path, object_name) as objects:
        result = yield from features_job(objects, options, extractor)
    result.grid.meta.setdefault("source", str(path))
    return result


def compute_features(objects, options: FeatureOptions | None = None, progress=None, extractor=None) -> FeatureResult:
    """:func:`features_job` run to the end (``progress`` can cancel)."""
    return run_job(features_job(objects, options, extractor), progress)


def features_for_file(path, object_name: str | None = None, options: FeatureOptions | None = None, progress=None,
                      extractor=None) -> FeatureResult:
    """:func:`features_file_job` run to the end (``progress`` can cancel)."""
    return run_job(features_file_job(path, object_name, options, extractor), progress)


# --------------------------------------------------------------------------- pictures
def _figure(width_in: float, height_in: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def save_view_sheet(views: Views, path, columns: int = 6) -> Path:
    """A PNG contact sheet of the rendered views (colour, with the view index)."""
    path = Path(path)
    V = views.count
    cols = min(columns, V)
    rows = (V + cols - 1) // cols
    fig = _figure(1.8 * cols, 1.9 * rows + 0.3)
    for v in range(V):
        ax = fig.add_subplot(rows, cols, v + 1)
        ax.imshow(np.clip(views.images[v], 0, 1), interpolation="nearest")
        ax.set_title(f"view {v}", fontsize=8)
        ax.axis("off")
    fig.suptitle(f"{V} views, {views.images.shape[2]}×{views.images.shape[1]} px, "
                 f"{views.meta.get('engine', '')}", fontsize=9)
    fig.tight_layout()
    from .atomic_io import save_figure

    save_figure(fig, path)
    return path


def pca_colours(features: np.ndarray) -> np.ndarray:
    """(K, D) features → (K, 3) RGB in [0, 1]: the first three principal components, each stretched
    between its 2nd and 98th percentile."""
    f = np.asarray(features, dtype=np.float32)
    f = f - f.mean(axis=0)
    cov = f.T @ f / max(len(f) - 1, 1)
    evals, evecs = np.linalg.eigh(cov.astype(np.float64))
    comps = evecs[:, ::-1][:, :3]
    proj = f @ comps.astype(np.float32)
    if proj.shape[1] < 3:
        proj = np.pad(proj, ((0, 0), (0, 3 - proj.shape[1])))
    lo, hi = np.percentile(proj, 2, axis=0), np.percentile(proj, 98, axis=0)
    return np.clip((proj - lo) / np.maximum(hi - lo, 1e-12), 0, 1)


def save_feature_slices(grid: FeatureGrid, path, slices_per_axis: int = 5) -> Path:
    """A PNG of slices through the feature grid coloured by PCA of the features (empty voxels white):
    for each axis x, y, z a row of ``slices_per_axis`` evenly spaced slices through the occupied range."""
    path = Path(path)
    R = grid.geometry.resolution
    rgb = np.ones((R, R, R, 3), dtype=np.float32)
    idx = grid.indices
    rgb[tuple(idx.T)] = pca_colours(grid.features)
    lo, hi = idx.min(axis=0), idx.max(axis=0)
    fig = _figure(1.9 * slices_per_axis, 6.2)
    names = "xyz"
    for a in range(3):
        positions = np.linspace(lo[a], hi[a], slices_per_axis + 2)[1:-1].round().astype(int)
        other = [n for i, n in enumerate(names) if i != a]
        for s, k in enumerate(positions):
            img = np.take(rgb, k, axis=a)                   # (R, R, 3) indexed [first other axis, second]
            ax = fig.add_subplot(3, slices_per_axis, a * slices_per_axis + s + 1)
            ax.imshow(np.transpose(img, (1, 0, 2)), origin="lower", interpolation="nearest")
            centre = grid.geometry.origin[a] + (k + 0.5) * grid.geometry.voxel_size
            ax.set_title(f"{names[a]} = {centre:+.2f}", fontsize=8)
            ax.set_xlabel(other[0], fontsize=7, labelpad=1)
            ax.set_ylabel(other[1], fontsize=7, labelpad=1)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle(f"feature grid, PCA colours ({grid.feature_model}, D = {grid.dim}, "
                 f"{len(idx)} voxels)", fontsize=9)
    fig.tight_layout()
    from .atomic_io import save_figure

    save_figure(fig, path)
    return path
