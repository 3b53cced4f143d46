"""``unipixie bake``: simulate objects of a .blend and bake their motion into keyframes, headless."""

from __future__ import annotations

import argparse
import json

from ...solvers.registry import SOLVER_NAMES
from . import _common

NAME = "bake"
HELP = "simulate objects of a .blend (MPM, LBS, spring-mass) and save them baked to keyframes"
EXAMPLES = """  unipixie bake scene.blend --object Jelly --solver mpm --alpha 0.5 --frames 1-12 --out baked.blend
      (renders, extracts features and predicts whatever the object lacks, cached for the next run)
  unipixie bake scene.blend --object Jelly --solver spring_mass --E 2e5 --nu 0.3 --density 800 --frames 1-120 --out baked.blend
  unipixie bake scene.blend --object 'Rock*' --object Plant --solver mpm --material-file field.npz --out 'baked_{object}.blend'
  unipixie bake scene.blend --object Jelly --alpha 0,0.5,1 --features jelly_grid.npz --effects linear_drag:c=0.5 --device cuda --out 'jelly_a{alpha}.blend'
  unipixie bake --manifest jobs.json --shard 3/8           (a farm task: the 4th of 8 parts)
  blender -b --python-expr "import bl_ext.user_default.unipixie.cli as c; c.main()" -- bake scene.blend --object Jelly --out baked.blend"""


def _vec3(text: str):
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers x,y,z, got {text!r}") from None
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers x,y,z, got {text!r}")
    return v


def _alphas(text: str):
    """``--alpha A[,B,...]``: numbers, each checked by the one α check (:func:`unipixie.core.types.check_alpha`)."""
    from ..errors import UserError
    from ..types import check_alpha

    out = []
    for part in text.split(","):
        try:
            out.append(check_alpha(_common._number(part.strip(), float, lambda x: True, "a number in [0, 1]")))
        except UserError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return out


def _positive(text: str) -> float:
    return _common._number(text, float, lambda x: x > 0, "a positive number", show_text=True)


def _json_object(text: str) -> dict:
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"--settings must be a JSON object ({exc})") from None
    if not isinstance(d, dict):
        raise argparse.ArgumentTypeError("--settings must be a JSON object, e.g. '{\"cells_across\": 24}'")
    return d


def add_arguments(p):
    p.add_argument("scene", nargs="?", metavar="SCENE.blend", help="the .blend holding the objects (not with --manifest)")
    p.add_argument("--object", action="append", default=[], metavar="NAME",
                   help="object to bake (repeatable; shell wildcards such as 'Rock*' allowed)")
    p.add_argument("--out", metavar="OUT.blend",
                   help="where to save the baked scene; may contain {object}, {alpha}, {frames}, {start}, {end}, "
                        "{solver}, {scene}, {job}. Mesh Cache files go to OUT_unipixie/ next to it")
    p.add_argument("--solver", default="mpm", help=f"{', '.join(SOLVER_NAMES)} (default mpm)")
    p.add_argument("--alpha", type=_alphas, metavar="A[,B,...]",
                   help="soft-to-stiff control in [0, 1] for the model's material (a list bakes a batch)")
    p.add_argument("--frames", metavar="START-END[,START-END]",
                   help="frames to bake (default: the scene's range); several ranges bake a batch")
    p.add_argument("--effects", nargs="+", action="extend", default=[], metavar="EFFECT",
                   help="effects such as linear_drag:c=0.5 wind:acceleration=0,1,0 (see 'unipixie diagnose')")
    p.add_argument("--device", type=_common.device, default=None, help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--shard", type=_common.shard, metavar="I/N", help="run only part I of N of the batch (0-based)")
    p.add_argument("--manifest", type=_common.existing_file, metavar="JOBS.json",
                   help="a job manifest (format unipixie.bake-manifest/1, see docs/baking.md)")
    p.add_argument("--list", action="store_true", help="print the jobs (of this shard) and exit")
    m = p.add_argument_group("material: one source — the model at --alpha [--features --checkpoint --seed], "
                             "--material-file, or --E/--nu/--density/--material-class (default: the object's "
                             "UniPixie settings)")
    m.add_argument("--features", metavar="GRID.npz",
                   help="the object's feature grid ('unipixie features'): the model predicts the material at --alpha "
                        "from it (without it, the object's own features are used or computed)")
    m.add_argument("--checkpoint", metavar="DIR", help="the model for --alpha (default: the shipped model)")
    m.add_argument("--seed", type=_common.seed, default=0, help="the model's noise seed (default 0)")
    m.add_argument("--solver-heads", action="store_true",
                   help="LBS and spring-mass take their own heads' material (LBS E/ν, spring stiffnesses) instead of "
                        "the continuum field all solvers share by default (one material, one motion)")
    m.add_argument("--no-auto", action="store_true",
                   help="compute nothing before baking: --alpha then needs --features or a prediction recorded on "
                        "the object (the panel's Predict, saved in the .blend); without --no-auto the missing steps "
                        "(render views, features, prediction) run first, as the panel's Run all, and are cached")
    m.add_argument("--material-file", metavar="FIELD.npz", help="a material field (unipixie.material_field/1)")
    m.add_argument("--E", type=_positive, metavar="PA", help="Young's modulus of a homogeneous material, Pa")
    m.add_argument("--nu", type=float, metavar="NU", help="Poisson's ratio of a homogeneous material")
    m.add_argument("--density", type=_positive, metavar="KG_M3", help="density of a homogeneous material, kg/m³")
    m.add_argument("--material-class", metavar="CLASS", help="material class of a homogeneous material (jelly, metal, ...)")
    s = p.add_argument_group("scenario (default: the scene's gravity and the object's UniPixie settings)")
    s.add_argument("--ground", metavar="OBJECT", help="the top of this object is the ground plane")
    s.add_argument("--ground-height", type=float, metavar="Z", help="the ground is the plane z = Z (metres)")
    s.add_argument("--no-ground", action="store_true", help="no ground plane")
    s.add_argument("--clamp", metavar="OBJECT", help="hold the material inside this object's bounding box fixed")
    s.add_argument("--clamp-group", metavar="GROUP", help="hold the material inside this vertex group's bounds fixed")
    s.add_argument("--gravity", type=_vec3, metavar="X,Y,Z", help="gravity in m/s² (default: the scene's)")
    s.add_argument("--initial-velocity", type=_vec3, metavar="X,Y,Z", help="initial velocity, m/s")
    s.add_argument("--initial-angular-velocity", type=_vec3, metavar="X,Y,Z", help="initial angular velocity, rad/s")
    o = p.add_argument_group("output")
    o.add_argument("--output", default="auto", choices=["auto", "shape_keys", "mesh_cache", "armature"],
                   help="how the motion is stored (default auto: armature for LBS, else shape keys or a Mesh Cache "
                        "for large bakes)")
    o.add_argument("--interpolation", default="LINEAR", type=str.upper, choices=["LINEAR", "CONSTANT"],
                   help="between frames (both are exact at integer frames)")
    o.add_argument("--particles", action="store_true", help="MPM: also make a particle object with E, class, velocity")
    o.add_argument("--settings", type=_json_object, metavar="JSON", help="solver settings, e.g. '{\"cells_across\": 24}'")
    o.add_argument("--allow-long", action="store_true",
                   help="bake even when the up-front cost estimate (frames × substeps) passes the long-job limit")


def _scenario_overrides(args) -> dict:
    sc: dict = {}
    grounds = [x for x in (args.ground, args.ground_height, args.no_ground or None) if x is not None]
    if len(grounds) > 1:
        from ..errors import UserError

        raise UserError("give only one of --ground, --ground-height and --no-ground")
    if args.ground:
        sc["ground"] = args.ground
    elif args.ground_height is not None:
        sc["ground"] = {"height": args.ground_height}
    elif args.no_ground:
        sc["ground"] = None
    if args.clamp:
        sc["clamp"] = args.clamp
    if args.clamp_group:
        sc["clamp_group"] = args.clamp_group
    for key in ("gravity", "initial_velocity", "initial_angular_velocity"):
        if getattr(args, key) is not None:
            sc[key] = getattr(args, key)
    return sc


def jobs_from_args(args):
    """The batch the arguments describe (before sharding)."""
    from .. import bake
    from ..errors import UserError

    if args.manifest:
        if args.scene or args.object or args.out:
            raise UserError("with --manifest, give the scenes, objects and outputs in the manifest, not on the command line")
        jobs = bake.load_manifest(args.manifest, resolve=_object_names)
        if args.device:
            for j in jobs:
                j.device = args.device
        return jobs
    if not args.scene:
        raise UserError("give a scene (SCENE.blend) or --manifest")
    if not args.out:
        raise UserError("give --out OUT.blend (where to save the baked scene)")
    homogeneous = [v is not None for v in (args.E, args.nu, args.density, args.material_class)]
    _check_one_material_source(args)
    if (args.features or args.checkpoint) and not args.alpha:
        raise UserError(f"{'--features' if args.features else '--checkpoint'} needs --alpha: the model predicts the "
                        "material at α")
    material = None
    if args.alpha:
        material = bake.ModelSource(features=str(args.features or ""), checkpoint=args.checkpoint or "",
                                    seed=args.seed, device=args.device or "cpu",
                                    solver_heads=bool(getattr(args, "solver_heads", False)))
    elif args.material_file:
        material = bake.FieldFileSource(str(args.material_file))
    elif any(homogeneous):
        d = bake.DEFAULT_HOMOGENEOUS
        material = bake.HomogeneousSource(E=args.E if args.E is not None else d["E"],
                                          nu=args.nu if args.nu is not None else d["nu"],
                                          density=args.density if args.density is not None else d["density"],
                                          material=args.material_class or d["material"])
    frame_ranges = bake.parse_frame_list(args.frames) if args.frames else [None]
    return bake.expand_jobs(str(args.scene), args.object, args.out, solver=args.solver,
                            alphas=args.alpha or [None], frame_ranges=frame_ranges, effects=list(args.effects),
                            device=args.device or "cpu", material=material, output=args.output,
                            interpolation=args.interpolation, particles=args.particles,
                            solver_settings=args.settings, scenario=_scenario_overrides(args), resolve=_object_names)


def _check_one_material_source(args) -> None:
    """Flags of more than one material source are refused, naming them and the rule (:data:`bake.MATERIAL_RULE`)."""
    from ..bake import MATERIAL_RULE
    from ..errors import UserError

    groups = [[f for f, v in (("--alpha", args.alpha), ("--features", args.features), ("--checkpoint", args.checkpoint))
               if v],
              ["--material-file"] if args.material_file else [],
              [f for f, v in (("--E", args.E), ("--nu", args.nu), ("--density", args.density),
                              ("--material-class", args.material_class)) if v is not None]]
    used = [g for g in groups if g]
    if len(used) > 1:
        raise UserError(f"{' with '.join('/'.join(g) for g in used)}: {MATERIAL_RULE}")


def _object_names(scene: str):
    from ..blender_io.bake_jobs import blend_object_names

    return blend_object_names(scene)


def run(args) -> int:
    from .. import bake
    from ..progress import Progress

    jobs = jobs_from_args(args)
    for j in jobs:  # options are checked before any scene is opened
        bake.BakeOptions(solver=j.solver, frames=j.frames or (1, 2), alpha=j.alpha, effects=j.effects,
                         output=j.output, interpolation=j.interpolation, particles=j.particles,
                         armature_tolerance=j.armature_tolerance)
    from ..cost import frames_estimate

    for j in jobs:  # absurd frame counts are refused before any scene is opened (the full estimate follows)
        if j.frames is not None:
            frames_estimate(f"baking '{j.object}' over frames {j.frames.start}-{j.frames.end}", j.frames.count).check(
                args.allow_long, remedy="bake fewer frames")
    groups = bake.group_jobs(jobs)
    mine = bake.shard_groups(groups, args.shard)
    tag = f"shard {args.shard[0]}/{args.shard[1]}: " if args.shard else ""
    mine_jobs = [j for g in mine for j in g]
    if args.list:
        print(f"{tag}{len(mine_jobs)} of {len(jobs)} job(s) in {len(mine)} of {len(groups)} output file(s)")
        for j in mine_jobs:
            print(f"  {j.describe()}")
        return 0
    if not mine_jobs:
        print(f"{tag}nothing to do ({len(groups)} output file(s) for {args.shard[1] if args.shard else 1} shard(s))")
        return 0
    from ..blender_io.bake_jobs import run_jobs

    with Progress(total=len(mine_jobs), description="bake") as progress:
        reports = run_jobs(mine_jobs, progress=progress, allow_long=args.allow_long, auto=not args.no_auto)
    print(f"{tag}baked {len(reports)} object(s) into {len(mine)} file(s)")
    return 0
