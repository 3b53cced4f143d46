"""``unipixie bench features``: time render → dense features → lift for one object, by stage.

The subject is a procedural textured object (Blender's Suzanne, subdivided twice, with a noise-texture
base colour), rendered from 24 views at 224² with Cycles (8 spp); features come from the **ViT-B-16 architecture
with random weights** (same cost as CLIP ViT-B-16, D = 768; no weights are needed, so the case name says
"random weights"); lifting onto the 64³ grid.  Metrics: ``render_seconds``, ``occupancy_seconds``,
``features_seconds``, ``lift_seconds``, ``total_seconds`` (their sum: one object with the model already
loaded) and ``load_model_seconds`` (once per process), each the median of ``--runs`` runs after a warm-up.

Machines without Blender (the GPU machine runs Python 3.12, bpy needs 3.11) time the stages after the
render from views saved here::

    unipixie bench features --device cpu --save-views benchmarks/features_views.npz     # with bpy
    unipixie bench features --device cuda --views-from benchmarks/features_views.npz    # anywhere
"""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

HELP = "render + features + lift of one object: 24 views at 224² with the ViT-B-16 architecture, by stage"
VIEWS_FORMAT = "unipixie.bench_features_views/1"


def add_arguments(p):
    from ..commands import _common
    from ..features import DEFAULT_RESOLUTION, DEFAULT_SAMPLES, DEFAULT_VIEW_COUNT

    p.add_argument("--device", type=_common.device, default="cpu", help="torch device for features and lifting")
    p.add_argument("--views", type=_common.positive_int, default=DEFAULT_VIEW_COUNT, help="number of views")
    p.add_argument("--resolution", type=_common.positive_int, default=DEFAULT_RESOLUTION, help="render size in pixels")
    p.add_argument("--engine", choices=("cycles", "workbench"), default="cycles")
    p.add_argument("--samples", type=_common.positive_int, default=DEFAULT_SAMPLES, help="Cycles samples per pixel")
    p.add_argument("--runs", type=_common.positive_int, default=3, help="timed runs after one warm-up (default 3)")
    p.add_argument("--views-from", metavar="NPZ", help="time features + lift on views saved with --save-views "
                                                       "(no Blender needed; the render is not timed)")
    p.add_argument("--save-views", metavar="NPZ", help="save the rendered views and mesh for --views-from")
    p.add_argument("--offline", action="store_true", help="also time the offline extractor (offline-random-vit-w32)")
    p.add_argument("--threads", type=_common.positive_int, default=None,
                   help="torch CPU threads (default: torch's choice; on an oversubscribed shared machine 1 can be "
                        "much faster)")


def _device_name(device: str) -> str:
    if device.startswith("cuda"):
        import torch

        return torch.cuda.get_device_name(torch.device(device))
    from ...solvers.warp_runtime import cpu_description

    return cpu_description()


def save_bench_views(path, views, vertices_normalised, faces) -> Path:
    """Views (uint8 images) and the normalised mesh in one compressed file for ``--views-from``."""
    from ..atomic_io import save_npz

    path = Path(path)
    save_npz(path, format=VIEWS_FORMAT, images=np.round(np.clip(views.images, 0, 1) * 255).astype(np.uint8),
                        depth=views.depth.astype(np.float32), intrinsics=views.intrinsics,
                        cam_to_world=views.cam_to_world, normalisation=views.normalisation,
                        vertices=np.asarray(vertices_normalised, np.float32), faces=np.asarray(faces, np.int32),
                        meta=json.dumps(views.meta, default=str))
    return path


def load_bench_views(path):
    from ..errors import UserError
    from ..types import Views

    path = Path(path)
    if not path.is_file():
        raise UserError(f"--views-from {path}: file not found")
    not_views = f"{path}: not a views file of 'unipixie bench features --save-views' (format {VIEWS_FORMAT})"
    try:
        with np.load(path, allow_pickle=False) as z:
            z = {k: z[k] for k in z.files}
    except Exception as exc:  # not a zip, pickled members, a damaged archive: one line
        raise UserError(f"{not_views}: {exc}") from None
    if str(z.get("format", "")) != VIEWS_FORMAT:
        raise UserError(not_views)
    try:
        views = Views(images=z["images"].astype(np.float32) / 255.0, depth=z["depth"], intrinsics=z["intrinsics"],
                      cam_to_world=z["cam_to_world"], normalisation=z["normalisation"], meta=json.loads(str(z["meta"])))
        return views, z["vertices"].astype(np.float64), z["faces"].astype(np.int64)
    except (KeyError, ValueError, TypeError) as exc:
        raise UserError(f"{not_views}: {type(exc).__name__}: {exc}") from None


def _median(values):
    return float(statistics.median(values))


def run(args) -> list[dict]:
    import torch

    from .. import clip_features as cf
    from ..features import _sync, occupancy_of
    from ..lift import feature_grid
    from ..normalise import Normalisation, unit_cube_grid

    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = f", {torch.get_num_threads()} torch threads" if device == "cpu" else ""
    stage_times: dict[str, list[float]] = {k: [] for k in ("render", "occupancy", "features", "lift")}
    if args.views_from:
        views, verts_n, faces = load_bench_views(args.views_from)
        render_once = None
        subject = f"{views.count} pre-rendered views {views.images.shape[1]}² from {Path(args.views_from).name}"
    else:
        import importlib.util

        from ..errors import UserError

        if importlib.util.find_spec("bpy") is None:
            raise UserError("the render stage needs Blender's 'bpy' module (Python 3.11); without it, time the "
                            "other stages with --views-from NPZ (saved by a run with --save-views)")
        from ..blender_io.render import RenderSettings, benchmark_object, describe_subject, render_views
        from ..blender_io.scene_import import temporary_scene

        settings = RenderSettings(view_count=args.views, resolution=args.resolution, engine=args.engine,
                                  samples=args.samples, device="auto")
        subject = f"{args.views} views {args.resolution}² {args.engine}" + (
            f" {args.samples} spp" if args.engine == "cycles" else "")

    t = time.perf_counter()
    extractors = [cf.random_clip_architecture(device=device)]
    load_times = {extractors[0].name: time.perf_counter() - t}
    if args.offline:
        t = time.perf_counter()
        extractors.append(cf.offline_extractor(device=device))
        load_times[extractors[1].name] = time.perf_counter() - t

    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    results = []
    with (temporary_scene("UniPixie benchmark") if not args.views_from else _null()) as scene:
        if not args.views_from:
            obj = benchmark_object(scene)
            subj = describe_subject([obj])

            def render_once():
                return render_views(obj, settings)
        for ext in extractors:
            times = {k: [] for k in stage_times}
            for run_index in range(args.runs + 1):                 # the first run is a warm-up
                if render_once is not None:
                    t = time.perf_counter()
                    views = render_once()
                    times["render"].append(time.perf_counter() - t)
                    norm = Normalisation.from_matrix(views.normalisation)
                    verts_n, faces = norm.to_normalised(subj.vertices), subj.faces
                t = time.perf_counter()
                occ = occupancy_of(verts_n, faces)
                times["occupancy"].append(time.perf_counter() - t)
                t = time.perf_counter()
                maps = ext(views.images)
                _sync(device)
                times["features"].append(time.perf_counter() - t)
                t = time.perf_counter()
                grid = feature_grid(views, maps, occ.occupancy, ext.name, unit_cube_grid(), device=device)
                _sync(device)
                times["lift"].append(time.perf_counter() - t)
            if args.save_views and render_once is not None and ext is extractors[0]:
                path = save_bench_views(args.save_views, views, verts_n, faces)
                print(f"saved views for --views-from: {path} ({path.stat().st_size / 1e6:.1f} MB)")
            case = f"{ext.name}, {subject}, {int(grid.occupancy.sum())} voxels, D = {grid.dim}{threads}"
            dev = _device_name(device)
            load_after = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
            note = (f"host load average {load_before:.1f} -> {load_after:.1f} on {os.cpu_count()} CPU cores "
                    "during the run (shared machine: CPU stages slow down with load)")
            total = []
            for r in range(1, args.runs + 1):
                total.append(sum(times[k][r] for k in times if times[k]))
            for stage, values in times.items():
                if values:
                    results.append({"case": case, "device": dev, "metric": f"{stage}_seconds",
                                    "value": _median(values[1:]), "runs": args.runs, "note": note})
            results.append({"case": case, "device": dev, "metric": "total_seconds", "value": _median(total),
                            "runs": args.runs, "note": note})
            results.append({"case": case, "device": dev, "metric": "load_model_seconds",
                            "value": float(load_times[ext.name]), "runs": 1, "note": note})
    return results


class _null:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False
