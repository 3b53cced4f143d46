"""Reading an object for a bake: :func:`read_object` gives its base mesh as a :class:`~unipixie.core.bake.BakeObject`
(refusing non-mesh, empty, linked or edit-mode objects before anything changes); :func:`world_vertices` and
:func:`evaluated_positions` read evaluated meshes (modifiers applied) in world metres; :func:`unit_scale` is the
scene's metres per Blender unit.

Uses bpy and :mod:`unipixie.core.bake` (the object as arrays).
"""

from __future__ import annotations

import bpy
import numpy as np

from ...bake import BakeObject
from ...errors import UserError


def unit_scale(scene) -> float:
    """Metres per Blender unit (Scene Properties > Units > Unit Scale; 1 when the unit system is None)."""
    us = scene.unit_settings
    return float(us.scale_length) if us.system != "NONE" and us.scale_length > 0 else 1.0


def _check_bakeable(obj) -> None:
    if obj is None:
        raise UserError("no object selected: select the mesh object to bake")
    if obj.type != "MESH":
        raise UserError(f"'{obj.name}' is a {obj.type.lower().replace('_', ' ')} object; UniPixie bakes mesh objects "
                        "(convert it with Object > Convert > Mesh)")
    if obj.library is not None or obj.data.library is not None or obj.override_library is not None:
        raise UserError(f"'{obj.name}' is linked from another file and cannot be changed; make it local first")
    if obj.mode == "EDIT" or obj.data.is_editmode:
        raise UserError(f"'{obj.name}' is in Edit Mode; switch to Object Mode before baking")


def read_object(obj, scene=None) -> BakeObject:
    """The object's base mesh (before modifiers) as arrays: local rest positions, triangles, transform."""
    _check_bakeable(obj)
    scene = scene or bpy.context.scene
    bpy.context.view_layer.update()  # transforms set from Python are applied to matrix_world here
    me = obj.data
    n = len(me.vertices)
    if n == 0:
        raise UserError(f"object '{obj.name}': the mesh is empty (no vertices)")
    co = np.empty(n * 3, dtype=np.float32)
    me.vertices.foreach_get("co", co)
    me.calc_loop_triangles()
    tris = np.empty(len(me.loop_triangles) * 3, dtype=np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    if tris.size == 0:
        raise UserError(f"object '{obj.name}': the mesh has no faces (only loose vertices or edges); "
                        "a solid needs a closed surface")
    return BakeObject(name=obj.name, rest_local=co.reshape(n, 3), triangles=tris.reshape(-1, 3),
                      matrix_world=np.array(obj.matrix_world, dtype=np.float64), unit_scale=unit_scale(scene))


def world_vertices(obj, scene=None, depsgraph=None) -> np.ndarray:
    """(N, 3) float64 world positions in metres of an object's evaluated mesh (modifiers applied)."""
    scene = scene or bpy.context.scene
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        n = len(me.vertices)
        co = np.empty(n * 3, dtype=np.float32)
        me.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    m = np.array(ev.matrix_world, dtype=np.float64)
    return (co.reshape(n, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]) * unit_scale(scene)


def evaluated_positions(obj, frame: int, scene=None) -> np.ndarray:
    """(N, 3) float64 world positions (metres) of the object's evaluated vertices at ``frame``.

    This is what a render or a viewport sees: shape keys, Mesh Cache and Armature modifiers applied.
    The scene's current frame is restored afterwards.
    """
    scene = scene or bpy.context.scene
    old = scene.frame_current
    try:
        scene.frame_set(int(frame))
        return world_vertices(obj, scene)
    finally:
        scene.frame_set(old)
