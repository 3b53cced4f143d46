"""``unipixie features OBJECT --out grid.npz``: render views, extract dense features, lift them to 64³."""

from __future__ import annotations

NAME = "features"
HELP = "render an object's views, extract dense features (CLIP, offline ViT or render-pass appearance) and lift them into the 64³ feature grid"
EXAMPLES = """  unipixie features chair.glb --out chair_grid.npz --clip-weights ~/models/ViT-B-16/
  unipixie features scene.blend --object Teapot --out teapot.npz --offline-features --sheet views.png --slices grid.png
  unipixie features bunny.ply --out bunny.npz --offline-features --engine workbench --views 12 --resolution 160
  unipixie features chair.glb --out chair_app.npz --extractor appearance+vit
  UNIPIXIE_CLIP_WEIGHTS=~/models/open_clip_pytorch_model.bin unipixie features cup.obj --out cup.npz --device cuda"""


def add_arguments(p):
    from ..features import DEFAULT_RESOLUTION, DEFAULT_SAMPLES, DEFAULT_VIEW_COUNT
    from . import _common

    p.add_argument("object", type=_common.existing_file, metavar="OBJECT",
                   help="a .glb/.gltf/.obj/.ply/.stl mesh file or a .blend file (with --object NAME)")
    p.add_argument("--out", required=True, metavar="NPZ", help="write the feature grid here (compressed .npz)")
    p.add_argument("--object", dest="object_name", metavar="NAME",
                   help="the object to use from a .blend file (or one of several objects in a mesh file)")
    p.add_argument("--views", type=_common.positive_int, default=DEFAULT_VIEW_COUNT, metavar="N",
                   help=f"number of views (default {DEFAULT_VIEW_COUNT})")
    p.add_argument("--resolution", type=_common.positive_int, default=DEFAULT_RESOLUTION, metavar="PX",
                   help=f"square render size in pixels (default {DEFAULT_RESOLUTION}, the ViT's input)")
    p.add_argument("--engine", choices=("cycles", "workbench"), default="cycles",
                   help="renderer: cycles (default; the object's materials as they are) or workbench (fast, "
                        "studio light)")
    p.add_argument("--samples", type=_common.positive_int, default=DEFAULT_SAMPLES, metavar="N",
                   help=f"Cycles samples per pixel (default {DEFAULT_SAMPLES}, adaptive, no denoising)")
    p.add_argument("--render-device", choices=("auto", "cpu", "gpu"), default="auto",
                   help="Cycles device (default auto: a GPU when Cycles finds one, else the CPU)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--clip-weights", metavar="PATH",
                     help="local OpenCLIP ViT-B-16 weights, file or folder (default: $UNIPIXIE_CLIP_WEIGHTS or "
                          "<cache>/clip/ViT-B-16/)")
    src.add_argument("--offline-features", action="store_true",
                     help="use the seeded untrained offline ViT (offline-random-vit-w32, D = 32; NOT CLIP; what the "
                          "models shipped before 2026-11-28 were trained on)")
    from ..extractors import EXTRACTORS

    p.add_argument("--extractor", choices=tuple(EXTRACTORS), metavar="NAME",
                   help="the feature extractor: " + "; ".join(f"{k}: {v[1]}" for k, v in EXTRACTORS.items())
                        + " (default clip, or offline with --offline-features; the appearance ones need "
                          "--engine cycles and no weights)")
    p.add_argument("--device", type=_common.device, default="cpu", help="torch device for features and lifting "
                                                                        "(cpu, cuda, auto; default cpu)")
    p.add_argument("--sheet", metavar="PNG", help="also write a contact sheet of the rendered views")
    p.add_argument("--slices", metavar="PNG", help="also write PCA-coloured slices through the feature grid")
    p.add_argument("--save-views", metavar="NPZ", help="also write the rendered views (unipixie.views/1)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the caches")


def run(args) -> int:
    from pathlib import Path

    from ..errors import UserError
    from ..features import FeatureOptions

    out = Path(args.out).expanduser()
    if out.suffix != ".npz":
        raise UserError(f"--out {args.out}: the feature grid is written as a .npz file; name it ….npz")
    for name in ("sheet", "slices"):
        value = getattr(args, name)
        if value and not value.lower().endswith(".png"):
            raise UserError(f"--{name} {value}: pictures are written as PNG; name it ….png")
    from ..atomic_io import check_writable, refuse_overwriting_inputs

    outputs = [(out, "output")] + [(Path(v).expanduser(), f"--{n.replace('_', '-')} file") for n, v in
                                   (("sheet", args.sheet), ("slices", args.slices), ("save_views", args.save_views)) if v]
    for path, what in outputs:  # before rendering: every output can be written and is not the input
        refuse_overwriting_inputs(path, [args.object], what=what)
        check_writable(path, what=what)
    if args.extractor and args.extractor != "clip" and args.clip_weights:
        raise UserError(f"--clip-weights is for the CLIP extractor, not --extractor {args.extractor}")
    options = FeatureOptions(view_count=args.views, resolution=args.resolution, engine=args.engine,
                             samples=args.samples, render_device=args.render_device,
                             offline=args.offline_features, clip_weights=args.clip_weights, device=args.device,
                             use_cache=not args.no_cache, extractor=args.extractor or "")
    if options.extractor_name == "clip":
        from ..clip_features import resolve_clip_weights

        resolve_clip_weights(args.clip_weights)          # fail before rendering when the weights are missing
    import importlib.util

    if importlib.util.find_spec("bpy") is None:             # rendering needs Blender
        raise UserError("rendering needs Blender's Python module 'bpy' (pip install bpy==5.0.1 with Python 3.11), "
                        "or run inside Blender: blender -b --python-expr \"from unipixie.core.cli import main; "
                        "main()\" -- features ...") from None
    from ..atomic_io import locked

    with locked([p for p, _ in outputs], what="output"):  # a second run writing the same files is refused
        return _render_and_write(args, out, options)


def _render_and_write(args, out, options) -> int:
    from pathlib import Path

    import sys

    from ..errors import UserError
    from ..features import features_file_job, save_feature_slices, save_view_sheet
    from ..jobs import run_job
    from ..progress import Progress
    from ..types import Views

    with Progress(total=100, description="features") as progress:
        result = run_job(features_file_job(args.object, args.object_name, options), progress)
    grid = result.grid
    out.parent.mkdir(parents=True, exist_ok=True)
    grid.save(out)
    views = result.views
    if (args.sheet or args.save_views) and views is None:
        if result.views_path is None:
            raise UserError("the rendered views are not in the cache any more; run again with --no-cache")
        views = Views.load(result.views_path)
    if args.sheet:
        save_view_sheet(views, Path(args.sheet).expanduser())
    if args.slices:
        save_feature_slices(grid, Path(args.slices).expanduser())
    if args.save_views:
        views.save(Path(args.save_views).expanduser())
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    from ..extractors import label as extractor_label

    label = extractor_label(grid.feature_model)
    print(f"{out}: {int(grid.occupancy.sum())} occupied voxels of {grid.geometry.resolution}³, features "
          f"{grid.features.shape[0]}×{grid.dim} from {label}; "
          f"{100 * grid.meta.get('painted_fraction_of_surface', 0):.1f} % of surface voxels seen"
          + (" (from the cache)" if result.cache_hit else ""))
    if result.timings and not result.cache_hit:
        print("seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in result.timings.items()))
    for name, value in (("sheet", args.sheet), ("slices", args.slices), ("views", args.save_views)):
        if value:
            print(f"{name}: {value}")
    return 0
