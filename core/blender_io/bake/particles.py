"""Writing the MPM particles: a vertex-only mesh object of the particles with their material as point attributes,
moving as the main motion is stored (shape keys or a Mesh Cache) — :func:`write_particles`.

Uses bpy, :mod:`unipixie.core.bake` (the output rule), :mod:`.writing`, :mod:`.shape_keys` and :mod:`.mesh_cache`.
"""

from __future__ import annotations

from typing import Iterator

import bpy
import numpy as np

from ...bake import BakeObject, BakeOptions, vertex_output
from .mesh_cache import cache_folder, write_mesh_cache
from .shape_keys import write_shape_keys
from .writing import PREFIX, WriteRecord, collection_of, unique_name


def write_particles(obj, bo: BakeObject, traj, frames: np.ndarray, options: BakeOptions, record: WriteRecord,
                    notes: list) -> Iterator[float]:
    """A vertex-only mesh object of the MPM particles, moving with them, with point attributes
    ``E`` (Pa), ``nu``, ``density`` (kg/m³), ``material_class`` (registry id) and ``velocity`` (m/s, at the
    first frame) for viewing the material field.  Positions are stored as the main motion is
    (shape keys, or a Mesh Cache for large particle counts)."""
    if traj.particle_positions is None:
        notes.append("the solver returned no particle states; no particle object was made")
        yield 1.0
        return
    P = traj.particle_positions.shape[1]
    us = bo.unit_scale
    world_bu = np.asarray(traj.particle_positions, dtype=np.float64) / us  # world, Blender units
    name = unique_name(bpy.data.objects.keys(), f"{PREFIX} {obj.name} particles")
    me = bpy.data.meshes.new(name)
    record.meshes.append(me.name)
    me.vertices.add(P)
    me.vertices.foreach_set("co", world_bu[0].astype(np.float32).ravel())
    attrs = traj.particle_attributes or {}
    for key, aname, atype in (("E", "E", "FLOAT"), ("nu", "nu", "FLOAT"), ("density", "density", "FLOAT"),
                              ("material", "material_class", "INT")):
        if key in attrs and np.asarray(attrs[key]).shape[:1] == (P,):
            vals = np.asarray(attrs[key]).reshape(P, -1)[:, 0]
            a = me.attributes.new(aname, atype, "POINT")
            a.data.foreach_set("value", vals.astype(np.int32 if atype == "INT" else np.float32))
    vel = attrs.get("velocity")
    if vel is not None:
        vel = np.asarray(vel, dtype=np.float32)
        v0 = vel[0] if vel.ndim == 3 else vel
        if v0.shape == (P, 3):
            a = me.attributes.new("velocity", "FLOAT_VECTOR", "POINT")
            a.data.foreach_set("vector", (v0 / us).astype(np.float32).ravel())
    me.update()
    pobj = bpy.data.objects.new(name, me)
    record.objects.append(pobj.name)
    collection_of(obj).objects.link(pobj)
    pobj.display_type = "WIRE"
    yield 0.2
    local = world_bu.astype(np.float32)
    mode = (options.output if options.output in ("shape_keys", "mesh_cache")
            else vertex_output(P, len(frames), False, False, []))
    if mode == "shape_keys":
        for f in write_shape_keys(pobj, local, frames, options.interpolation, record):
            yield 0.2 + 0.8 * f
    else:
        folder, more = cache_folder(obj.name, options, record)
        notes.extend(more)
        for f in write_mesh_cache(pobj, local, frames, options.interpolation, folder, record, suffix="_particles"):
            yield 0.2 + 0.8 * f
