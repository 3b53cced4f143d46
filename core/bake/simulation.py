"""Running a bake's simulation: :func:`simulate` resolves the material, builds the body, checks the up-front
cost, runs the chosen solver with progress and cancellation and returns a :class:`SimulationResult` (the
trajectory plus what the writer needs); :class:`FrameProgress` counts the solvers' per-frame steps, and a
trajectory that does not fit the object is refused (:func:`check_trajectory`).

Uses :mod:`.body`, :mod:`.options`, the cost estimate (:mod:`unipixie.core.cost`) and the solvers' interface
(:mod:`unipixie.solvers.api`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import UserError
from ..progress import Progress, silent
from .body import BakeObject, build_body
from .options import BakeOptions


@dataclass
class SimulationResult:
    """What the Blender writer needs from a simulation.

    trajectory: the solver's Trajectory (world metres; positions of the object's vertices).
    skinning_weights: LBS only — (N, H+1) float64 handle weights of the vertices, the constant handle
        last, as the LBS solver defines them (see :func:`lbs_blend_form`).
    material_description / warnings / seconds: for the report and the bake record.
    ground_height: world z (metres) of the ground plane the run used, or None; an armature bake
        keeps the skinned vertices above it as the solver's tracked points are (:func:`plan_armature`).
    """

    trajectory: object
    skinning_weights: Optional[np.ndarray] = None
    material_description: str = ""
    warnings: list = field(default_factory=list)
    seconds: float = 0.0
    ground_height: Optional[float] = None


def simulate(obj: BakeObject, scenario, options: BakeOptions, progress: Optional[Progress] = None) -> SimulationResult:
    """Resolve the material, build the body, run the solver (cancellable through ``progress``).

    Raises :class:`UserError` for bad input and
    :class:`~unipixie.core.errors.CancelledError` when ``progress`` is cancelled.
    """
    from ...solvers import api
    from ...solvers.warp_runtime import resolve_device

    progress = progress or silent()
    t0 = time.perf_counter()
    progress.set_status("checking the mesh")
    body, warnings = build_body(obj, options.solver)
    if scenario.ground_height is not None:
        lowest = float(body.rest_points[:, 2].min())
        if lowest < scenario.ground_height - 1e-6 * max(obj.size, 1e-9):
            warnings.append(f"object '{obj.name}' starts {scenario.ground_height - lowest:.3g} m below the ground "
                            "plane; the ground will push it up")
    progress.set_status("resolving the material")
    resolved = options.material.resolve(obj, options.alpha, options.solver)
    warnings.extend(resolved.warnings)
    settings = _merge_settings(resolved.settings, options.solver_settings)
    from ..cost import estimate

    est = estimate(f"baking '{obj.name}'", options.solver, size=max(float(obj.size), 1e-9), times=options.times(),
                   material_spec=resolved.spec, points=obj.vertex_count, settings=settings)
    est.check(options.allow_long, remedy="bake fewer frames or use a coarser solver setting")
    progress.set_status(f"estimated cost: {est.describe()}")
    device = resolve_device(options.device)
    progress.set_status(f"preparing the {options.solver} simulation")
    sim = api.prepare(options.solver, body, resolved.spec, scenario, options.times(), device=device,
                      settings=settings, progress=progress)
    progress.set_status(f"simulating {options.frames.count} frames")
    traj = sim.run(options.effects, progress=FrameProgress(progress, options.frames.count - 1),
                   particle_states=bool(options.particles))
    # the solver's own notes (a coarse grid for thin parts, a class it models as elastic); the body's are above
    warnings.extend(w for w in getattr(sim, "warnings", []) if w not in body.warnings and w not in warnings)
    check_trajectory(traj, obj.vertex_count, options.frames.count, obj.name)
    weights = None
    if options.solver == "lbs":
        weights = lbs_vertex_weights(sim, traj, obj)
    return SimulationResult(traj, skinning_weights=weights, material_description=resolved.description,
                            warnings=warnings, seconds=time.perf_counter() - t0,
                            ground_height=scenario.ground_height)


class FrameProgress(Progress):
    """Forwards a solver's per-frame ``step`` calls to ``parent`` as a fraction of ``frames``.

    Solvers advance their progress once per simulated frame but in different units (one step, or
    1/(T−1)); counting the calls gives the same fraction for all.  Status text and cancellation are
    passed through.
    """

    def __init__(self, parent: Progress, frames: int):
        super().__init__(total=1.0, description=parent.description, show_bar=False)
        self.parent = parent
        self._cancel = parent._cancel
        self.frames = max(int(frames), 1)
        self.calls = 0

    def step(self, amount: float = 1.0, status: str | None = None) -> None:
        if amount > 0:
            self.calls += 1
        target = min(self.calls, self.frames) / self.frames * self.parent.total
        self.parent.step(max(0.0, target - self.parent.done), status)


def _merge_settings(source_settings, user_settings):
    if not source_settings:
        return user_settings
    if user_settings is None:
        return dict(source_settings)
    if isinstance(user_settings, dict):
        return {**source_settings, **user_settings}
    for k, v in source_settings.items():  # a settings object: fill what the user left at its default
        if hasattr(user_settings, k):
            setattr(user_settings, k, v)
    return user_settings


def check_trajectory(traj, n_vertices: int, n_frames: int, name: str = "") -> None:
    """Refuse a trajectory that does not fit the object (wrong shapes, NaN): never write garbage."""
    pos = np.asarray(traj.positions)
    if pos.shape != (n_frames, n_vertices, 3):
        raise UserError(f"object '{name}': the solver returned positions of shape {pos.shape}, expected "
                        f"{(n_frames, n_vertices, 3)} (frames, vertices, 3)")
    if not np.all(np.isfinite(pos)):
        from ..errors import SimulationDiverged

        bad_t = int(np.argmax(~np.all(np.isfinite(pos), axis=(1, 2))))
        raise SimulationDiverged(f"object '{name}': the simulation produced NaN/inf positions at frame index {bad_t}; "
                                 "try a smaller time step or a softer material")


def lbs_vertex_weights(sim, traj, obj: BakeObject) -> Optional[np.ndarray]:
    """(N, H+1) skinning weights of the vertices (the constant handle last) from the LBS simulation
    (``sim.weights(points)``, :mod:`unipixie.solvers.lbs`); ``None`` if it has none that fit the
    handles (the bake then stores the motion per vertex)."""
    fn = getattr(sim, "weights", None)
    if traj.handle_transforms is None or not callable(fn):
        return None
    w = np.asarray(fn(np.asarray(sim.tracked_rest, dtype=np.float64)), dtype=np.float64)
    return w if w.shape == (obj.vertex_count, traj.handle_transforms.shape[1]) else None
