"""Synthetic measurements with hidden effects: rehearse the diagnosis, and test it.

:func:`synthesize` simulates a scenario with effects switched on (any solver), adds white
noise (σ per coordinate) and occlusions (contiguous runs of unobserved frames per point),
and returns a :class:`~unipixie.core.measurement.Measurement` whose scenario states the
material the model *believes* — which may differ from the one simulated
(``true_E_scale``), as a real model's prediction would.  The truth (effects, E scale,
solver, noise) is stored under the archive key ``synth_truth`` (JSON); the diagnosis never
reads it.

Shapes (closed triangle surfaces, tracked points = their vertices, ~``points`` of them):
``cube`` (0.2 m), ``bar`` (0.4 × 0.08 × 0.08 m), ``plate`` (0.3 × 0.3 × 0.05 m),
``sphere`` (radius 0.1 m).

Scenarios (ground z = 0):

* ``drop``: released 0.15 m above the ground with a sideways speed of 0.5 m/s; lands,
  bounces, vibrates and slides.
* ``clamped``: the low-x end (15 % of the length) held in a clamp, no ground; sags and
  vibrates under gravity.
* ``throw``: thrown at (1.5, 0, 2.5) m/s, no ground: free flight (``spin`` adds a rotation about y).
* ``slide``: resting on the ground, pushed along x at 1.5 m/s.
"""

from __future__ import annotations

import json
import math
from typing import Optional, Sequence

import numpy as np

from ...solvers import effects as fx
from ..errors import UserError
from ..measurement import MeasuredMaterial, Measurement
from ..progress import Progress

SHAPES = ("cube", "bar", "plate", "sphere")
SCENARIOS = ("drop", "clamped", "throw", "slide")
SHAPE_EXTENTS = {"cube": (0.2, 0.2, 0.2), "bar": (0.4, 0.08, 0.08), "plate": (0.3, 0.3, 0.05)}
SPHERE_RADIUS = 0.1


def box_surface(extents: Sequence[float], spacing: float):
    """A closed, outward-oriented box surface (``trimesh.Trimesh``) centred at the origin with
    vertices on a regular grid of about ``spacing`` metres on every face."""
    import trimesh

    ext = np.asarray(extents, dtype=np.float64)
    n = np.maximum(np.round(ext / spacing).astype(int), 1)
    verts, faces = [], []
    offset = 0
    for axis in range(3):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        for side in (-1.0, 1.0):
            us = np.linspace(-ext[u_ax] / 2, ext[u_ax] / 2, n[u_ax] + 1)
            vs = np.linspace(-ext[v_ax] / 2, ext[v_ax] / 2, n[v_ax] + 1)
            U, V = np.meshgrid(us, vs, indexing="ij")
            P = np.zeros(U.shape + (3,))
            P[..., axis] = side * ext[axis] / 2
            P[..., u_ax] = U
            P[..., v_ax] = V
            verts.append(P.reshape(-1, 3))
            nu, nv = U.shape
            idx = np.arange(nu * nv).reshape(nu, nv) + offset
            a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            faces.append(f)
            offset += nu * nv
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=True)
    mesh.merge_vertices()
    trimesh.repair.fix_normals(mesh)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def make_shape(shape: str, points: int = 250):
    """The closed surface of a built-in shape with about ``points`` vertices (metres, centred at 0)."""
    import trimesh

    if shape == "sphere":
        sub = 2 if points < 400 else 3
        mesh = trimesh.creation.icosphere(subdivisions=sub, radius=SPHERE_RADIUS)
        return mesh
    if shape not in SHAPE_EXTENTS:
        raise UserError(f"unknown shape {shape!r}; choose one of: {', '.join(SHAPES)}")
    ext = np.asarray(SHAPE_EXTENTS[shape])
    area = 2 * (ext[0] * ext[1] + ext[1] * ext[2] + ext[0] * ext[2])
    spacing = math.sqrt(area / max(points, 8))
    best = None
    for f in np.linspace(0.7, 1.4, 15):  # get close to the requested vertex count
        m = box_surface(ext, spacing * f)
        if best is None or abs(len(m.vertices) - points) < abs(len(best.vertices) - points):
            best = m
    return best


def make_scenario(name: str, mesh, notes: str = "", spin: float = 0.0):
    """Place ``mesh`` (moved in place) for the scenario and return its :class:`Scenario`.

    spin: rad/s about y added to the initial motion (all scenarios but ``clamped``)."""
    from ...solvers.scenario import Scenario

    lo, hi = mesh.bounds
    ext = hi - lo
    if name == "drop":
        mesh.apply_translation([-mesh.bounds[0][0] - ext[0] / 2, -mesh.bounds[0][1] - ext[1] / 2,
                                0.15 - mesh.bounds[0][2]])
        return Scenario(ground_height=0.0, initial_velocity=[0.5, 0.0, 0.0], initial_angular_velocity=[0, spin, 0],
                        notes=notes)
    if name == "clamped":
        mesh.apply_translation([-mesh.bounds[0][0], -mesh.bounds[0][1] - ext[1] / 2,
                                0.5 - mesh.bounds[0][2] - ext[2] / 2])
        lo, hi = mesh.bounds
        clamp = np.array([lo - 0.01, [lo[0] + 0.15 * ext[0], hi[1] + 0.01, hi[2] + 0.01]])
        return Scenario(ground_height=None, pinned_box=clamp, notes=notes)
    if name == "throw":
        mesh.apply_translation(-mesh.bounds.mean(0) + np.array([0.0, 0.0, 1.0]))
        return Scenario(ground_height=None, initial_velocity=[1.5, 0.0, 2.5], initial_angular_velocity=[0.0, spin, 0.0],
                        notes=notes)
    if name == "slide":
        mesh.apply_translation([-mesh.bounds[0][0] - ext[0] / 2, -mesh.bounds[0][1] - ext[1] / 2,
                                -mesh.bounds[0][2] + 1e-4])
        return Scenario(ground_height=0.0, initial_velocity=[1.5, 0.0, 0.0], initial_angular_velocity=[0, 0, spin],
                        notes=notes)
    raise UserError(f"unknown scenario {name!r}; choose one of: {', '.join(SCENARIOS)}")


def occlusion_mask(frames: int, points: int, fraction: float, rng: np.random.Generator,
                   mean_run: float = 8.0) -> np.ndarray:
    """(T, N) bool, True where hidden: contiguous runs (geometric lengths, mean ``mean_run`` frames)
    placed at random until about ``fraction`` of all samples are hidden."""
    if not 0.0 <= fraction < 1.0:
        raise UserError(f"occlusion must be a fraction in [0, 1), got {fraction}")
    hidden = np.zeros((frames, points), dtype=bool)
    target = int(round(fraction * frames * points))
    guard = 0
    while hidden.sum() < target and guard < 100 * (target + 1):
        guard += 1
        p = int(rng.integers(points))
        length = int(min(rng.geometric(1.0 / mean_run), frames))
        start = int(rng.integers(0, max(frames - length + 1, 1)))
        hidden[start:start + length, p] = True
    return hidden


def synthesize(effects: Sequence = (), solver: str = "mpm", *, shape: str = "cube", scenario: str = "drop",
               noise: float = 0.001, occlusion: float = 0.1, duration: float = 1.0, fps: float = 100.0,
               points: int = 250, E: float = 2.0e5, nu: float = 0.3, density: float = 1000.0,
               true_E_scale: float = 1.0, spin: float = 0.0, velocity: Optional[Sequence[float]] = None,
               height: Optional[float] = None, seed: int = 0, device: str = "cpu", settings=None,
               progress: Optional[Progress] = None) -> Measurement:
    """A measurement of ``shape`` in ``scenario`` simulated by ``solver`` with hidden ``effects``.

    effects: effect objects or specs (``"wind:acceleration=0,0.5,0"``).
    noise: σ (m) of white noise per coordinate.  occlusion: fraction of samples hidden.
    duration (s) and fps: the instants are ``0, 1/fps, ..., duration``.
    E (Pa), nu, density (kg/m³): the material the file states; the simulation uses
    ``E × true_E_scale`` (a model that is close but not identical to the truth).
    spin: rad/s of initial rotation (about y; about z when sliding on the ground).
    velocity: (3,) m/s initial velocity replacing the scenario's.  height: metres between the ground
    and the lowest point at the start (``drop`` / ``slide``), replacing the scenario's.
    settings: the generating solver's settings (e.g. a finer discretisation than the diagnosis uses).
    """
    from ...solvers import api
    from ...solvers.body import Body

    effs = [fx.parse(e) if isinstance(e, str) else e for e in effects]
    for e in effs:
        if not isinstance(e, fx.Effect):
            raise UserError(f"not an effect: {e!r}")
    if noise < 0 or not math.isfinite(noise):
        raise UserError(f"noise must be a non-negative number of metres, got {noise}")
    if duration <= 0 or fps <= 0:
        raise UserError("duration and fps must be positive")
    if not (true_E_scale > 0):
        raise UserError("true_E_scale must be positive")
    solver = api.canonical_solver(solver)
    fx.check_supported(effs, solver)
    believed = MeasuredMaterial(float(E), float(nu), float(density))
    mesh = make_shape(shape, points)
    sc = make_scenario(scenario, mesh, notes=f"synthetic measurement ({shape}, {scenario}) made by unipixie measure synth",
                       spin=float(spin))
    if velocity is not None:
        sc.initial_velocity = np.asarray(velocity, dtype=np.float64).reshape(3)
    if height is not None:
        if sc.ground_height is None:
            raise UserError(f"the {scenario} scenario has no ground; 'height' applies to drop and slide")
        mesh.apply_translation([0.0, 0.0, sc.ground_height + float(height) - mesh.bounds[0][2]])
    frames = int(round(duration * fps)) + 1
    times = np.arange(frames) / fps
    body = Body.from_mesh(mesh)
    rest = np.asarray(body.tracked_points, dtype=np.float64)
    truth_material = believed.scaled(true_E_scale)
    sim = api.prepare(solver, body, truth_material.to_spec(rest), sc, times, device=device, settings=settings,
                      progress=progress)
    traj = sim.run(effs, progress=progress)
    clean = np.asarray(traj.positions, dtype=np.float64)
    rng = np.random.default_rng(seed)
    measured = clean + rng.normal(scale=noise, size=clean.shape) if noise > 0 else clean.copy()
    hidden = occlusion_mask(frames, len(rest), occlusion, rng) if occlusion > 0 else np.zeros(clean.shape[:2], bool)
    measured[hidden] = np.nan
    truth = {"effects": [e.to_dict() for e in effs], "solver": solver, "true_E_scale": float(true_E_scale),
             "noise_sigma": float(noise), "occlusion": float(occlusion), "shape": shape, "scenario": scenario,
             "spin": float(spin), "seed": int(seed), "velocity": None if velocity is None else list(map(float, velocity)),
             "height": height,
             "settings": {k: v for k, v in (settings or {}).items()} if isinstance(settings, dict) else None}
    faces = np.asarray(body.mesh.faces, dtype=np.int64)
    m = Measurement(positions=measured, times=times, scenario=sc, rest_positions=rest, faces=faces,
                    material=believed, extra_arrays={"synth_truth": np.array(json.dumps(_jsonable(truth)))},
                    source=f"synthetic {shape}/{scenario}")
    return m


def truth_of(measurement: Measurement) -> Optional[dict]:
    """The hidden truth of a synthetic measurement (``None`` for real data)."""
    t = measurement.extra_arrays.get("synth_truth")
    return None if t is None else json.loads(str(t))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
