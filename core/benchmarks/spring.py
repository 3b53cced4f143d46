"""``unipixie bench spring``: spring-mass throughput in substeps per second.

Cases (a jelly sphere of radius 0.1 m, E = 100 kPa, ν = 0.3, 1000 kg/m³, falling at 1 m/s onto a
frictionless ground under gravity; set-up once, then ``sim.run`` timed, median of ``--runs``
after one warm-up run):

* ``N anchors`` — the network of ``--anchors`` (default 2048, the paper's N_a) anchors with 32
  springs each, tracked points = the 642 vertices of an icosphere;
* ``N anchors, 100k-vertex mesh bound`` — the same network with every vertex of a ~100k-vertex
  sphere bound to it and written every frame;
* ``diagnosis size`` — 300 anchors, 250 tracked points, 1 s at 100 frames: the run the
  diagnosis repeats (metric ``runs_per_s``);
* ``batch of 8`` — 8 environments (base + 7 effects) stepped in one launch per substep
  (metric ``env_substeps_per_s``: environments × substeps per second).

A timed run includes everything a diagnosis re-run pays: state upload, all substeps, the
per-frame binding of the tracked points and reading them back.  ``substeps_per_s`` =
substeps of the run / its wall time; every entry also records ``simulated_s_per_wall_s`` (simulated time / wall
time: what a user waits, which a longer substep improves and ``substeps_per_s`` does not show) and the run's
``step_bound``.
"""

from __future__ import annotations

import numpy as np

from ..commands._common import positive_number
from . import sphere_drop, sphere_mesh, time_simulation

HELP = "spring-mass solver throughput (substeps/s): 2048 anchors, a 100k-vertex mesh bound, diagnosis-size runs"


def add_arguments(p):
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--anchors", type=int, default=2048, help="anchors of the large cases (default 2048)")
    p.add_argument("--runs", type=int, default=3, help="timed runs per case (median; default 3)")
    p.add_argument("--duration", type=positive_number, default=None,
                   help="simulated seconds per timed run of the large cases (default: 0.5 on a GPU, 0.05 on the CPU)")
    p.add_argument("--skip-mesh", action="store_true", help="skip the 100k-vertex case")


def run(args) -> list[dict]:
    from ...core.errors import UserError
    from ...solvers import effects as fx
    from ...solvers import spring_mass as sm
    from ...solvers.body import Body
    from ...solvers.warp_runtime import device_description, init_warp, resolve_device

    wp = init_warp()
    device = resolve_device(args.device)
    if args.runs < 1 or args.anchors < 2:
        raise UserError("--runs must be at least 1 and --anchors at least 2")
    duration = args.duration or (0.5 if device.startswith("cuda") else 0.05)
    described = device_description(device)
    material, scenario = sphere_drop()
    results = []

    def bench(case, mesh, anchors, frames, effects_lists=None, tracked=None, metric="substeps_per_s"):
        body = Body.from_mesh(mesh, tracked_points=tracked)
        sim = sm.prepare(body, material, scenario, frames, device=device, settings={"anchors": anchors})
        _, traj, med, envs = time_simulation(sim, effects_lists, args.runs, wp, device)
        subs = traj.meta["substeps"]
        value = {"substeps_per_s": subs / med, "env_substeps_per_s": envs * subs / med, "runs_per_s": 1.0 / med}[metric]
        entry = {"case": case, "device": described, "metric": metric, "value": value, "runs": args.runs,
                 "anchors": sim.network.count, "springs": int(len(sim.network.springs)),
                 "tracked_points": int(len(body.tracked_points)), "frames": len(frames), "substeps_per_run": subs,
                 "environments": envs, "median_run_s": med, "substep_s": traj.meta["substep_s"],
                 "step_bound": traj.meta.get("step_bound"),
                 "simulated_s_per_wall_s": float(frames[-1] - frames[0]) / med}
        results.append(entry)
        print(f"  {case}: {value:.4g} {metric} (run {med:.3g} s, {subs} substeps, {sim.network.count} anchors; "
              f"{entry['simulated_s_per_wall_s']:.3g} simulated s per wall s)", flush=True)

    ico = sphere_mesh()
    frames = np.linspace(0.0, duration, 11)
    bench(f"{args.anchors} anchors, jelly sphere drop", ico, args.anchors, frames)
    if not args.skip_mesh:
        big = sphere_mesh(large=True)
        bench(f"{args.anchors} anchors, {len(big.vertices) // 1000}k-vertex mesh bound", big, args.anchors, frames)
    small = sphere_mesh()
    rng = np.random.default_rng(0)
    tracked = small.vertices[rng.choice(len(small.vertices), 250, replace=False)]
    diag_frames = np.linspace(0.0, 1.0, 101)
    bench("diagnosis size: 300 anchors, 250 tracked points, 1 s at 100 frames", small, 300, diag_frames,
          tracked=tracked, metric="runs_per_s")
    effs = [[], [fx.make("linear_drag", c=1.0)], [fx.make("quadratic_drag", k=1.0)],
            [fx.make("wind", acceleration=[1.0, 0, 0])], [fx.make("ground_friction", mu=0.5)],
            [fx.make("plasticity", yield_stress=2e3)],
            [fx.make("stiffness_region", factor=2.0, region={"box": [[-1, -1, -1], [0, 1, 1]]})],
            [fx.make("linear_drag", c=3.0)]]
    bench("batch of 8 environments, 300 anchors, 1 s at 100 frames", small, 300, diag_frames, effects_lists=effs,
          tracked=tracked, metric="env_substeps_per_s")
    return results
