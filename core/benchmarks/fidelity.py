"""``unipixie bench fidelity``: the solvers' refinement study on the canonical scenes, and their agreement.

For every scene of :mod:`._scenes` and every solver, the scene runs at a ladder of resolutions (MPM grid
pitch, spring-mass anchors, LBS cubature points and step); each run's measurements are compared with the
scene's reference (a closed form, or the converged independent referee: ``--referee FILE``, the JSON that
``python -m unipixie.training.independent_fem.study`` writes).  Then, at each solver's bake default, the
solvers' tracked-point trajectories are compared with each other (RMSE as a fraction of the object's size).

Results: ``benchmarks/fidelity.json`` (one entry per scene × solver × resolution × metric: ``value``,
``reference``, ``error`` (relative), ``default`` (bake default or not), ``wall_s``; and one per scene ×
solver pair: ``metric: trajectory_rmse_over_size``) and, with ``--plots DIR``, one figure per scene
(``fidelity_<scene>.png``: each metric against resolution, per solver, with the reference and its ±5 % band).

The ladders are data (:data:`LADDERS`); ``--ladder fast`` keeps the runs a 2-core CPU affords in minutes,
``full`` adds the fine levels meant for a GPU; ``defaults`` runs only each solver's bake default (the cross-solver
agreement in a few runs).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from ..atomic_io import save_figure, save_npz
from ...solvers.registry import SOLVER_NAMES

HELP = "solver fidelity: refinement study on canonical scenes (cantilever, drop, slide, drag) and cross-solver agreement"

TOLERANCE = 0.05
"""Acceptance: within 5 % of the reference at the bake default; solvers within 5 % of the size of each other."""

# scene -> solver -> [(label, settings, is bake default, ladder)]: "fast" runs in both ladders, "full" only in
# the full one.  MPM's bake default is cells_across = 32 (of the largest extent).
_MPM_CUBE = [("16 cells across", {"cells_across": 16}, False, "fast"),
             ("24 cells across", {"cells_across": 24}, False, "fast"),
             ("32 cells across", {}, True, "fast"),
             ("48 cells across", {"cells_across": 48}, False, "full"),
             ("64 cells across", {"cells_across": 64}, False, "full")]
_SPRING = [("512 anchors", {"anchors": 512}, False, "fast"),
           ("2048 anchors", {}, True, "fast"),
           ("8192 anchors", {"anchors": 8192}, False, "full")]
_LBS = [("200 cubature points", {"cubature_points": 200}, False, "fast"),
        ("500 cubature points", {}, True, "fast"),
        ("1500 cubature points", {"cubature_points": 1500}, False, "fast"),
        ("500 points, 5 ms steps", {"max_dt": 5e-3}, False, "fast"),
        ("500 points, 1 ms steps", {"max_dt": 1e-3}, False, "fast"),
        ("500 points, 0.5 ms steps", {"max_dt": 5e-4}, False, "full")]
_LBS_SAMPLED = {"mass_samples": 16000, "cubature_points": 3000}
"""Sampling at which LBS's bars and drop hardly move with the samples any more (16,000 mass samples and 3000 cubature
points: the bars' static sag within 2.5 % of 6000 points; docs/fidelity.md, "LBS's bars: the handles are the
resolution"), so that the handle ladder below measures the basis alone."""
_LBS_HANDLES = [
    ("10 handles, 16,000 samples, 3000 cubature points", dict(_LBS_SAMPLED), False, "fast"),
    ("20 handles, 16,000 samples, 3000 cubature points", {"handles": 20, **_LBS_SAMPLED}, False, "fast"),
    ("40 handles, 16,000 samples, 3000 cubature points", {"handles": 40, **_LBS_SAMPLED}, False, "fast")]
_LBS_WITH_HANDLES = _LBS + _LBS_HANDLES
_MPM_BAR = [("2 cells across the thickness", {"dx": 0.01}, False, "full"),
            ("3 cells across the thickness", {"dx": 0.02 / 3}, False, "full"),
            ("bake default (4 cells across the thinnest part)", {}, True, "full"),
            ("8 cells across the thickness", {"dx": 0.0025}, False, "full")]
LADDERS = {
    "cantilever_z": {"mpm": _MPM_BAR, "spring_mass": _SPRING, "lbs": _LBS_WITH_HANDLES},
    "cantilever_y": {"mpm": _MPM_BAR, "spring_mass": _SPRING, "lbs": _LBS_WITH_HANDLES},
    "drop": {"mpm": _MPM_CUBE, "spring_mass": _SPRING, "lbs": _LBS_WITH_HANDLES},
    "slide": {"mpm": _MPM_CUBE[:3], "spring_mass": _SPRING[:2], "lbs": _LBS[:2] + _LBS[3:4]},
    "drag_linear": {"mpm": _MPM_CUBE[:1] + _MPM_CUBE[2:3], "spring_mass": _SPRING[1:2], "lbs": _LBS[1:2]},
    "drag_quadratic": {"mpm": _MPM_CUBE[:1] + _MPM_CUBE[2:3], "spring_mass": _SPRING[1:2], "lbs": _LBS[1:2]},
}


def add_arguments(p):
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--scenes", default=",".join(LADDERS), help=f"comma-separated scenes (default: all: {','.join(LADDERS)})")
    p.add_argument("--solvers", default=",".join(SOLVER_NAMES), help="comma-separated solvers (default: all)")
    p.add_argument("--ladder", choices=("fast", "full", "defaults"), default="fast",
                   help="fast: the resolutions a 2-core CPU affords; full: also the fine levels (a GPU); defaults: "
                        "only each solver's bake default (the cross-solver agreement without the study)")
    p.add_argument("--referee", metavar="JSON", help="reference values from the independent referee "
                                                     "(scene -> metric -> value), for the scenes without a closed form")
    p.add_argument("--plots", metavar="DIR", help="write fidelity_<scene>.png figures here")
    p.add_argument("--trajectories", metavar="DIR", help="keep each run's tracked positions here (.npz), for re-plotting")


def load_referee(path) -> dict:
    """{scene: {metric: value}} from the referee's study JSON (``{"scenes": {scene: {metric: value}}}``)."""
    from ...core.errors import read_json

    doc = read_json(Path(path))
    scenes = doc.get("scenes", doc) if isinstance(doc, dict) else None
    if not isinstance(scenes, dict):
        from ...core.errors import UserError

        raise UserError(f"{path}: expected {{'scenes': {{scene: {{metric: value}}}}}}")
    return scenes


def run_scene(scene, solver: str, settings: dict, device: str):
    """(measurements, trajectory, wall seconds) of one scene run; a scene with a ``settle`` companion runs it too
    and merges its measurements (the trajectory and the cross-solver comparison are the main run's)."""
    from ...solvers import api

    t0 = time.perf_counter()
    traj = api.simulate(solver, scene.body, scene.material, scene.scenario, scene.frame_times, scene.effects,
                        device=device, settings=dict(settings))
    measured = scene.measure(traj)
    if scene.settle is not None:  # the static figures from the companion run (its trajectory is not kept)
        s = scene.settle
        settled = api.simulate(solver, s.body, s.material, s.scenario, s.frame_times, s.effects, device=device,
                               settings=dict(settings))
        measured.update(s.measure(settled))
    wall = time.perf_counter() - t0
    return measured, traj, wall


def trajectory_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance (m) between two (T, N, 3) tracked-point trajectories of the same points."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def run(args) -> list[dict]:
    from ...core.errors import UserError
    from ...solvers.registry import canonical_solver
    from ...solvers.warp_runtime import device_description, resolve_device
    from . import _scenes

    device = resolve_device(args.device)
    described = device_description(device)
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = [s for s in scenes if s not in LADDERS]
    if unknown:
        raise UserError(f"unknown scene(s) {unknown}; the scenes are {', '.join(LADDERS)}")
    solvers = [canonical_solver(s) for s in args.solvers.split(",") if s.strip()]
    referee = load_referee(args.referee) if args.referee else {}
    keep = Path(args.trajectories) if args.trajectories else None
    if keep:
        keep.mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    for name in scenes:
        scene = _scenes.scene(name)
        refs = {k: v for k, v in scene.reference.items()}
        units = dict(scene.units)
        if scene.settle is not None:
            refs.update(scene.settle.reference)
            units.update(scene.settle.units)
        for metric, value in referee.get(name, {}).items():
            if metric not in refs and isinstance(value, (int, float)):
                refs[metric] = (float(value), "independent referee (converged)")
        at_default: dict = {}
        for solver in solvers:
            for label, settings, default, level in LADDERS[name].get(solver, []):
                if (level == "full" and args.ladder == "fast") or (args.ladder == "defaults" and not default):
                    continue
                print(f"[fidelity] {name} / {solver} / {label} ...", flush=True)
                try:
                    measured, traj, wall = run_scene(scene, solver, settings, device)
                except Exception as exc:  # a resolution a solver cannot run is a result too
                    results.append({"case": f"{name}: {solver}, {label}", "device": described, "metric": "failed",
                                    "value": math.nan, "runs": 1, "error_message": str(exc)[:300],
                                    "scene": name, "solver": solver, "resolution": label, "default": default})
                    continue
                if keep:
                    save_npz(keep / f"{name}__{solver}__{label.replace(' ', '_')}.npz",
                             times=traj.times, positions=traj.positions)
                if default:
                    at_default[solver] = traj.positions
                for metric, value in measured.items():
                    entry = {"case": f"{name}: {solver}, {label}", "device": described, "metric": metric,
                             "value": float(value), "unit": units.get(metric, ""), "runs": 1,
                             "scene": name, "solver": solver, "resolution": label, "settings": settings,
                             "default": default, "wall_s": round(wall, 2)}
                    if metric in refs:
                        ref, source = refs[metric]
                        entry.update(reference=float(ref), reference_source=source,
                                     error=float(value / ref - 1.0) if ref else math.nan)
                    results.append(entry)
        if scene.cross_solver:
            names = sorted(at_default)
            for i, a in enumerate(names):
                for b in names[i + 1:]:
                    rmse = trajectory_rmse(at_default[a], at_default[b])
                    results.append({"case": f"{name}: {a} vs {b} at bake defaults", "device": described,
                                    "metric": "trajectory_rmse_over_size", "value": rmse / scene.size, "runs": 1,
                                    "rmse_m": rmse, "size_m": scene.size, "scene": name, "solvers": [a, b]})
    if args.plots:
        plot(results, Path(args.plots))
    return results


def plot(results: list[dict], out_dir: Path) -> list[Path]:
    """One figure per scene: each referenced metric against the runs' resolutions, per solver, with the reference
    and its ±5 % band; the bake default circled.  Returns the written paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    by_scene: dict = {}
    for r in results:
        if "reference" in r and "scene" in r and "solver" in r:
            by_scene.setdefault(r["scene"], []).append(r)
    colours = dict(zip(SOLVER_NAMES, ("tab:blue", "tab:green", "tab:orange")))
    for scene, rows in by_scene.items():
        metrics = sorted({r["metric"] for r in rows})
        fig, axes = plt.subplots(1, len(metrics), figsize=(5.2 * len(metrics), 4.0), squeeze=False)
        for ax, metric in zip(axes[0], metrics):
            sub = [r for r in rows if r["metric"] == metric]
            ref = sub[0]["reference"]
            ax.axhspan(ref * (1 - TOLERANCE), ref * (1 + TOLERANCE), color="0.85", label="reference ± 5 %")
            ax.axhline(ref, color="k", lw=1)
            for solver in SOLVER_NAMES:
                ladder = [label for label, *_ in LADDERS.get(scene, {}).get(solver, [])]
                pts = sorted((r for r in sub if r["solver"] == solver),  # the ladder's order, whatever the file's
                             key=lambda r: ladder.index(r["resolution"]) if r["resolution"] in ladder else len(ladder))
                for number, (varied, series) in enumerate(refinement_series(solver, pts)):
                    xs = np.arange(len(series))
                    ax.plot(xs, [r["value"] for r in series], ("o-", "s--", "^:")[min(number, 2)], color=colours[solver],
                            label=solver if number == 0 else f"{solver}: {varied}")
                    for x, r in zip(xs, series):
                        if r.get("default"):
                            ax.plot([x], [r["value"]], "o", ms=13, mfc="none", mec=colours[solver])
                        ax.annotate(r["resolution"], (x, r["value"]), fontsize=6, rotation=20,
                                    xytext=(3, 3), textcoords="offset points")
            ax.set_title(f"{scene}: {metric}\nreference: {sub[0]['reference_source']}", fontsize=8)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.set_xlabel("refinement level (coarse → fine; circled: bake default)")
            ax.set_ylabel(f"{metric} ({sub[0].get('unit', '')})")
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = out_dir / f"fidelity_{scene}.png"
        save_figure(fig, path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


COARSER_WHEN_LARGER = ("max_dt", "dx")
"""Settings whose larger value is the coarser run (a step, a cell size); the others refine as they grow."""


def refinement_series(solver: str, rows: list) -> list:
    """A solver's rows of one metric split into refinement series, one per setting the ladder varies (LBS's
    cubature points and its time step), each ordered coarse → fine with the bake default (settings ``{}``) in
    every series at its own value.  Rows that set several settings at once (LBS's handle ladder at a fixed, finer
    sampling) form one more series, named by the setting that varies among them and ordered by it.  Returns
    [(setting name or "", rows)]; one series when the ladder varies one setting (or when a default's value is not
    known, kept in the given order)."""
    from ...solvers.registry import SOLVERS

    compound = [r for r in rows if len(r.get("settings") or {}) > 1]
    rows = [r for r in rows if len(r.get("settings") or {}) <= 1]
    varied = []
    for r in rows:
        for name in (r.get("settings") or {}):
            if name not in varied:
                varied.append(name)
    defaults = SOLVERS[solver].defaults() if (len(varied) >= 2 or compound) else None

    def value(r, name):
        return (r.get("settings") or {}).get(name, getattr(defaults, name, None))

    def ordered(series, name):
        values = [value(r, name) for r in series]
        if all(v is not None for v in values):
            order = sorted(range(len(series)), key=lambda i: values[i], reverse=name in COARSER_WHEN_LARGER)
            series = [series[i] for i in order]
        return series

    if len(varied) < 2:
        out = [(varied[0] if varied else "", rows)] if rows else []
    else:
        out = []
        for name in varied:
            series = [r for r in rows if set(r.get("settings") or {}) in ({name}, set())]
            out.append((name, ordered(series, name)))
    if compound:
        keys = list(dict.fromkeys(k for r in compound for k in r["settings"]))
        moving = [k for k in keys if len({value(r, k) for r in compound}) > 1] or keys[:1]
        out.append((moving[0], ordered(compound, moving[0])))
    return out


def summary_table(results: list[dict]) -> str:
    """Markdown: per scene and metric, each solver's value at each resolution with its error against the reference."""
    rows = ["| scene | metric | solver | resolution | value | reference | error |", "|---|---|---|---|---|---|---|"]
    for r in results:
        if "solver" not in r or r.get("metric") in ("failed",):
            continue
        err = f"{100 * r['error']:+.1f} %" if "error" in r and math.isfinite(r["error"]) else ""
        mark = " (bake default)" if r.get("default") else ""
        rows.append(f"| {r['scene']} | {r['metric']} | {r['solver']} | {r['resolution']}{mark} | {r['value']:.5g} | "
                    f"{r.get('reference', ''):.5g} | {err} |" if "reference" in r else
                    f"| {r['scene']} | {r['metric']} | {r['solver']} | {r['resolution']}{mark} | {r['value']:.5g} | | |")
    return "\n".join(rows)


def main(argv=None):  # pragma: no cover - convenience for `python -m`
    import argparse

    p = argparse.ArgumentParser(description=HELP)
    add_arguments(p)
    args = p.parse_args(argv)
    results = run(args)
    print(summary_table(results))
    print(json.dumps(results, indent=1)[:2000])


if __name__ == "__main__":  # pragma: no cover
    main()
