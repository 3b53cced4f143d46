"""Writing a finished simulation: :func:`write_result` picks the output (:func:`unipixie.core.bake.choose_output`,
the armature plan or its per-vertex fallback), clears a previous bake, runs the writer, stores the bake record and
returns a :class:`BakeReport`; if writing fails or is closed (Esc) everything written so far is removed again.

Uses bpy, :mod:`unipixie.core.bake` and the writers of this package (:mod:`.shape_keys`, :mod:`.mesh_cache`,
:mod:`.armature`, :mod:`.particles`), :mod:`.removal`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterator, Optional

from ...bake import (BAKE_RECORD_KEY, BakeObject, BakeOptions, SimulationResult, choose_output, effects_to_json,
                     make_record, plan_armature, trajectory_to_local, vertex_output)
from .armature import write_armature
from .mesh_cache import cache_folder, write_mesh_cache
from .particles import write_particles
from .removal import bake_record, clear_bake, remove_recorded
from .shape_keys import write_shape_keys
from .writing import WriteRecord


@dataclass
class BakeReport:
    """What a bake did: ``mode`` (shape_keys / mesh_cache / armature), frames, timings and notes."""

    object: str
    solver: str
    mode: str
    frames: tuple
    simulate_seconds: float
    write_seconds: float
    material: str
    notes: list = field(default_factory=list)
    files: list = field(default_factory=list)
    armature_error: Optional[float] = None
    trajectory: object = field(default=None, repr=False)
    """The solver's :class:`~unipixie.core.types.Trajectory` (world metres; in memory only, not saved)."""

    def summary(self) -> str:
        return (f"baked '{self.object}' with {self.solver} ({self.material}) as {self.mode.replace('_', ' ')}, "
                f"frames {self.frames[0]}-{self.frames[1]}: simulation {self.simulate_seconds:.1f} s, "
                f"writing {self.write_seconds:.2f} s")


def write_result(obj, bo: BakeObject, result: SimulationResult, options: BakeOptions,
                 report: Optional[dict] = None) -> Iterator[tuple[float, str]]:
    """Write a finished simulation to Blender data; yields ``(fraction, status)``, returns a :class:`BakeReport`.

    Any previous UniPixie bake on the object is cleared first.  If writing fails or the generator is
    closed (Esc), everything written so far is removed again: there is never a half-written bake.
    """
    t0 = time.perf_counter()
    traj = result.trajectory
    frames = options.frames.frames
    notes = list(result.warnings)
    me = obj.data
    own_keys = me.shape_keys is not None and bake_record(obj) is None
    mode, more = choose_output(options.solver, options.output, bo.vertex_count, len(frames),
                               has_other_shape_keys=own_keys, mesh_shared=me.users > 1)
    notes.extend(more)
    if bake_record(obj) is not None:
        clear_bake(obj)
    plan = None
    if mode == "armature":
        if traj.handle_transforms is None or result.skinning_weights is None:
            reason = "the LBS run returned no handle transforms / vertex weights"
        else:
            plan, reason = plan_armature(bo, result.skinning_weights, traj.handle_transforms, traj.positions,
                                         options.armature_tolerance, result.ground_height)
        if plan is None:
            fallback = vertex_output(bo.vertex_count, len(frames), me.shape_keys is not None, me.users > 1, [])
            notes.append(f"LBS handles baked per vertex ({fallback.replace('_', ' ')}) instead of an armature: {reason}")
            mode = fallback
    record = WriteRecord(obj.name)
    done = False
    try:
        if mode == "armature":
            for f in write_armature(obj, bo, plan, frames, options.interpolation, record):
                yield 0.9 * f, "writing the armature"
        else:
            local = trajectory_to_local(bo, traj.positions)
            if mode == "shape_keys":
                for f in write_shape_keys(obj, local, frames, options.interpolation, record):
                    yield 0.9 * f, "writing shape keys"
            else:
                folder, more = cache_folder(obj.name, options, record)
                notes.extend(more)
                for f in write_mesh_cache(obj, local, frames, options.interpolation, folder, record):
                    yield 0.9 * f, "writing the PC2 cache"
        if options.particles:
            for f in write_particles(obj, bo, traj, frames, options, record, notes):
                yield 0.9 + 0.1 * f, "writing the particle object"
        rep = BakeReport(object=obj.name, solver=options.solver, mode=mode, frames=(int(frames[0]), int(frames[-1])),
                         simulate_seconds=result.seconds, write_seconds=time.perf_counter() - t0,
                         material=result.material_description, notes=notes, files=list(record.files),
                         armature_error=None if plan is None else plan.max_error, trajectory=traj)
        obj[BAKE_RECORD_KEY] = make_record(
            **record.to_dict(), mode=mode, solver=options.solver, frames=[int(frames[0]), int(frames[-1])],
            fps=options.fps, alpha=options.alpha, material=result.material_description,
            material_source=options.material.to_dict(), effects=effects_to_json(options.effects),
            device=options.device, notes=notes, armature_error=rep.armature_error,
            simulate_seconds=result.seconds, write_seconds=rep.write_seconds, **(report or {}))
        done = True
        return rep
    finally:
        if not done:
            remove_recorded(obj, record.to_dict())
