"""``unipixie demo``: guided runs on built-in data.

For now this build has one guided run, ``unipixie demo --diagnose``: a built-in measurement
with a hidden physical effect is diagnosed step by step (error, where it fails, the ranking
of effects, the effect added, the error falling) and the report is written.
"""

from __future__ import annotations

from ._common import device as device_type

NAME = "demo"
HELP = "guided runs on built-in data: --diagnose finds a hidden physical effect in a built-in measurement"
EXAMPLES = """  unipixie demo --diagnose
  unipixie demo --diagnose --out demo-report/ --solver spring_mass
  unipixie demo --diagnose --solver mpm --device cuda"""


def add_arguments(p):
    p.add_argument("--diagnose", action="store_true",
                   help="diagnose a built-in measurement with a hidden effect, printing every step")
    p.add_argument("--out", default="unipixie-demo-diagnosis", metavar="DIR",
                   help="where the measurement and the report go (default: ./unipixie-demo-diagnosis)")
    p.add_argument("--solver", default="spring_mass", choices=("mpm", "lbs", "spring_mass"),
                   help="solver the diagnosis uses (default spring_mass)")
    p.add_argument("--device", type=device_type, default="cpu")


def run(args) -> int:
    from ..errors import UserError

    if not args.diagnose:
        raise UserError("this build has the diagnosis demo only: run 'unipixie demo --diagnose'")
    from ..diagnosis.demo import run_demo
    from ..progress import Progress
    from ...solvers.warp_runtime import resolve_device

    with Progress(total=100, description="demo") as progress:
        run_demo(args.out, solver=args.solver, device=resolve_device(args.device), progress=progress)
    return 0
