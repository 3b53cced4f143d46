"""A bake's scenario from the scene: gravity from the scene's gravity settings, the ground plane from a picked
object (:func:`ground_height`), a clamp box from a picked object's bounds or a vertex group's bounds
(:func:`clamp_box`), the initial velocity from the object's properties — :func:`scenario_from_scene`.

Uses bpy, :mod:`.reading`, :mod:`.options` (the object's settings) and :mod:`unipixie.solvers.scenario`.
"""

from __future__ import annotations

from typing import Optional

import bpy
import numpy as np

from ...errors import UserError
from .options import object_settings
from .reading import read_object, unit_scale, world_vertices


def _mesh_object(scene, obj, role: str):
    if obj is None:
        return None
    if obj.type not in {"MESH", "CURVE", "SURFACE", "META", "FONT"}:
        raise UserError(f"the {role} object '{obj.name}' has no geometry (it is a {obj.type.lower()}); pick a mesh")
    return obj


def ground_height(ground_obj, scene=None) -> float:
    """Height (metres) of the horizontal plane z = h given by a ground object: the top of its geometry.

    The solvers' ground is the infinite horizontal plane; a tilted ground object is refused.
    """
    pts = world_vertices(ground_obj, scene)
    if len(pts) == 0:
        raise UserError(f"the ground object '{ground_obj.name}' has no vertices")
    top = float(pts[:, 2].max())
    extent = float(np.max(pts.max(0) - pts.min(0))) or 1.0
    on_top = pts[pts[:, 2] >= top - 1e-5 * extent]
    span = on_top[:, :2].max(0) - on_top[:, :2].min(0)
    if np.any(span <= 1e-6 * extent):
        raise UserError(f"the ground object '{ground_obj.name}' has no horizontal top face (it is tilted or a single "
                        "edge); UniPixie's ground is the horizontal plane z = height — rotate it flat")
    return top


def clamp_box(obj, scene=None, clamp_object=None, clamp_group: str = "") -> Optional[np.ndarray]:
    """The clamp (``scenario.pinned_box``, (2, 3) metres) from a clamp object's world bounds or the world
    bounds of the vertices of a vertex group of ``obj`` (weight ≥ 0.5).  ``None`` when neither is set."""
    if clamp_object is not None and clamp_group:
        raise UserError("set either a clamp object or a clamp vertex group, not both")
    if clamp_object is not None:
        if clamp_object == obj:
            raise UserError("the clamp object cannot be the baked object itself")
        pts = world_vertices(clamp_object, scene)
        if len(pts) == 0:
            raise UserError(f"the clamp object '{clamp_object.name}' has no vertices")
        box = np.stack([pts.min(0), pts.max(0)])
    elif clamp_group:
        vg = obj.vertex_groups.get(clamp_group)
        if vg is None:
            raise UserError(f"object '{obj.name}' has no vertex group '{clamp_group}' (for the clamp)")
        bo = read_object(obj, scene)
        member = np.zeros(bo.vertex_count, dtype=bool)
        idx = vg.index
        for v in obj.data.vertices:  # vertex-group membership has no bulk accessor in Blender's API
            for g in v.groups:
                if g.group == idx and g.weight >= 0.5:
                    member[v.index] = True
        if not member.any():
            raise UserError(f"the clamp vertex group '{clamp_group}' has no vertices with weight ≥ 0.5")
        pts = bo.rest_world[member]
        box = np.stack([pts.min(0), pts.max(0)])
    else:
        return None
    pad = 1e-6 * max(float(np.max(box[1] - box[0])), 1e-3)
    return box + np.array([[-pad], [pad]])


def scenario_from_scene(obj, scene=None, *, ground_object=None, use_ground: Optional[bool] = None,
                        clamp_object=None, clamp_group: str = "", initial_velocity=None,
                        initial_angular_velocity=None):
    """The :class:`~unipixie.solvers.scenario.Scenario` of a bake from the scene and the object's settings.

    gravity: ``scene.gravity`` (× unit scale, m/s²) when the scene uses gravity, else zero.
    ground: the top of ``ground_object`` (default: the object's ``bake_ground`` setting); none when
    no ground object is set.  Clamp: see :func:`clamp_box`.  Initial velocity (m/s) and angular
    velocity (rad/s): the object's settings unless given.
    Explicit keyword arguments override the object's settings.
    """
    from ....solvers.scenario import Scenario

    scene = scene or bpy.context.scene
    s = object_settings(obj)
    us = unit_scale(scene)
    gravity = np.array(scene.gravity, dtype=np.float64) * us if scene.use_gravity else np.zeros(3)
    if ground_object is None and s is not None and use_ground is not False:
        ground_object = s.bake_ground
    if clamp_object is None and not clamp_group and s is not None:
        clamp_object = s.bake_clamp_object
        clamp_group = s.bake_clamp_group
    if initial_velocity is None:
        initial_velocity = tuple(s.bake_initial_velocity) if s is not None else (0.0, 0.0, 0.0)
    if initial_angular_velocity is None:
        initial_angular_velocity = tuple(s.bake_initial_angular_velocity) if s is not None else (0.0, 0.0, 0.0)
    height = None
    if use_ground is not False and ground_object is not None:
        if ground_object == obj:
            raise UserError("the ground object cannot be the baked object itself")
        height = ground_height(_mesh_object(scene, ground_object, "ground"), scene)
    box = clamp_box(obj, scene, _mesh_object(scene, clamp_object, "clamp"), clamp_group)
    return Scenario(gravity=gravity, ground_height=height, initial_velocity=initial_velocity,
                    initial_angular_velocity=initial_angular_velocity, pinned_box=box,
                    notes=f"baked from Blender scene '{scene.name}'")
