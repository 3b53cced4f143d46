"""``unipixie measure``: make, inspect and convert measurements (``unipixie.measurement/1``)."""

from __future__ import annotations

import math

from ...solvers.registry import SOLVER_NAMES
from ._common import device as device_type
from ._common import existing_file

NAME = "measure"
MIN_SYNTH_POINTS = 8
"""The fewest tracked points ``measure synth`` makes (the coarsest closed surface of its shapes)."""
HELP = "make a synthetic measurement with hidden effects, inspect or convert measurement files"
EXAMPLES = """  unipixie measure synth --out m.npz --effect wind:acceleration=0,0.5,0 --solver mpm --noise 0.001 --occlusion 0.1
  unipixie measure synth --out drag.npz --effect quadratic_drag:k=0.3 --scenario throw --shape cube
  unipixie measure synth --out slide.npz --effect ground_friction:mu=0.3 --scenario slide --solver spring_mass
  unipixie measure show m.npz
  unipixie measure convert tracks.csv tracks.npz --scenario tracks.json"""


def add_arguments(p):
    from ..diagnosis.synth import SCENARIOS, SHAPES
    from .diagnose import add_measurement_arguments

    sub = p.add_subparsers(dest="measure_command", metavar="ACTION", required=True)
    s = sub.add_parser("synth", help="simulate a scenario with hidden effects, add noise and occlusions, write a "
                                     "measurement file",
                       description="Simulate a scenario with effects switched on (any solver), add white noise and "
                                   "occlusions, and write a unipixie.measurement/1 file whose scenario states the "
                                   "material the model believes. The truth is kept in the archive key 'synth_truth'.")
    s.add_argument("--out", required=True, metavar="FILE.npz", help="measurement file to write (.npz; .csv writes "
                                                                     "t,id,x,y,z plus a scenario .json)")
    s.add_argument("--effect", action="append", default=[], metavar="EFFECT",
                   help="hidden effect, e.g. wind:acceleration=0,0.5,0 or stiffness_region:factor=3,box=0,0,0,1,1,1; "
                        "repeatable (none: no hidden effect)")
    s.add_argument("--solver", default="mpm", choices=SOLVER_NAMES, help="generating solver (default mpm)")
    s.add_argument("--noise", type=float, default=0.001, metavar="M", help="noise σ per coordinate in metres "
                                                                          "(default 0.001)")
    s.add_argument("--occlusion", type=float, default=0.1, help="fraction of samples hidden (default 0.1)")
    s.add_argument("--shape", default="cube", choices=SHAPES)
    s.add_argument("--scenario", default="drop", choices=SCENARIOS)
    s.add_argument("--duration", type=float, default=1.0, metavar="S")
    s.add_argument("--fps", type=float, default=100.0)
    s.add_argument("--points", type=int, default=250, help="about this many tracked points (surface vertices)")
    s.add_argument("--E", type=float, default=2.0e5, metavar="PA", help="Young's modulus stated in the file")
    s.add_argument("--nu", type=float, default=0.3)
    s.add_argument("--density", type=float, default=1000.0, metavar="KG_M3")
    s.add_argument("--true-E-scale", type=float, default=1.0, metavar="X",
                   help="simulate with E × X while the file states E (a model close to, not equal to, the truth)")
    s.add_argument("--spin", type=float, default=0.0, metavar="RAD_S", help="initial rotation rate")
    s.add_argument("--velocity", metavar="VX,VY,VZ", help="initial velocity in m/s (replaces the scenario's)")
    s.add_argument("--height", type=float, metavar="M", help="start this high above the ground (drop, slide)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE",
                   help="generating solver setting, e.g. cells_across=16 (mpm) or anchors=512 (spring_mass)")
    s.add_argument("--device", type=device_type, default="cpu")
    s.add_argument("--force", action="store_true", help="overwrite an existing output file")
    s.add_argument("--allow-long", action="store_true",
                   help="simulate even when the number of instants (duration × fps) passes the long-job limit")

    sh = sub.add_parser("show", help="validate a measurement and print a summary (and the noise estimate)")
    sh.add_argument("measurement", type=existing_file, metavar="MEASUREMENT")
    add_measurement_arguments(sh)

    cv = sub.add_parser("convert", help="convert a CSV (t,id,x,y,z) measurement into the .npz format, or back")
    cv.add_argument("measurement", type=existing_file, metavar="INPUT")
    cv.add_argument("output", metavar="OUTPUT")
    cv.add_argument("--force", action="store_true", help="overwrite an existing output file")
    add_measurement_arguments(cv)


def _check_output(path, force: bool, inputs=()):
    """The output path, checked before any work: .npz or .csv, not an existing file without --force (a
    CSV's side-car .json included), not (a link to) an input, writable with room."""
    from pathlib import Path

    from ..atomic_io import check_writable, refuse_overwriting_inputs
    from ..errors import UserError

    p = Path(path).expanduser()
    if p.suffix.lower() not in (".npz", ".csv"):
        raise UserError(f"{p}: the output must end in .npz or .csv")
    targets = [p] + ([p.with_suffix(".json")] if p.suffix.lower() == ".csv" else [])
    for t in targets:
        refuse_overwriting_inputs(t, inputs)
        if (t.exists() or t.is_symlink()) and not force:
            raise UserError(f"{t} exists; use --force to overwrite it")
        check_writable(t)
    return p


def _write(m, p):
    """Write ``m`` to ``p`` (.npz or .csv + side-car .json), locked against a second run writing it at the same
    time; returns the path and says what a CSV drops."""
    from ..atomic_io import OutputLock

    with OutputLock(p, "output"):
        return _write_unlocked(m, p)


def _write_unlocked(m, p):
    if p.suffix.lower() == ".csv":
        path, dropped = m.save_csv(p)
        held = ["the scenario", "every point id"] + (["rest positions"] if m.rest_positions is not None else []) + (
            [f"{len(m.faces)} faces"] if m.faces is not None else []) + (
            ["the per-point material"] if m.material is not None and not m.material.homogeneous else [])
        print(f"wrote {p.with_suffix('.json')} ({', '.join(held)}: the side-car the CSV needs; keep them together)")
        if dropped:
            print(f"note: the CSV and its side-car drop the archive key(s) {', '.join(dropped)} (only a .npz holds "
                  "them)")
        return path
    return m.save(p)


def run(args) -> int:
    if args.measure_command == "synth":
        return _synth(args)
    if args.measure_command == "show":
        return _show(args)
    return _convert(args)


def _synth(args) -> int:
    from ..diagnosis import synth
    from ..progress import Progress
    from ...solvers.warp_runtime import resolve_device
    from .diagnose import parse_settings

    from ..cost import frames_estimate
    from ..errors import UserError

    if args.points < MIN_SYNTH_POINTS:
        raise UserError(f"--points {args.points}: a synthetic measurement needs at least {MIN_SYNTH_POINTS} tracked "
                        "points (the shape's surface vertices)")
    checks = [("--duration", args.duration, args.duration > 0, "a positive number of seconds"),
              ("--fps", args.fps, args.fps > 0, "a positive number of instants per second"),
              ("--noise", args.noise, args.noise >= 0, "0 or more metres"),
              ("--occlusion", args.occlusion, 0 <= args.occlusion < 1, "a fraction in [0, 1)"),
              ("--spin", args.spin, True, "a finite rotation rate in rad/s")]
    if args.height is not None:
        checks.append(("--height", args.height, args.height >= 0, "0 or more metres above the ground (a negative "
                                                                  "height starts the object inside the ground)"))
    for flag, value, ok, what in checks:
        if not (ok and value == value and abs(value) != float("inf")):
            raise UserError(f"{flag} {value:g}: expected {what}")
    if args.seed < 0:
        raise UserError(f"--seed {args.seed}: expected 0 or a positive whole number")
    velocity = _vector(args.velocity)
    frames_estimate(f"a synthetic measurement of {args.duration:g} s at {args.fps:g} fps",
                    int(args.duration * args.fps) + 1).check(allow_long=args.allow_long)
    out = _check_output(args.out, args.force)
    effects = [e for e in args.effect if e.strip().lower() != "none"]
    _synth_cost(args).check(args.allow_long, remedy="use a shorter --duration, a lower --fps or a coarser --setting")
    with Progress(total=1.0, description="synth") as progress:
        m = synth.synthesize(effects, args.solver, shape=args.shape, scenario=args.scenario, noise=args.noise,
                             occlusion=args.occlusion, duration=args.duration, fps=args.fps, points=args.points,
                             E=args.E, nu=args.nu, density=args.density, true_E_scale=args.true_E_scale,
                             spin=args.spin, velocity=velocity, height=args.height,
                             seed=args.seed, device=resolve_device(args.device),
                             settings=parse_settings(args.setting) or None, progress=progress)
    path = _write(m, out)
    print(f"wrote {path}: {m.summary()}")
    print(f"hidden: {', '.join(effects) or 'no effect'} (simulated with {args.solver}, E × {args.true_E_scale:g}); "
          f"noise σ = {args.noise:g} m, {100 * args.occlusion:.0f} % occluded")
    return 0


def _synth_cost(args):
    """The up-front cost of ``measure synth`` (frames x substeps, core/cost.py), printed before it runs."""
    import numpy as np

    from ..cost import estimate
    from ..diagnosis.synth import make_shape
    from .diagnose import parse_settings

    mesh = make_shape(args.shape, args.points)
    frames = int(args.duration * args.fps) + 1
    from ...solvers.material_sampling import HomogeneousMaterial

    HomogeneousMaterial(args.E * args.true_E_scale, args.nu, args.density)  # the one material rule, before the cost
    material = type("StatedMaterial", (), {"E": args.E * args.true_E_scale, "nu": args.nu, "density": args.density})
    est = estimate(f"synthesising {args.duration:g} s at {args.fps:g} fps with {args.solver}", args.solver,
                   size=float(np.max(mesh.extents)), times=np.arange(frames) / args.fps, material_spec=material,
                   points=len(mesh.vertices), settings=parse_settings(args.setting) or None)
    print(f"estimated cost: {est.describe()}", flush=True)
    return est


def _vector(text):
    from ..errors import UserError

    if text is None:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise UserError(f"--velocity {text!r}: expected three numbers vx,vy,vz") from None
    if len(v) != 3 or not all(abs(x) < float("inf") for x in v):
        raise UserError(f"--velocity {text!r}: expected three finite numbers vx,vy,vz (m/s)")
    return v


def _show(args) -> int:
    import json

    from ..diagnosis.compare import estimate_noise, noise_rmse
    from .diagnose import load_measurement

    m = load_measurement(args)
    print(f"{m.source}: valid unipixie.measurement/1")
    print(f"  {m.summary()}")
    print(f"  times {m.times[0]:.4g} .. {m.times[-1]:.4g} s")
    mat = m.material.to_dict() if m.material is not None else "none stated"
    print(f"  material: {json.dumps(mat)}")
    print(f"  scenario: {json.dumps(m.scenario.to_dict())}")
    if m.frame_count >= 4:
        from ..diagnosis.outliers import find_tracking_outliers

        found = find_tracking_outliers(m.positions, m.rest)
        s = found.noise_sigma if math.isfinite(found.noise_sigma) else estimate_noise(m.positions, m.rest)
        print(f"  noise estimated from the tracks: σ = {1e3 * s:.3g} mm per coordinate "
              f"(noise floor RMSE {1e3 * noise_rmse(s):.3g} mm)")
        if found.count:
            print(f"  tracking outliers: {found.describe(m.observed_count)}")
    for w in m.warnings:
        print(f"  warning: {w}")
    from ..diagnosis import sanity
    from ..errors import UserError

    try:  # what a diagnosis would say of the scenario against the measurement, before anyone runs one
        for w in sanity.check(m, "spring_mass", estimate_cost=False):
            print(f"  warning: {w}")
    except UserError as exc:
        print(f"  warning: unipixie diagnose would refuse it: {exc}")
    return 0


def _convert(args) -> int:
    from .diagnose import load_measurement

    out = _check_output(args.output, args.force, inputs=[args.measurement] + (
        [args.measurement.with_suffix(".json")] if str(args.measurement).lower().endswith(".csv") else []) + (
        [args.scenario] if getattr(args, "scenario", None) else []))
    m = load_measurement(args)
    for w in m.warnings:
        print(f"warning: {w}")
    path = _write(m, out)
    print(f"wrote {path}: {m.summary()}")
    return 0
