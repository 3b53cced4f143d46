"""``unipixie demo``: the whole pipeline on built-in objects (README's main job), and the diagnosis demo.

``unipixie demo`` builds a potted plant and a rubber duck, renders them, extracts features, predicts
their materials with the default model, bakes MPM at α = 0, 0.5, 1, one LBS and one spring-mass bake,
and saves ``demo/unipixie_demo.blend`` with a contact sheet, field pictures and a summary
(:mod:`unipixie.core.demo`).  ``--quick`` does less of everything (CI).

``unipixie demo --diagnose``: a built-in measurement with a hidden physical effect is diagnosed step
by step (error, where it fails, the ranking of effects, the effect added, the error falling) and the
report is written (:mod:`unipixie.core.diagnosis.demo`).
"""

from __future__ import annotations

from ...solvers.registry import SOLVER_NAMES
from ._common import device as device_type

NAME = "demo"
HELP = ("the whole pipeline on built-in objects: features, material prediction, MPM/LBS/spring-mass bakes, "
        "a .blend and pictures (--diagnose: find a hidden physical effect in a built-in measurement)")
EXAMPLES = """  unipixie demo                                  # everything, into ./demo (about 10-15 min on a 2-core CPU)
  unipixie demo --quick --out /tmp/demo          # fewer views, frames and coarser solvers
  unipixie demo --checkpoint runs/small          # another model than the shipped models/default
  unipixie demo --diagnose
  unipixie demo --diagnose --out demo-report/ --solver spring_mass"""

DEFAULT_OUT = "demo"
DEFAULT_DIAGNOSIS_OUT = "unipixie-demo-diagnosis"


def add_arguments(p):
    p.add_argument("--quick", action="store_true",
                   help="fewer views, a 3-value alpha sweep, fewer frames, coarser solvers (a CI check)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help=f"output directory (default: ./{DEFAULT_OUT}; with --diagnose ./{DEFAULT_DIAGNOSIS_OUT})")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="model checkpoint directory (default: the shipped models/default)")
    p.add_argument("--device", type=device_type, default="cpu",
                   help="cpu (default) or cuda: where features, the model and the solvers run")
    p.add_argument("--diagnose", action="store_true",
                   help="instead: diagnose a built-in measurement with a hidden effect, printing every step")
    p.add_argument("--solver", default="spring_mass", choices=SOLVER_NAMES,
                   help="with --diagnose: the solver the diagnosis uses (default spring_mass)")


def run(args) -> int:
    from ..errors import UserError
    from ..progress import Progress
    from ...solvers.warp_runtime import resolve_device

    if args.diagnose:
        if args.quick or args.checkpoint:
            raise UserError("--quick and --checkpoint apply to the pipeline demo, not to --diagnose")
        from ..diagnosis.demo import run_demo

        with Progress(total=100, description="demo") as progress:
            run_demo(args.out or DEFAULT_DIAGNOSIS_OUT, solver=args.solver, device=resolve_device(args.device),
                     progress=progress)
        return 0
    import importlib.util

    if importlib.util.find_spec("bpy") is None:
        raise UserError("the demo renders and bakes with Blender: install the bpy module (./setup.sh does) or run "
                        "it inside Blender: blender -b --python-expr \"import bl_ext.user_default.unipixie.cli as c; "
                        "c.main()\" -- demo")
    from ..demo import run_demo

    import sys

    device = resolve_device(args.device)
    with Progress(total=100, description="demo") as progress:
        result = run_demo(args.out or DEFAULT_OUT, quick=args.quick, checkpoint=args.checkpoint, device=device,
                          progress=progress)
    if result.failed:
        print(f"unipixie demo: {len(result.failed)} bake(s) failed (see above and {result.out_dir}/summary.json)",
              file=sys.stderr)
        return 3
    return 0
