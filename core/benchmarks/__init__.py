"""Benchmarks (``unipixie bench <name>``) and the one writer of ``benchmarks/<name>.json``.

Each benchmark is a module ``core/benchmarks/<name>.py`` with ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> list[dict]`` returning
result entries as ``shared/specs/benchmarks.md`` defines them::

    {"case": "1M particles, jelly, drop", "device": "NVIDIA H100 80GB HBM3",
     "metric": "particle_substeps_per_s", "value": 6.1e8, "runs": 5,
     "vs": {"what": "reference APIC kernel, same run", "ratio": 2.4}}

:func:`record` merges them into the JSON file: an entry replaces an earlier
one only when case, device and metric are the same; everything else is kept.
Each entry carries the ``commit`` and ``date`` it was measured at (given by the
caller, else the checkout's HEAD and today); the file's own ``commit`` and
``date`` are those of its latest write, not of every entry.
The benchmarks share their timing (:func:`median_time`, :func:`synchronized_times`, :func:`time_simulation`) and
the jelly sphere drop that ``bench lbs`` and ``bench spring`` both measure (:func:`sphere_drop`, :func:`sphere_mesh`).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import statistics
import subprocess
import time
from pathlib import Path
from typing import Callable, Iterable

REPO_ROOT = Path(__file__).resolve().parents[2]


def results_dir() -> Path:
    """``benchmarks/`` of the source checkout (``UNIPIXIE_BENCH_DIR`` overrides)."""
    d = Path(os.environ.get("UNIPIXIE_BENCH_DIR") or (REPO_ROOT / "benchmarks"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True,
                              text=True, timeout=10).stdout.strip() or "unknown"
    except Exception:
        return "unknown"


def record(name: str, results: Iterable[dict], path: Path | None = None) -> Path:
    """Merge ``results`` into ``benchmarks/<name>.json`` (see module docstring); returns the path.  Two benchmarks
    recording into the same file at once take turns (a lock; the second waits up to a minute), so neither's
    results are lost."""
    from ..atomic_io import OutputLock

    path = Path(path) if path else results_dir() / f"{name}.json"
    with OutputLock(path, "benchmark file", wait=60.0):
        return _merge(name, results, path)


def _merge(name: str, results: Iterable[dict], path: Path) -> Path:
    old = {"benchmark": name, "results": []}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except json.JSONDecodeError:
            pass
    entries = list(old.get("results", []))
    commit, today = git_commit(), _dt.date.today().isoformat()
    for r in results:
        missing = {"case", "device", "metric", "value", "runs"} - set(r)
        if missing:
            raise ValueError(f"benchmark entry lacks {sorted(missing)}: {r}")
        entries = [e for e in entries if (e.get("case"), e.get("device"), e.get("metric"))
                   != (r["case"], r["device"], r["metric"])]
        entry = dict(r)
        entry.setdefault("commit", commit)
        entry.setdefault("date", today)
        entries.append(entry)
    doc = {"benchmark": name, "commit": commit, "date": today, "results": entries}
    from ..atomic_io import write_json

    write_json(path, doc)
    return path


def median_time(fn: Callable[[], object], runs: int = 5, warmup: int = 1) -> tuple[float, list[float]]:
    """Median wall time in seconds of ``fn()`` over ``runs`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def synchronized_times(fn: Callable[[], object], runs: int, wp, device: str) -> list[float]:
    """Wall times in seconds of ``runs`` calls of ``fn()``, each between two ``wp.synchronize_device(device)``
    (so the work a call leaves queued on a GPU is counted)."""
    times = []
    for _ in range(runs):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return times


def time_simulation(sim, effects_lists: list | None, runs: int, wp, device: str) -> tuple:
    """Time a prepared simulation's run: ``sim.run([])``, or with ``effects_lists`` (one list of effects per
    environment) ``sim.run_batch(effects_lists)``; once untimed (the warm-up), then ``runs`` times by
    :func:`synchronized_times`.

    Returns ``(go, trajectory, median_s, environments)``: the timed call (for further runs), the warm-up run's
    trajectory (the first environment's of a batch), the median wall time in seconds and the number of environments
    (1 without a batch).
    """
    if effects_lists is None:
        go = lambda: sim.run([])  # noqa: E731
    else:
        go = lambda: sim.run_batch(effects_lists)  # noqa: E731
    trajectory = go()
    trajectory = trajectory[0] if isinstance(trajectory, list) else trajectory
    median_s = statistics.median(synchronized_times(go, runs, wp, device))
    environments = 1 if effects_lists is None else len(effects_lists)
    return go, trajectory, median_s, environments


# --------------------------------------------------------------------------- the jelly sphere drop
# the case of ``bench lbs`` and ``bench spring`` (the same object, so the two solvers' figures compare)
SPHERE_E, SPHERE_NU, SPHERE_DENSITY = 1.0e5, 0.3, 1000.0  # Pa, -, kg/m³
SPHERE_RADIUS = 0.1  # m


def sphere_drop():
    """(material, scenario) of the jelly sphere drop: homogeneous jelly of :data:`SPHERE_E`,
    :data:`SPHERE_NU`, :data:`SPHERE_DENSITY`, falling at 1 m/s onto a frictionless ground under gravity."""
    from ...solvers.material_sampling import HomogeneousMaterial
    from ...solvers.scenario import Scenario

    return (HomogeneousMaterial(SPHERE_E, SPHERE_NU, SPHERE_DENSITY),
            Scenario(initial_velocity=[0.0, 0.0, -1.0]))


def sphere_mesh(large: bool = False):
    """The dropped sphere (radius :data:`SPHERE_RADIUS`, its lowest point 2 cm above the ground) as a
    trimesh: an icosphere of 642 vertices, or (``large``) a UV sphere of 101,122 vertices."""
    import trimesh

    if large:
        mesh = trimesh.creation.uv_sphere(radius=SPHERE_RADIUS, count=[160, 320])
    else:
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=SPHERE_RADIUS)
    mesh.apply_translation((0.0, 0.0, SPHERE_RADIUS + 0.02))
    return mesh


def print_table(results: list[dict]) -> None:
    if not results:
        print("(no results)")
        return
    rows = [(r["case"], r["device"], r["metric"], f"{r['value']:.4g}", str(r["runs"]),
             (f"x{r['vs']['ratio']:.2f} vs {r['vs']['what']}" if r.get("vs") else "")) for r in results]
    headers = ("case", "device", "metric", "value", "runs", "comparison")
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(headers)]
    print("  ".join(h.ljust(w) for h, w in zip(headers, widths)))
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)))
