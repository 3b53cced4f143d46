"""``unipixie dataset build|ground-truth|card|pack|unpack``: the procedural training set, its ground truth, its card,
and its transfer pack."""

from __future__ import annotations

NAME = "dataset"
HELP = "build the procedural dataset (sharded, resumable), write its card, pack it for a GPU machine"
EXAMPLES = """  unipixie dataset build data/pmv --count 500                      # everything, one process
  unipixie dataset build data/pmv --count 500 --shard 0/4          # one of four farm jobs (any scheduler)
  unipixie dataset build data/tiny --count 6 --resolution 16 --views 2 --render-resolution 64 --tiny-ground-truth
  unipixie dataset ground-truth data/pmv --shard 0/4              # the full ground truth over a tiny-ground-truth build
  unipixie dataset card data/pmv                                   # refresh split.json, dataset.json, CARD.md
  unipixie dataset pack data/pmv packs/pmv --part-mb 50            # compact pack in parts of <= 50 MB
  unipixie dataset unpack packs/pmv data/pmv_samples               # on the GPU machine (torch + numpy only)"""


def add_arguments(p):
    from ...core.commands import _common

    sub = p.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="build objects 0..N-1 of this shard (finished objects are skipped)",
                       description="Generate procedural objects, render and lift their features, simulate MPM "
                                   "ground truth at α = 0 and 1 and fit LBS and spring-mass parameters to it. "
                                   "Every option below is recorded in OUT/build.json; later shards and resumes "
                                   "must use the same.")
    b.add_argument("out", metavar="OUT", help="dataset directory (created)")
    b.add_argument("--count", type=_common.positive_int, required=True, metavar="N", help="objects in the whole dataset")
    b.add_argument("--shard", type=_common.shard, default=(0, 1), metavar="i/n",
                   help="build only objects with index ≡ i (mod n) (default 0/1 = all)")
    b.add_argument("--seed", type=_common.seed, default=0, help="base seed (default 0)")
    b.add_argument("--classes", metavar="A,B,...", help="semantic classes to cycle through (default: all ten)")
    b.add_argument("--resolution", type=_common.positive_int, default=64, metavar="R", help="grid voxels per side (default 64)")
    b.add_argument("--views", type=_common.positive_int, default=8, metavar="N", help="rendered views per object (default 8)")
    b.add_argument("--render-resolution", type=_common.positive_int, default=224, metavar="PX",
                   help="square render size (default 224)")
    b.add_argument("--engine", choices=("workbench", "cycles"), default="workbench",
                   help="renderer for the features (default workbench: fast, texture colours)")
    b.add_argument("--samples", type=_common.positive_int, default=8, help="Cycles samples (with --engine cycles)")
    src = b.add_mutually_exclusive_group()
    src.add_argument("--clip-weights", metavar="PATH", help="use CLIP ViT-B-16 from these local weights instead of the "
                                                            "offline extractor")
    src.add_argument("--offline-features", action="store_true", default=True,
                     help="the seeded untrained offline ViT (offline-random-vit-w32, NOT CLIP; the default)")
    from ...core.extractors import EXTRACTORS

    b.add_argument("--extractor", choices=tuple(EXTRACTORS), metavar="NAME",
                     help="build with this feature extractor (" + ", ".join(EXTRACTORS) + "); appearance and "
                          "appearance+vit read Cycles' render passes (base colour, roughness, metallic, normal): "
                          "use them with --engine cycles")
    b.add_argument("--split", default="0.8,0.1,0.1", metavar="TRAIN,VAL,TEST", help="split fractions (default 0.8,0.1,0.1)")
    _add_ground_truth_arguments(b)
    b.add_argument("--device", type=_common.device, default="cpu",
                   help="Warp device of the solvers and torch device of the features (cpu, cuda; default cpu)")
    b.add_argument("--retry-failed", action="store_true", help="build objects recorded as failed again")
    b.add_argument("--only-splits", metavar="NAMES", default=None,
                   help="build only the objects of these splits among 0..N-1, e.g. 'test' (Table 2's objects with "
                        "the full ground truth: --count 200 --only-splits test builds the first 20 test objects)")

    g = sub.add_parser("ground-truth", help="give built objects another ground truth (e.g. the full one over a "
                                             "--tiny-ground-truth build) without rendering again",
                       description="Generate each finished object again from the build's seed, simulate and fit it "
                                   "with these ground-truth settings and replace its ground_truth.npz, its sample's "
                                   "LBS and spring-mass targets and its record (resumable: objects already at the "
                                   "target are skipped).  With --portable-out, compute from DIR/build.json alone "
                                   "into OUT/<object_id>.npz (on another machine); --apply FROM brings such files "
                                   "into DIR.  build.json takes the new settings once every object has them.")
    g.add_argument("dir", metavar="DIR", help="built dataset (with --portable-out: a folder with its build.json)")
    g.add_argument("--shard", type=_common.shard, default=(0, 1), metavar="i/n",
                   help="only objects with index ≡ i (mod n) (default 0/1 = all)")
    g.add_argument("--splits", metavar="NAMES", default=None, help="only these splits, e.g. 'train,val' (default all)")
    _add_ground_truth_arguments(g)
    g.add_argument("--device", type=_common.device, default="cpu", help="Warp device of the solvers (default cpu)")
    mode = g.add_mutually_exclusive_group()
    mode.add_argument("--portable-out", metavar="OUT", help="compute objects 0..--count-1 into OUT/<object_id>.npz "
                                                            "from DIR/build.json alone (no dataset needed)")
    mode.add_argument("--apply", metavar="FROM", help="apply the files a --portable-out run wrote to DIR's objects")
    g.add_argument("--count", type=_common.positive_int, metavar="N", help="objects in the whole dataset (--portable-out)")
    g.add_argument("--keep-trajectories", action="store_true",
                   help="with --portable-out: keep the MPM motions in the files (0.3–0.7 MB an object instead of "
                        "about 20 kB; the evaluation's Table 2 needs them)")

    c = sub.add_parser("card", help="rescan a dataset: write split.json, dataset.json and CARD.md")
    c.add_argument("dir", metavar="DIR")

    k = sub.add_parser("pack", help="write a compact pack of a built dataset for a torch-only GPU machine")
    k.add_argument("dir", metavar="DIR", help="built dataset")
    k.add_argument("out", metavar="PACK", help="pack directory (index.json + part files)")
    k.add_argument("--part-mb", type=float, default=50.0, help="largest part file in MB (default 50)")
    k.add_argument("--splits", default="train,val,test", help="splits to pack (default all)")

    u = sub.add_parser("unpack", help="turn a pack back into training samples (needs only torch and numpy)")
    u.add_argument("pack", metavar="PACK")
    u.add_argument("out", metavar="OUT", help="directory for samples/*.npz and split.json")


def _add_ground_truth_arguments(p):
    """The ground-truth settings (shared by ``build`` and ``ground-truth``)."""
    from ...core.commands import _common

    p.add_argument("--frames", type=_common.positive_int, default=30, help="frames of the ground-truth clip (default 30)")
    p.add_argument("--fps", type=_common.positive_number, default=60.0, help="frame rate of the clip (default 60)")
    p.add_argument("--cells-across", type=_common.positive_int, default=12, help="MPM cells across the object (default 12)")
    p.add_argument("--wave-speed-per-size", type=_common.positive_number, default=400.0, metavar="PER_S",
                   help="cap on the simulated elastic wave speed, in object sizes per second (default 400)")
    p.add_argument("--tracked-points", type=_common.non_negative_int, default=1024, help="tracked mesh vertices (default 1024; 0 = all)")
    p.add_argument("--spring-anchors", type=_common.positive_int, default=256,
                   help="spring-mass anchors N_a (default 256; train the model with --set spring_anchors=N_a)")
    p.add_argument("--lbs-cubature", type=_common.positive_int, default=200, help="LBS cubature points (default 200)")
    p.add_argument("--fit-evaluations", type=_common.positive_int, default=5,
                   help="simulations per end of each test-time fit (default 5)")
    p.add_argument("--tiny-ground-truth", action="store_true",
                   help="tiny ground truth for tests (6 frames, 6 cells, 64 tracked points, 32 anchors, 3 fit simulations)")


def _gt_settings(args):
    from ..ground_truth import GroundTruthSettings

    if args.tiny_ground_truth:
        return GroundTruthSettings(frames=6, cells_across=6, min_particles=100, tracked_points=64, spring_anchors=32,
                                   lbs_cubature_points=32, lbs_mass_samples=300, fit_evaluations=3,
                                   wave_speed_per_size=100.0, device="cpu" if args.device == "auto" else args.device)
    return GroundTruthSettings(frames=args.frames, fps=args.fps, cells_across=args.cells_across,
                               wave_speed_per_size=args.wave_speed_per_size, tracked_points=args.tracked_points,
                               spring_anchors=args.spring_anchors, lbs_cubature_points=args.lbs_cubature,
                               fit_evaluations=args.fit_evaluations, device=args.device)


def run(args) -> int:
    from ...core.errors import UserError

    action = args.dataset_command
    if action == "build":
        from .. import dataset
        from ...core.progress import Progress

        try:
            split = tuple(float(x) for x in args.split.split(","))
        except ValueError:
            raise UserError(f"--split {args.split!r}: expected three numbers TRAIN,VAL,TEST") from None
        classes = tuple(c.strip() for c in args.classes.split(",")) if args.classes is not None else None
        if classes is not None and not all(classes):
            raise UserError(f"--classes {args.classes!r}: an empty class name; give names separated by commas (or "
                            "leave --classes out for all ten)")
        kw = {"classes": classes} if classes else {}
        if args.extractor and args.extractor != "clip" and args.clip_weights:
            raise UserError(f"--clip-weights is for the CLIP extractor, not --extractor {args.extractor}")
        settings = dataset.BuildSettings(seed=args.seed, resolution=args.resolution, views=args.views,
                                         render_resolution=args.render_resolution, engine=args.engine,
                                         samples=args.samples,
                                         offline_features=args.clip_weights is None and not args.extractor,
                                         clip_weights=args.clip_weights,
                                         feature_device="cpu" if args.device == "auto" else args.device,
                                         split=split, ground_truth=_gt_settings(args).to_dict(),
                                         extractor=args.extractor or "", **kw)
        import importlib.util

        if importlib.util.find_spec("bpy") is None:
            raise UserError("building a dataset renders with Blender: it needs the 'bpy' module "
                            "(pip install bpy==5.0.1 with Python 3.11)")
        splits = None if args.only_splits is None else tuple(x.strip() for x in args.only_splits.split(",") if x.strip())
        n = len(dataset.shard_indices(args.count, args.shard, splits, split))
        with Progress(total=n, description=f"dataset {args.shard[0]}/{args.shard[1]}") as progress:
            summary = dataset.build(args.out, args.count, settings, shard=args.shard,
                                    retry_failed=args.retry_failed, progress=progress, splits=splits)
        print(f"built {len(summary['built'])}, skipped {len(summary['skipped'])} (already there), failed "
              f"{len(summary['failed'])} in {summary['seconds']:.0f} s; card: {args.out}/CARD.md")
        for oid in summary["failed"]:
            print(f"  failed: {oid} (see {args.out}/objects/{oid}/record.json)")
        return 1 if summary["failed"] else 0
    if action == "ground-truth":
        from .. import ground_truth_rebuild as rebuild

        splits = None if args.splits is None else tuple(x.strip() for x in args.splits.split(",") if x.strip())
        if args.apply:
            summary = rebuild.apply_portable(args.dir, args.apply)
            print(f"applied {len(summary['applied'])} ground truths to {args.dir}"
                  + (f"; {len(summary['unknown'])} files name no finished object: {', '.join(summary['unknown'][:5])}"
                     if summary["unknown"] else "")
                  + ("; build.json now names these settings" if summary["promoted"] else
                     "; build.json keeps its settings until every object has the new ones"))
            return 1 if summary["unknown"] else 0
        if args.portable_out:
            if args.count is None:
                raise UserError("--portable-out needs --count N (objects in the whole dataset)")
            summary = rebuild.compute_portable(f"{args.dir}/build.json", args.portable_out, args.count,
                                               _gt_settings(args), shard=args.shard, splits=splits,
                                               keep_trajectories=args.keep_trajectories)
            print(f"computed {len(summary['written'])}, skipped {len(summary['skipped'])} (already there), failed "
                  f"{len(summary['failed'])} in {summary['seconds']:.0f} s into {args.portable_out}")
        else:
            summary = rebuild.rebuild(args.dir, _gt_settings(args), shard=args.shard, splits=splits)
            print(f"rebuilt {len(summary['rebuilt'])}, skipped {len(summary['skipped'])} (already at these settings), "
                  f"failed {len(summary['failed'])} in {summary['seconds']:.0f} s"
                  + ("; build.json now names these settings" if summary["promoted"] else ""))
        for oid, err in summary["failed"].items():
            print(f"  failed: {oid}: {err}")
        return 1 if summary["failed"] else 0
    if action == "card":
        from .. import dataset

        card = dataset.write_card(args.dir)
        print(f"{card['objects']} objects ({', '.join(f'{k} {v}' for k, v in card['split_counts'].items())}), "
              f"{card['failed']} failed; wrote {args.dir}/CARD.md, dataset.json, split.json")
        return 0
    if action == "pack":
        from .. import pack

        splits = tuple(s.strip() for s in args.splits.split(",") if s.strip())
        info = pack.write_pack(args.dir, args.out, part_bytes=int(args.part_mb * 1e6), splits=splits)
        print(f"packed {info['objects']} objects into {len(info['parts'])} part(s), {info['bytes'] / 1e6:.1f} MB "
              f"({info['bytes'] / max(info['objects'], 1) / 1e3:.0f} kB per object) in {args.out}")
        return 0
    if action == "unpack":
        from .. import pack

        n = pack.unpack(args.pack, args.out)
        print(f"wrote {n} training samples and split.json to {args.out}")
        return 0
    raise UserError(f"unknown dataset action {action!r}")
