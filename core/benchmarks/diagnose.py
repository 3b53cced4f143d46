"""``unipixie bench diagnose``: wall time of a full diagnosis.

A full diagnosis = the baseline simulation, the base (E/ρ) fit, every registry effect fitted
with significance tests, and one addition, of a 1 s, 101-instant (100 frame intervals),
~250-point measurement (a cube thrown through the air with a hidden effect, 1 mm noise,
10 % occlusions).  The measurement is generated once (not timed); every run diagnoses it
from scratch (solver preparation included).  Targets: ≤ 2 min on the 2-core CPU with the
fastest adequate solver (spring-mass), ≤ 30 s on one H100 with MPM.
"""

from __future__ import annotations

import argparse

from ...solvers.registry import SOLVER_NAMES

HELP = "time a full diagnosis (baseline + every effect fitted + one addition) of a 1 s, 100-frame, ~250-point measurement"


def add_arguments(p):
    from ..commands import _common

    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--solver", default="spring_mass", choices=SOLVER_NAMES,
                   help="solver of the diagnosis (default spring_mass)")
    p.add_argument("--gen-solver", default="mpm", choices=SOLVER_NAMES,
                   help="solver that makes the measurement (default mpm)")
    p.add_argument("--effect", default="quadratic_drag:k=0.3", help="the hidden effect")
    p.add_argument("--runs", type=_common.positive_int, default=1, help="timed runs (median reported)")
    p.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE", help="solver setting of the diagnosis")
    p.add_argument("--parallel", action=argparse.BooleanOptionalAction, default=None,
                   help="candidate fits side by side (default: the diagnosis's own choice for the device)")


def run(args) -> list[dict]:
    import os
    import statistics
    import time

    from ...solvers.warp_runtime import device_description, resolve_device
    from ..commands.diagnose import parse_settings
    from ..diagnosis import diagnose, synth

    device = resolve_device(args.device)
    gen_settings = {"cells_across": 10} if args.gen_solver == "mpm" and device == "cpu" else None
    m = synth.synthesize([args.effect], args.gen_solver, shape="cube", scenario="throw", noise=0.001, occlusion=0.1,
                         duration=1.0, fps=100.0, points=250, seed=1, device=device, settings=gen_settings)
    settings = parse_settings(args.setting) or None
    times, sims, found = [], [], []
    load_before = os.getloadavg()[0]
    for _ in range(max(1, args.runs)):
        t0 = time.perf_counter()
        d = diagnose.diagnose(m, args.solver, max_additions=1, device=device, settings=settings,
                              parallel=args.parallel, allow_long=True)  # a benchmark is long on purpose
        times.append(time.perf_counter() - t0)
        sims.append(d.simulations)
        found.append(d.identified)
    expected = args.effect.split(":")[0]
    mode = {True: ", candidates side by side", False: ", candidates one after another", None: ""}[args.parallel]
    case = (f"full diagnosis ({args.solver}{' ' + ','.join(args.setting) if args.setting else ''}{mode}, "
            f"{m.frame_count} instants / {m.duration:g} s, {m.point_count} points, hidden {args.effect} made by "
            f"{args.gen_solver}; baseline + every effect + one addition)")
    return [{"case": case, "device": device_description(device), "metric": "diagnosis_wall_s",
             "value": statistics.median(times), "runs": len(times), "unit": "s",
             "simulations": sims[0], "identified": found[0], "correct": found[0] == expected,
             "all_runs_s": [round(t, 2) for t in times],
             "load_average": [round(load_before, 2), round(os.getloadavg()[0], 2)],
             "note": "machine shared with other jobs: see load_average (1-minute, before/after)"}]
