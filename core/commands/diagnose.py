"""``unipixie diagnose``: compare a simulation with a measurement and find the missing physical effect."""

from __future__ import annotations

import argparse

from ...solvers.registry import SOLVER_NAMES
from ._common import device as device_type
from ._common import existing_file
from ._common import non_negative_seconds
from ..diagnosis.resolution import DEFAULT_BUDGET_S

NAME = "diagnose"
HELP = "compare the model with a measurement, find the missing physical effect, add it, watch the error fall"
EXAMPLES = """  unipixie diagnose drop.npz --solver spring_mass --out report/
  unipixie diagnose drop.npz --solver mpm --device cuda --out report/ --max-additions 2
  unipixie diagnose tracks.csv --scenario tracks.json --solver spring_mass --out report/
  unipixie diagnose drop.npz --effects-on linear_drag:c=0.2 --add quadratic_drag --out report/
  (writes report/diagnosis.json, report/diagnosis.html and the pictures)"""


def parse_settings(items) -> dict:
    """``["anchors=128", "cfl=0.3", "dx=none"]`` -> ``{"anchors": 128, "cfl": 0.3, "dx": None}``."""
    from ..errors import UserError

    out = {}
    for item in items or []:
        if "=" not in item:
            raise UserError(f"--setting {item!r}: expected key=value")
        k, v = (s.strip() for s in item.split("=", 1))
        low = v.lower()
        if low in ("none", "null"):
            val = None
        elif low in ("true", "false"):
            val = low == "true"
        else:
            try:
                val = int(v)
            except ValueError:
                try:
                    val = float(v)
                except ValueError:
                    val = v
        out[k] = val
    return out


def add_measurement_arguments(p) -> None:
    """Options shared by commands that read a measurement (CSV scenario, material override)."""
    p.add_argument("--scenario", metavar="JSON", help="scenario JSON file for a CSV measurement "
                                                      "(default: NAME.json beside NAME.csv)")
    p.add_argument("--E", type=float, metavar="PA", help="Young's modulus the model believes (overrides the file)")
    p.add_argument("--nu", type=float, help="Poisson's ratio the model believes (overrides the file)")
    p.add_argument("--density", type=float, metavar="KG_M3", help="density the model believes (overrides the file)")


def load_measurement(args):
    """The measurement named by ``args.measurement`` with the command line's overrides applied."""
    from ..errors import UserError
    from ..measurement import MeasuredMaterial, load

    kwargs = {}
    if getattr(args, "scenario", None):
        if str(args.measurement).lower().endswith(".npz"):
            raise UserError("--scenario applies to CSV measurements (a .npz file carries its own scenario)")
        kwargs["scenario"] = args.scenario
    m = load(args.measurement, **kwargs)
    over = {k: getattr(args, k, None) for k in ("E", "nu", "density")}
    if any(v is not None for v in over.values()):
        base = m.material
        if base is None and any(v is None for v in over.values()):
            missing = [f"--{k}" for k, v in over.items() if v is None]
            raise UserError(f"the measurement states no material; also give {', '.join(missing)}")
        vals = {k: (v if v is not None else getattr(base, k)) for k, v in over.items()}
        m.material = MeasuredMaterial(vals["E"], vals["nu"], vals["density"],
                                      base.material_class if base is not None else "jelly")
        m.__post_init__()
    return m


def add_arguments(p):
    p.add_argument("measurement", type=existing_file, metavar="MEASUREMENT",
                   help="measurement file: .npz (unipixie.measurement/1) or .csv (t,id,x,y,z)")
    p.add_argument("--solver", default="auto", choices=("auto",) + SOLVER_NAMES,
                   help="solver that simulates the model (default auto: the most faithful the device affords, "
                        "mpm on a GPU, spring_mass on the CPU; docs/diagnosis.md)")
    p.add_argument("--out", required=True, metavar="DIR", help="directory for diagnosis.json, pictures and HTML")
    p.add_argument("--effects-on", nargs="*", default=[], metavar="EFFECT",
                   help="effects already on in the current model, e.g. linear_drag:c=0.2")
    p.add_argument("--add", action="append", default=[], metavar="EFFECT",
                   help="add this effect (fitted) instead of the top-ranked one; repeat for later rounds")
    p.add_argument("--max-additions", type=int, default=3, metavar="N",
                   help="add at most N effects (0: only rank the candidates; default 3)")
    p.add_argument("--candidates", metavar="NAMES", help="comma-separated effects to try (default: all)")
    p.add_argument("--device", type=device_type, default="cpu", help="cpu (default), cuda or cuda:N")
    p.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE",
                   help="solver setting, e.g. anchors=256 (spring_mass) or cells_across=24 (mpm); repeatable")
    p.add_argument("--parallel", action=argparse.BooleanOptionalAction, default=None,
                   help="fit the candidate effects side by side with their simulations batched together "
                        "(default: on a GPU with mpm/lbs and with spring_mass on the CPU, whose runs share the cores; "
                        "off for mpm/lbs on the CPU)")
    p.add_argument("--resolution-budget", type=non_negative_seconds, default=DEFAULT_BUDGET_S, metavar="SECONDS",
                   help="seconds of simulation the rest of the diagnosis may spend on a finer model when the "
                        f"resolution check finds the fitted base model moving by more than the noise (default "
                        f"{DEFAULT_BUDGET_S:g}: "
                        "decided by this machine's speed; 0: never refine, enforce the coarse model's floor, the same "
                        "verdict on every machine; inf: always refine)")
    p.add_argument("--keep-outliers", action="store_true",
                   help="keep every sample: by default samples a tracker got wrong (a point centimetres off its "
                        "neighbours' motion at one instant) are found from the tracks and treated as not observed")
    p.add_argument("--quiet", action="store_true", help="print only the result")
    p.add_argument("--allow-long", action="store_true",
                   help="run even when the times look like milliseconds or the estimated cost passes the long-job "
                        "limit (see docs/diagnosis.md)")
    add_measurement_arguments(p)


def run(args) -> int:
    from ..diagnosis import diagnose
    from ..errors import UserError
    from ..progress import Progress
    from ...solvers.warp_runtime import resolve_device

    if args.max_additions < 0:
        raise UserError("--max-additions must be 0 or more")
    m = load_measurement(args)
    device = resolve_device(args.device)
    solver = diagnose.default_solver(device) if args.solver == "auto" else args.solver
    cands = None
    if args.candidates is not None:  # "--candidates ''" is a mistake, not "every effect"
        cands = [c.strip() for c in args.candidates.split(",") if c.strip()]
        if not cands:
            raise UserError(f"--candidates {args.candidates!r}: no effect named; give comma-separated effect names "
                            "(e.g. wind,linear_drag) or leave the option out to try the whole registry")
    log = None if args.quiet else print
    with Progress(total=100, description="diagnose", show_bar=not args.quiet) as progress:
        if not args.quiet and args.solver == "auto":
            print(f"solver: {solver} (the most faithful on {device} within the time limits; --solver to choose)")
        result = diagnose.diagnose(m, solver, out_dir=args.out, effects_on=args.effects_on, add=args.add,
                                   max_additions=args.max_additions, device=device,
                                   settings=parse_settings(args.setting) or None, candidates=cands,
                                   parallel=args.parallel, allow_long=args.allow_long, progress=progress,
                                   log=log, resolution_budget_s=args.resolution_budget,
                                   reject_outliers=not args.keep_outliers)
    print(result.summary())
    print(f"report: {args.out}/diagnosis.json, {args.out}/diagnosis.html")
    return 0
