"""``unipixie bench bake``: simulate-and-bake time per solver, split into simulation and keyframe writing.

The case is the issue's: a closed mesh of 10,242 vertices (an icosphere of radius 0.5 m,
subdivision 5) dropped from 0.1 m onto the ground, 250 frames at 24 fps, a homogeneous jelly
(E 1e5 Pa, ν 0.3, 1000 kg/m³), each solver with its product defaults unless an option says
otherwise.  Simulation time covers the solver's set-up and run (``core.bake.simulate``); writing
covers turning the trajectory into Blender data (``core.blender_io.bake.write_result``) — timed
for the automatic choice (a Mesh Cache at this size), for shape keys, and for LBS also the
armature.  Writing needs bpy: where bpy is missing (the GPU machine) only simulation is timed.
"""

from __future__ import annotations

import statistics
import time

from ...solvers.registry import SOLVER_NAMES

HELP = "bake time per solver for a 10k-vertex mesh × 250 frames: simulation vs keyframe writing"


def add_arguments(p):
    from ..commands import _common

    p.add_argument("--device", type=_common.device, default="cpu", help="Warp device for the solvers (cpu, cuda)")
    p.add_argument("--solvers", default=",".join(SOLVER_NAMES), help="comma-separated solvers (default all)")
    p.add_argument("--frames", type=_common.positive_int, default=250, help="frames to bake (default 250)")
    p.add_argument("--subdivisions", type=_common.positive_int, default=5,
                   help="icosphere subdivisions: 5 = 10,242 vertices (default)")
    p.add_argument("--runs", type=_common.positive_int, default=1,
                   help="simulation runs per solver (median reported; writing is always timed 3 times)")
    p.add_argument("--mpm-cells", type=_common.positive_int, default=None,
                   help="MPM grid cells across the object (default: the solver's default)")


MAX_SUBDIVISIONS = 8
"""The finest benchmark subject: 655,362 vertices (each subdivision quadruples them; 20 would need terabytes)."""


def _subject(subdivisions: int):
    import trimesh

    from ..bake import BakeObject
    from ..errors import UserError

    if not 0 < subdivisions <= MAX_SUBDIVISIONS:
        raise UserError(f"--subdivisions {subdivisions}: expected 1..{MAX_SUBDIVISIONS} ({MAX_SUBDIVISIONS} is "
                        f"{10 * 4 ** MAX_SUBDIVISIONS + 2:,} vertices)")

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    verts = mesh.vertices + [0.0, 0.0, 0.6]
    return BakeObject("Ball", verts, mesh.faces)


def run(args) -> list[dict]:
    from .. import bake as core_bake
    from ...solvers.registry import canonical_solver
    from ...solvers.scenario import Scenario
    from ...solvers.warp_runtime import device_description, resolve_device

    bo = _subject(args.subdivisions)  # checked first: the solvers' imports take seconds
    solvers = [canonical_solver(s) for s in args.solvers.split(",") if s.strip()]
    n, T = bo.vertex_count, args.frames
    device = resolve_device(args.device)
    sim_device = device_description(device)
    cpu_device = device_description("cpu")
    try:
        from ..blender_io.bake import time_writes
    except ImportError:
        time_writes = None
        print("bpy is not available here: only simulation is timed (writing needs Blender)")
    scenario = Scenario(ground_height=0.0)
    results: list[dict] = []
    for solver in solvers:
        settings = {"cells_across": args.mpm_cells} if (solver == "mpm" and args.mpm_cells) else None
        options = core_bake.BakeOptions(solver=solver, frames=(1, T), fps=24.0, device=device,
                                        material=core_bake.HomogeneousSource(E=1e5, nu=0.3, density=1000.0),
                                        solver_settings=settings)
        sims, result = [], None
        for _ in range(args.runs):
            t0 = time.perf_counter()
            result = core_bake.simulate(bo, scenario, options)
            sims.append(time.perf_counter() - t0)
        sim_s = statistics.median(sims)
        case = f"{n} vertices x {T} frames, {solver}" + (f", cells_across {args.mpm_cells}" if settings else "")
        meta = result.trajectory.meta
        detail = {k: meta[k] for k in ("particles", "substeps_total", "anchors", "substeps", "steps", "cubature_points")
                  if k in meta and not isinstance(meta[k], list)}
        results.append({"case": case, "device": sim_device, "metric": "simulate_s", "value": sim_s, "runs": len(sims),
                        "detail": detail})
        if time_writes is None:
            continue
        modes = ["mesh_cache", "shape_keys"] + (["armature"] if solver == "lbs" else [])
        auto_mode = core_bake.choose_output(solver, "auto", n, T)[0]
        writes = time_writes(bo, result, options, modes)
        for mode, (sec, runs) in writes.items():
            entry = {"case": case, "device": cpu_device, "metric": f"write_{mode}_s", "value": sec, "runs": runs,
                     "vs": {"what": "simulation time of the same case (write / simulate)", "ratio": sec / sim_s}}
            if mode == auto_mode:
                entry["auto"] = True
            results.append(entry)
        if auto_mode in writes:
            w = writes[auto_mode][0]
            results.append({"case": case, "device": sim_device, "metric": "write_fraction_of_bake",
                            "value": w / (w + sim_s), "runs": len(sims),
                            "detail": {"output": auto_mode, "simulate_s": sim_s, "write_s": w}})
    return results
