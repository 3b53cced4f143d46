"""``unipixie bench objects``: Table 2's protocol on the dataset's test objects, and how far its ground truth is
from converged.

Table 2 of the evaluation (:mod:`unipixie.training.evaluate`) compares each solver with the object's ground-truth
MPM motion, which the dataset simulates at :class:`~unipixie.training.ground_truth.GroundTruthSettings`'s
``cells_across`` (12).  This benchmark asks what that comparison can show, on the first ``--objects`` objects of
the procedural generator's test split (no dataset build needed; the objects are regenerated):

- **The ground truth's own error**: the same object and material simulated by MPM at each level of ``--cells``
  (default 12, 24, 36 cells across); the tracked points' RMSE between levels, over the whole clip, as a fraction
  of the object's size (the metric of Table 2).
- **The test-time fits** of Table 2 (spring-mass and LBS at the ground-truth protocol's resolutions, one stiffness
  scale fitted by :func:`~unipixie.training.ground_truth.fit_scale`) against the coarsest MPM level (the dataset's
  ground truth) and against the finest, and the spring-mass network at its bake default (2048 anchors) with the
  stated material against the finest.

Everything is at one α (default 0.5, the α the dataset simulates for test objects).  Objects are independent:
``--workers`` processes run them side by side (CPU cores, or one GPU shared).  Results, per object and their
medians: ``benchmarks/objects.json`` (``metric`` ``trajectory_rmse_over_size``, dimensionless).
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ProcessPoolExecutor
import numpy as np

HELP = "Table 2's protocol on test objects: MPM ground truth at several resolutions, spring-mass/LBS fits to it"

def add_arguments(p):
    p.add_argument("--objects", type=int, default=20, help="number of test-split objects (default 20)")
    p.add_argument("--seed", type=int, default=0, help="generator seed (default 0, the shipped dataset's)")
    p.add_argument("--cells", default="12,24,36",
                   help="MPM levels, cells across the object; the first is the ground truth's (default 12,24,36)")
    p.add_argument("--alpha", type=float, default=0.5, help="α of the material (default 0.5)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--workers", type=int, default=1, help="objects simulated side by side (processes; default 1)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                   help="a ground-truth setting (GroundTruthSettings field), e.g. --set frames=3 (tests)")
    p.add_argument("--no-bake-default", action="store_true",
                   help="skip the spring-mass run at its bake-default anchor count")


def test_indices(count: int) -> list:
    """The first ``count`` object indices of the procedural test split (:func:`~unipixie.training.dataset.split_of`)."""
    from ..dataset import split_of

    out, i = [], 0
    while len(out) < count:
        if split_of(i) == "test":
            out.append(i)
        i += 1
    return out


def _rmse_over_size(a: np.ndarray, b: np.ndarray, size: float) -> float:
    from ..ground_truth import motion_rmse

    return motion_rmse(a, b) / size


def measure_object(index: int, seed: int, cells: tuple, alpha: float, settings: dict, bake_default: bool) -> dict:
    """One object: MPM at each level of ``cells``, the fits, the bake-default network.

    Returns {"object", "size_m", "capped_mass_fraction", "pairs": {name: RMSE / size}, "seconds": {...}}; a
    step that fails records its error under "errors" (the rest still runs).
    """
    from ...core import procedural
    from ...core.types import Trajectory
    from ...solvers import spring_mass
    from ...solvers.spring_mass_settings import SpringMassSettings
    from .. import ground_truth as G

    obj = procedural.generate(int(index), int(seed))
    base = G.GroundTruthSettings(**settings, cells_across=int(cells[0]))   # the ground truth's level
    solid = G.build_solid(obj, base)
    size = float(solid.size)
    motions, seconds, errors = {}, {}, {}
    out = {"object": obj.object_id, "size_m": size, "scenario": getattr(solid.scenario, "notes", ""),
           "pairs": {}, "seconds": seconds, "errors": errors}
    for c in cells:
        s = dataclasses.replace(base, cells_across=int(c))
        level = solid if c == cells[0] else G.build_solid(obj, s)
        if level.tracked.shape != solid.tracked.shape or not np.allclose(level.tracked, solid.tracked):
            errors[f"mpm{c}"] = "the tracked points differ between levels"
            continue
        t = time.perf_counter()
        try:
            traj, info = G.simulate_mpm(level, alpha, s)
        except Exception as exc:  # a level that diverges is reported, the others still run
            errors[f"mpm{c}"] = str(exc)[:300]
            continue
        seconds[f"mpm{c}"] = time.perf_counter() - t
        motions[f"mpm{c}"] = traj.positions
        if c == cells[0]:
            out["capped_mass_fraction"] = info.get("capped_mass_fraction")
    levels = [f"mpm{c}" for c in cells if f"mpm{c}" in motions]
    for i, a in enumerate(levels):
        for b in levels[i + 1:]:
            out["pairs"][f"{a} vs {b}"] = _rmse_over_size(motions[a], motions[b], size)
    targets = [x for x in dict.fromkeys([f"mpm{cells[0]}", f"mpm{cells[-1]}"]) if x in motions]
    for target in targets:
        for name, fitter in (("spring_mass", G.fit_spring), ("lbs", G.fit_lbs)):
            t = time.perf_counter()
            try:
                fit = fitter(solid, alpha, Trajectory(solid.frame_times, motions[target]), base, keep_best=True)
            except Exception as exc:
                errors[f"{name} fit to {target}"] = str(exc)[:300]
                continue
            seconds[f"{name} fit to {target}"] = time.perf_counter() - t
            out["pairs"][f"{name} fit vs {target}"] = float(fit["fit"].rmse) / size
    if bake_default and levels:
        finest = levels[-1]
        anchors = SpringMassSettings().anchors
        mat, _ = solid.material(alpha)
        t = time.perf_counter()
        try:
            sim = spring_mass.prepare(solid.body(), mat, solid.scenario, solid.frame_times, device=base.device,
                                      settings={"anchors": anchors})
            motion = sim.run([]).positions
            seconds[f"spring_mass {anchors}"] = time.perf_counter() - t
            out["pairs"][f"spring_mass {anchors} anchors vs {finest}"] = _rmse_over_size(motion, motions[finest], size)
        except Exception as exc:
            errors[f"spring_mass {anchors}"] = str(exc)[:300]
    return out


def _parse_overrides(items) -> dict:
    import json

    from ...core.errors import UserError
    from ..ground_truth import GroundTruthSettings

    fields = {f.name for f in dataclasses.fields(GroundTruthSettings)}
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in fields or key in ("device", "cells_across"):
            raise UserError(f"--set expects FIELD=VALUE with a ground-truth setting other than device and "
                            f"cells_across ({', '.join(sorted(fields - {'device', 'cells_across'}))}); got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            raise UserError(f"--set {key}: {value!r} is not a number") from None
    return out


def run(args) -> list:
    from ...core.errors import UserError
    from ...core.progress import Progress
    from ...solvers.warp_runtime import device_description, resolve_device

    try:
        cells = tuple(int(c) for c in str(args.cells).split(","))
    except ValueError:
        raise UserError(f"--cells expects whole numbers separated by commas, got {args.cells!r}") from None
    if not cells or min(cells) < 2:
        raise UserError(f"--cells: each level needs at least 2 cells across, got {args.cells!r}")
    if args.objects < 1 or args.workers < 1:
        raise UserError("--objects and --workers must be at least 1")
    if not 0.0 <= float(args.alpha) <= 1.0:
        raise UserError(f"--alpha must lie in [0, 1], got {args.alpha}")
    device = resolve_device(args.device)
    settings = dict(_parse_overrides(args.overrides), device=device)
    described = device_description(device)
    jobs = [(i, int(args.seed), cells, float(args.alpha), settings, not args.no_bake_default)
            for i in test_indices(int(args.objects))]
    rows = []
    with Progress(total=len(jobs), description="objects") as progress:
        if int(args.workers) == 1:
            for job in jobs:
                rows.append(measure_object(*job))
                progress.step(1.0, rows[-1]["object"])
        else:
            import multiprocessing

            with ProcessPoolExecutor(max_workers=int(args.workers),
                                     mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = [pool.submit(measure_object, *job) for job in jobs]
                try:
                    for future in futures:
                        rows.append(future.result())
                        progress.step(1.0, rows[-1]["object"])
                except BaseException:  # cancelled (Ctrl-C) or failed: the objects not started never start
                    pool.shutdown(wait=False, cancel_futures=True)
                    raise
    return entries(rows, described, cells)


def entries(rows: list, device: str, cells: tuple) -> list:
    """Benchmark entries: one per object and comparison, then the median over objects of each comparison."""
    results = []
    by_pair: dict = {}
    for r in rows:
        for pair, value in r["pairs"].items():
            by_pair.setdefault(pair, []).append(value)
            results.append({"case": f"{r['object']}: {pair}", "device": device, "metric": "trajectory_rmse_over_size",
                            "value": float(value), "runs": 1, "object": r["object"], "size_m": r["size_m"],
                            "capped_mass_fraction": r.get("capped_mass_fraction"), "cells_across": list(cells)})
        for step, message in r["errors"].items():
            results.append({"case": f"{r['object']}: {step}", "device": device, "metric": "failed", "value": None,
                            "runs": 1, "error": message})
    for pair, values in by_pair.items():
        v = np.asarray(values, float)
        results.append({"case": f"median over {len(v)} objects: {pair}", "device": device,
                        "metric": "trajectory_rmse_over_size", "value": float(np.median(v)), "runs": 1,
                        "max": float(v.max()), "within_5_percent": int(np.sum(v <= 0.05)), "objects": int(len(v)),
                        "cells_across": list(cells)})
    return results
