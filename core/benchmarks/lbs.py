"""``unipixie bench lbs``: LBS solver throughput in implicit steps per second.

Cases (a jelly sphere of radius 0.1 m, E = 100 kPa, ν = 0.3, 1000 kg/m³, falling at 1 m/s onto a
frictionless ground; 500 cubature points, 10 handles + the constant one, one backward-Euler step
of 5 ms per frame, Newton with line search; set-up once — including the skinning fit — then
``sim.run`` timed, median of ``--runs`` after one warm-up run):

* ``500 cubature points, 101k-vertex mesh`` — every vertex of a 101,122-vertex sphere is
  output at every step (x = X + Z a(X): after the stepping, one GEMM per chunk of frames on the
  device) and read back to the host;
* ``500 cubature points, 642 vertices`` — the same with a small output mesh;
* ``batch of 8 environments`` — base + 7 effects in one batched Newton solve (metric
  ``env_steps_per_s``);
* ``skinning fit`` — :func:`unipixie.solvers.lbs_fit.fit_skinning` of the sphere's fill points
  (metric ``fit_s``, seconds; lower is better).

``steps_per_s`` = implicit steps of a run / its wall time; entries also give the Newton
iterations per step and, from one more run of each case, where the time goes per step
(``phase_ms_per_step``: host wall time of the step-start evaluation with its Hessian, the line
search's trial evaluations, the host's energy terms, the Newton solve, the line search's
bookkeeping, plasticity, vertex output; ``evaluation_ms_per_step``: inside the evaluations, the
upload, the Warp kernel with and without the Hessian, the gradient and Hessian reductions, the
download and the host's wait — device times from CUDA events on a GPU (that run sets
``profile_device``), wall times on the CPU).
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from ..commands._common import positive_int
from . import sphere_drop, sphere_mesh, time_simulation

HELP = "LBS solver throughput (implicit steps/s): 500 cubature points, 100k-vertex mesh output, batches, skinning fit"

STEP = 5.0e-3


def add_arguments(p):
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--cubature", type=int, default=500, help="cubature points (default 500)")
    p.add_argument("--steps", type=positive_int, default=None, help="steps per timed run (default: 200 on a GPU, 30 on the CPU)")
    p.add_argument("--runs", type=int, default=3, help="timed runs per case (median; default 3)")
    p.add_argument("--skip-mesh", action="store_true", help="skip the 100k-vertex case")
    p.add_argument("--line-search-candidates", type=int, default=0,
                   help="step lengths per line-search launch (default 0: automatic, 1 on the CPU, 4 on a GPU)")


PHASES = ("hessian_evaluation", "trial_evaluation", "host_terms", "trial_host_terms", "newton_solve",
          "line_search_bookkeeping", "plasticity", "vertex_output", "set_up", "other")
EVALUATION_PHASES = ("upload", "kernel_hessian", "kernel_trial", "reduction_gradient", "reduction_hessian", "download",
                     "wait")


def _breakdown(meta: dict, steps: int) -> tuple[dict, dict]:
    """Per-step milliseconds of the run's phases and of the phases inside its device evaluations."""
    phases = {k: 1e3 * meta["phase_seconds"][k] / steps for k in PHASES if k in meta["phase_seconds"]}
    inner = {k: 1e3 * meta["evaluation_seconds"][k] / steps for k in EVALUATION_PHASES if k in meta["evaluation_seconds"]}
    return phases, inner


def _print_breakdown(phases: dict, inner: dict, evaluations: dict, steps: int) -> None:
    print("      per step (ms): " + ", ".join(f"{k} {v:.3f}" for k, v in phases.items() if v > 0), flush=True)
    print("      evaluations (ms/step): " + ", ".join(f"{k} {v:.3f}" for k, v in inner.items() if v > 0)
          + f"; {evaluations['hessian'] / steps:.2f} Hessian + {evaluations['trial'] / steps:.2f} trial "
          f"evaluations/step ({evaluations['trial_rows'] / max(evaluations['trial'], 1):.2f} rows each)", flush=True)


def run(args) -> list[dict]:
    from ...core.errors import UserError
    from ...solvers import effects as fx
    from ...solvers import lbs, lbs_fit
    from ...solvers.body import Body
    from ...solvers.warp_runtime import device_description, init_warp, resolve_device

    wp = init_warp()
    device = resolve_device(args.device)
    if args.runs < 1 or args.cubature < 4:
        raise UserError("--runs must be at least 1 and --cubature at least 4")
    steps = args.steps or (200 if device.startswith("cuda") else 30)
    described = device_description(device)
    material, scenario = sphere_drop()
    frames = np.arange(steps + 1) * STEP
    settings = {"cubature_points": args.cubature, "max_dt": STEP, "line_search_candidates": args.line_search_candidates}
    results = []

    def bench(case, mesh, effects_lists=None, metric="steps_per_s"):
        if args.line_search_candidates:   # a non-default setting is its own case (record() keys on the case)
            case += f", {args.line_search_candidates} line-search step lengths per launch"
        body = Body.from_mesh(mesh)
        t0 = time.perf_counter()
        sim = lbs.prepare(body, material, scenario, frames, device=device, settings=settings)
        prepare_s = time.perf_counter() - t0
        go, traj, med, envs = time_simulation(sim, effects_lists, args.runs, wp, device)
        n_steps = traj.meta["steps"]
        value = {"steps_per_s": n_steps / med, "env_steps_per_s": envs * n_steps / med}[metric]
        # one more run for the breakdown (device phases timed with CUDA events on a GPU)
        sim.settings.profile_device = True
        profiled = go()
        sim.settings.profile_device = False
        meta = (profiled[0] if isinstance(profiled, list) else profiled).meta
        phases, inner = _breakdown(meta, n_steps)
        entry = {"case": case, "device": described, "metric": metric, "value": value, "runs": args.runs,
                 "cubature_points": len(sim.cubature_rest), "handles": sim.handles + 1,
                 "vertices": int(len(body.tracked_points)), "steps_per_run": n_steps, "environments": envs,
                 "newton_iterations_per_step": traj.meta["newton_iterations"] / n_steps, "median_run_s": med,
                 "prepare_s": prepare_s, "line_search_candidates": traj.meta["line_search_candidates"],
                 "phase_ms_per_step": phases, "evaluation_ms_per_step": inner,
                 "profiled_run_s": meta["phase_seconds"]["total"]}
        results.append(entry)
        print(f"  {case}: {value:.4g} {metric} (run {med:.3g} s, {entry['newton_iterations_per_step']:.2f} Newton "
              f"iterations/step)", flush=True)
        _print_breakdown(phases, inner, meta["evaluations"], n_steps)
        return sim

    ico = sphere_mesh()
    if not args.skip_mesh:
        big = sphere_mesh(large=True)
        bench(f"{args.cubature} cubature points, {len(big.vertices) // 1000}k-vertex mesh, jelly sphere drop", big)
    sim = bench(f"{args.cubature} cubature points, {len(ico.vertices)} vertices, jelly sphere drop", ico)
    effs = [[], [fx.make("linear_drag", c=1.0)], [fx.make("quadratic_drag", k=1.0)],
            [fx.make("wind", acceleration=[1.0, 0, 0])], [fx.make("ground_friction", mu=0.5)],
            [fx.make("plasticity", yield_stress=2e3)], [fx.make("material_damping", eta=100.0)],
            [fx.make("stiffness_region", factor=2.0, region={"box": [[-1, -1, -1], [0, 1, 1]]})]]
    bench(f"batch of 8 environments, {args.cubature} cubature points", ico, effects_lists=effs,
          metric="env_steps_per_s")
    # the data-free skinning fit of the same object (its fill points, as prepare() uses them)
    pts, vol = sim.mass_rest, sim._fill_volume
    fit_times = []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        lbs_fit.fit_skinning(pts, vol, bounds=sim.bounds)
        fit_times.append(time.perf_counter() - t0)
    med = statistics.median(fit_times)
    results.append({"case": f"skinning fit, {len(pts)} fill points, {sim.handles} handles (650 parameters)",
                    "device": described + " (torch CPU)", "metric": "fit_s", "value": med, "runs": args.runs,
                    "points": int(len(pts))})
    print(f"  skinning fit: {med:.3g} s", flush=True)
    return results
