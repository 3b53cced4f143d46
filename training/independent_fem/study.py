"""The referee's convergence study and its reference numbers for the canonical scenes.

The canonical scenes (:mod:`unipixie.core.benchmarks._scenes`, read only for their constants and their
measurement definitions) need a reference where no closed form exists: the soft cube dropped onto the
floor (peak height of the centre of mass after the first contact, contact duration).  This module
computes it with the independent FEM (:mod:`unipixie.training.independent_fem`, no solver code of the
project) and shows that it is converged: each case runs at a ladder of mesh and time-step levels, and
the difference between the two finest levels is reported beside the value.  The drop is run under both
contact laws (a hard inelastic projection and an undamped penalty spring), because neither is the truth.
The clamped bars (static tip sag, first bending frequency) are measured on quadratic tetrahedra
(:mod:`.linear`) against Euler–Bernoulli.

``python -m unipixie.training.independent_fem.study --out benchmarks/referee_fem.json`` writes the JSON
that ``unipixie bench fidelity --referee`` reads (``{"scenes": {scene: {metric: value}}, ...}``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from . import FEMModel, FEMSettings, box_tet_mesh
from ...core.atomic_io import write_json
from ...core.errors import UserError

DROP_DURATION = 0.36
"""s, the drop scene's record (frames every 1 ms)."""
CASES = ("drop", "cantilever_z", "cantilever_y")
"""The cases :func:`convergence_study` knows."""
DROP_LEVELS = ({"cells": 4, "safety": 0.25}, {"cells": 8, "safety": 0.25}, {"cells": 12, "safety": 0.25},
               {"cells": 12, "safety": 0.125})
"""The drop's ladder: cells along each edge of the cube (6 linear tetrahedra per cell) and the fraction of the
RK4 stability limit used as the step; the last level halves the step of the finest mesh."""
BAR_LEVELS = ({"across": 1}, {"across": 2}, {"across": 3}, {"across": 4})
"""The bars' ladder: quadratic-tetrahedron cells across the bar's thickness (0.02 m)."""
DROP_LAWS = {"hard": {"contact_law": "hard"},
             "penalty": {"contact_law": "penalty", "contact_damping_ratio": 0.0}}
"""The drop's contact laws: the inelastic projection, and an undamped penalty spring that returns what it stores."""


def _scenes():
    from ...core.benchmarks import _scenes

    return _scenes


def _drop(cells: int, safety: float = 0.25, contact_law: str = "hard", contact_damping_ratio: float = 0.0,
          contact_stiffness: float = 1.0, friction: float = 0.0, duration: Optional[float] = None,
          floor: Optional[tuple[float, float]] = None) -> dict:
    """Run the canonical drop (arguments: :func:`drop_figures`); {"model", "mesh", "frames" (F,) s, "x" (F, n, 3) m,
    "com" (F,) m: the measured centre's height, "lowest" (F,) m, "mass_centre" (F,) m, "on_lattice", "wall_s"}."""
    sc = _scenes()
    if cells < 1:
        raise UserError(f"cells must be 1 or more, got {cells}")
    s = sc.CUBE_SIZE
    mesh = box_tet_mesh((s, s, s), centre=(0.0, 0.0, sc.DROP_HEIGHT + s / 2), spacing=s / cells)
    material = {"E": sc.CUBE_E, "nu": sc.CUBE_NU, "density": sc.CUBE_DENSITY}
    scenario = {"gravity": [0.0, 0.0, -sc.G], "ground": {"height": 0.0}, "initial_velocity": [0.0, 0.0, 0.0]}
    effects = [f"ground_friction:mu={friction}"] if friction > 0 else []
    if floor is not None:
        effects.append(f"contact_damping:k={floor[0]},c={floor[1]}")
    settings = FEMSettings(safety=safety, contact_law=contact_law, contact_damping_ratio=contact_damping_ratio,
                           contact_stiffness=contact_stiffness)
    model = FEMModel(mesh, material, scenario, effects, settings)
    frames = np.linspace(0.0, DROP_DURATION, int(round(DROP_DURATION * 1000)) + 1)  # the scene's 1 ms frames
    if duration is not None:
        frames = frames[frames <= duration + 1e-12]
    t0 = time.perf_counter()
    x = model.run(frames)
    wall = time.perf_counter() - t0
    z = x[:, :, 2]
    mass_centre = z @ model.mass / model.mass.sum()
    lattice = sc.lattice(mesh.nodes.min(0), mesh.nodes.max(0), (5, 5, 5))
    dist, idx = _nearest(mesh.nodes, lattice)
    on_lattice = bool(np.all(dist < 1e-9 * s))
    return {"model": model, "mesh": mesh, "frames": frames, "x": x, "mass_centre": mass_centre,
            "com": z[:, idx].mean(1) if on_lattice else mass_centre, "lowest": z[:, idx].min(1) if on_lattice else z.min(1),
            "on_lattice": on_lattice, "wall_s": wall}


def drop_centre(cells: int, duration: Optional[float] = None, floor: Optional[tuple[float, float]] = None,
                **settings) -> tuple[np.ndarray, np.ndarray]:
    """(centre (F,) m, frames (F,) s): the measured centre's height over the canonical drop at 1 ms frames (the
    scene's 5 × 5 × 5 lattice mean when ``cells`` is a multiple of 4); arguments as :func:`drop_figures`."""
    run = _drop(cells, duration=duration, floor=floor, **settings)
    return run["com"], run["frames"]


def drop_figures(cells: int, safety: float = 0.25, contact_law: str = "hard", contact_damping_ratio: float = 0.0,
                 contact_stiffness: float = 1.0, friction: float = 0.0, duration: Optional[float] = None,
                 floor: Optional[tuple[float, float]] = None) -> dict:
    """The canonical drop (0.2 m cube, E, ν, ρ of the scene, lower face 0.1 m above a rigid floor, released at
    rest, 1 ms frames) on ``cells``³ cells × 6 linear tetrahedra, RK4 at ``safety`` × its stability limit.

    Returns {"rebound_peak": m, peak of the centre of mass after the first contact (the scene's measure: the
    mean of its 5 × 5 × 5 lattice of tracked points when ``cells`` is a multiple of 4, else the mass centre);
    "rebound_peak_mass_centre": m; "contact_duration": s, "first_contact": s (the lowest tracked point within
    the scene's 0.5 mm of the floor); "lowest": m, the lowest node height over the run; "energy_kept": total
    energy at the end over that at release, measured from rest on the floor; "nodes", "tets", "dt": s,
    "steps", "wall_s"}.  ``friction`` is a Coulomb μ (0: the scene's frictionless floor); ``floor`` = (k Pa/m, c Pa·s/m) makes the
    floor give and damp (the ``contact_damping`` effect; the contact law is then not used).
    """
    sc = _scenes()
    s = sc.CUBE_SIZE
    run = _drop(cells, safety, contact_law, contact_damping_ratio, contact_stiffness, friction, duration, floor)
    model, mesh, frames, x = run["model"], run["mesh"], run["frames"], run["x"]
    com, lowest, mass_centre, on_lattice, wall = (run[k] for k in ("com", "lowest", "mass_centre", "on_lattice",
                                                                   "wall_s"))
    z = x[:, :, 2]
    first, last = sc.contact_interval(frames, lowest)
    after = frames > last
    peak = float(com[after].max()) if np.isfinite(last) and after.any() else math.nan
    peak_mc = float(mass_centre[after].max()) if np.isfinite(last) and after.any() else math.nan
    xf, vf = model.final_state
    e0 = model.energy(model.X, model.v0)["total"] - model.mass.sum() * sc.G * s / 2
    e1 = model.energy(xf, vf)["total"] - model.mass.sum() * sc.G * s / 2
    return {"rebound_peak": peak, "rebound_peak_mass_centre": peak_mc, "measured_on": "lattice" if on_lattice else "mass centre",
            "contact_duration": last - first, "first_contact": first, "lowest": float(z.min()),
            "energy_kept": float(e1 / e0), "nodes": int(len(mesh.nodes)), "tets": int(len(mesh.tets)),
            "dt": float(model.dt_max), "steps": int(model.steps_taken), "wall_s": wall}


def _nearest(nodes: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial import cKDTree

    return cKDTree(nodes).query(points)


def cantilever_figures(direction: str, across: int) -> dict:
    """The canonical cantilever (0.5 × 0.04 × 0.02 m, clamped over its first 0.05 m, E, ν, ρ of the scene)
    bending under gravity along -``direction`` ("z": across its thin side, "y": its wide side), on cells
    thickness / ``across`` square in the section and about twice as long along the bar (a cell boundary on the
    clamp's edge), cut into 6 quadratic tetrahedra each; small-deformation statics and modes.

    Returns {"tip_sag": m, the mean deflection of the free end face; "frequency": Hz, the lowest mode whose
    end face moves along the deflection; "euler_bernoulli_sag": m, "euler_bernoulli_frequency": Hz;
    "cell_length": m, "nodes", "tets", "dofs", "wall_s"}.
    """
    from .linear import clamped_response

    sc = _scenes()
    if direction not in ("z", "y"):
        raise UserError(f"direction must be 'z' or 'y', got {direction!r}")
    if across < 1:
        raise UserError(f"across must be 1 or more, got {across}")
    L, b, h, clamp = sc.BAR_LENGTH, sc.BAR_WIDTH, sc.BAR_THICKNESS, sc.BAR_CLAMP
    free = L - clamp
    # cells: ``across`` through the thickness, square in the section, about twice as long along the bar, and a
    # number along it that puts a cell boundary on the clamp's edge (the clamp is 1/10 of the length)
    pitch = h / across
    along = int(round(L / clamp)) * max(1, int(round(L / (2 * pitch) / round(L / clamp))))
    spacing = np.array([L / along, pitch, pitch])
    mesh = box_tet_mesh((L, b, h), centre=(L / 2 - clamp, 0.0, 0.5), spacing=spacing)
    pinned = mesh.nodes[:, 0] <= 1e-9 * L
    axis = 2 if direction == "z" else 1
    gravity = np.zeros(3)
    gravity[axis] = -sc.G
    t0 = time.perf_counter()
    r = clamped_response(mesh, {"E": sc.BAR_E, "nu": sc.BAR_NU, "density": sc.BAR_DENSITY}, gravity, pinned)
    wall = time.perf_counter() - t0
    end = np.isclose(r.nodes[:, 0], free)
    sag = -float(r.static[end, axis].mean())
    moves = np.abs(r.modes[:, end].mean(1))  # (k, 3) the end face's mean motion per mode
    along = np.nonzero(moves[:, axis] > 0.5 * np.linalg.norm(moves, axis=1))[0]
    freq = float(r.frequencies[along[0]]) if len(along) else math.nan
    depth, width = (h, b) if axis == 2 else (b, h)
    EI = sc.BAR_E * width * depth ** 3 / 12
    rhoA = sc.BAR_DENSITY * b * h
    return {"tip_sag": sag, "frequency": freq, "euler_bernoulli_sag": rhoA * sc.G * free ** 4 / (8 * EI),
            "euler_bernoulli_frequency": 1.875104 ** 2 / (2 * math.pi * free ** 2) * math.sqrt(EI / rhoA),
            "cell_length": float(spacing[0]), "nodes": int(len(r.nodes)), "tets": int(len(mesh.tets)), "dofs": r.dofs,
            "wall_s": wall}


def convergence_study(case: str, levels: Optional[Sequence[dict]] = None, contact_law: str = "hard",
                      log=None) -> list[dict]:
    """The figures of interest of ``case`` (one of :data:`CASES`) at each refinement level.

    levels: for "drop", dicts of :func:`drop_figures` keywords (``cells``, ``safety``; default
    :data:`DROP_LEVELS`); for the cantilevers, dicts with ``across`` (default :data:`BAR_LEVELS`).
    contact_law: for "drop", a key of :data:`DROP_LAWS` ("hard" or "penalty").
    Returns one dict per level: {"level": the level's settings, "figures": ...} with mesh size (``spacing``
    m), step (``dt`` s, drop only) and ``wall_s`` among the figures.
    """
    if case not in CASES:
        raise UserError(f"unknown case {case!r}; the cases are {', '.join(CASES)}")
    out = []
    if case == "drop":
        if contact_law not in DROP_LAWS:
            raise UserError(f"unknown contact law {contact_law!r}; the drop's laws are {', '.join(DROP_LAWS)}")
        for level in levels or DROP_LEVELS:
            figures = drop_figures(**level, **DROP_LAWS[contact_law])
            figures["spacing"] = _scenes().CUBE_SIZE / level["cells"]
            out.append({"level": dict(level), "figures": figures})
            if log:
                log(f"drop/{contact_law} {level}: {_brief(figures)}")
    else:
        for level in levels or BAR_LEVELS:
            figures = cantilever_figures(case[-1], **level)
            figures["spacing"] = _scenes().BAR_THICKNESS / level["across"]
            out.append({"level": dict(level), "figures": figures})
            if log:
                log(f"{case} {level}: {_brief(figures)}")
    return out


def _brief(f: dict) -> str:
    return ", ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in f.items())


def change_between_finest(levels: list[dict], metric: str, finest: int = -1, previous: int = -2) -> float:
    """|figure at level ``finest`` − at level ``previous``| (same unit as the figure)."""
    return abs(levels[finest]["figures"][metric] - levels[previous]["figures"][metric])


def reference_study(drop_levels: Sequence[dict] = DROP_LEVELS, bar_levels: Sequence[dict] = BAR_LEVELS,
                    log=print) -> dict:
    """The whole study: the drop under both contact laws and both cantilevers, with the reference values
    (``scenes``: the finest level; the drop's under the hard law, the rigid floor of the scene) and their
    convergence (``convergence``: the change between the two finest mesh levels, and between the two steps
    of the finest mesh)."""
    studies: dict = {}
    for law in DROP_LAWS:
        studies[f"drop/{law}"] = convergence_study("drop", drop_levels, law, log=log)
    for case in ("cantilever_z", "cantilever_y"):
        studies[case] = convergence_study(case, bar_levels, log=log)
    return summarise(studies)


def summarise(studies: dict) -> dict:
    """The JSON of :func:`reference_study` from its studies ({"drop/<law>" or case: convergence_study(...)}; each
    with at least two levels)."""
    scenes: dict = {}
    convergence: dict = {}
    best_drop: dict = {}
    for key, levels in studies.items():
        if key.startswith("drop"):
            mesh_levels = [i for i, lv in enumerate(levels) if lv["level"].get("safety", 0.25) == 0.25]
            cells = [lv["level"]["cells"] for lv in levels]
            stepped = max((c for c in cells if cells.count(c) > 1), default=cells[mesh_levels[-1]])
            step_levels = [i for i, c in enumerate(cells) if c == stepped]
            metrics = ("rebound_peak", "contact_duration")
            conv = {m: {"mesh": change_between_finest(levels, m, mesh_levels[-1], mesh_levels[-2]),
                        "step": (change_between_finest(levels, m, step_levels[-1], step_levels[0])
                                 if len(step_levels) > 1 else None)} for m in metrics}
            best = levels[mesh_levels[-1]]["figures"]
        else:
            metrics = ("tip_sag", "frequency")
            conv = {m: {"mesh": change_between_finest(levels, m)} for m in metrics}
            best = levels[-1]["figures"]
        convergence[key] = conv
        values = {m: best[m] for m in metrics}
        if key.startswith("drop"):
            best_drop[key] = values
        if key == "drop/hard":
            scenes["drop"] = values
        elif not key.startswith("drop"):
            scenes[key] = values
    return {"scenes": scenes, "scenes_by_contact_law": {k.split("/")[1]: best_drop[k] for k in best_drop},
            "convergence": convergence, "studies": studies,
            "simulator": "unipixie.training.independent_fem (drop: linear tets, fixed-corotated, RK4; bars: "
                         "quadratic tets, linear elasticity)",
            "machine": {"cpus": os.cpu_count(), "loadavg": _loadavg()}}


def _loadavg() -> Optional[str]:
    try:
        return Path("/proc/loadavg").read_text().strip()
    except OSError:
        return None


def main(argv: Optional[Sequence[str]] = None) -> None:
    p = argparse.ArgumentParser(description="The independent referee's convergence study on the canonical scenes.")
    p.add_argument("--out", default="benchmarks/referee_fem.json", help="the JSON written (atomically)")
    p.add_argument("--quick", action="store_true", help="the two coarsest levels only (minutes less)")
    args = p.parse_args(argv)
    drop = DROP_LEVELS[:2] if args.quick else DROP_LEVELS
    bars = BAR_LEVELS[:2] if args.quick else BAR_LEVELS
    result = reference_study(drop, bars)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, result, indent=1)
    print(json.dumps({"scenes": result["scenes"], "convergence": result["convergence"]}, indent=1))


if __name__ == "__main__":
    main()
