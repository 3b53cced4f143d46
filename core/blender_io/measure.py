"""Measurements in Blender: read an object's motion, show a measurement, colour the error.

* :func:`measurement_from_object` — an object's keyframed / cached / simulated motion (whatever
  the evaluated mesh does: keyframes, shape keys, Mesh Cache, armatures, physics caches) as a
  :class:`~unipixie.core.measurement.Measurement` of its vertices (world space, metres).
* :func:`create_measurement_object` — a measurement as an animated point cloud beside the bake:
  a vertex-only mesh animated with absolute shape keys (one per instant, one ``eval_time``
  curve, linear between instants) and drawn as small spheres by a Geometry Nodes modifier (an ico
  sphere on each vertex, realised, so the error colours show in Solid shading and in renders).
  A point is drawn only at the instants where it was observed (the point attribute
  ``unipixie_observed_now``, keyed 1 / 0, constant between instants); its position there holds
  the nearest observed one.  The fraction of instants at which each point was observed is
  stored in the point attribute ``unipixie_observed``.
* :func:`write_error_attribute` — per-point error as a colour attribute (``unipixie_error``,
  viridis, 0 → dark blue … ``vmax`` → yellow; never-observed points grey) plus the raw value
  in metres (``unipixie_error_m``, float; NaN for never observed); :func:`remove_error_attribute`.
  The error at each frame, keyed for the time slider, is :mod:`.error_animation`'s.
"""

from __future__ import annotations

from typing import Optional

import bpy
import numpy as np

from ..errors import UserError
from .bake import scenario_from_scene, scene_fps, unit_scale, world_vertices
from .bake.writing import PREFIX, assign_action, layered_action, set_keys

ERROR_COLOR_ATTRIBUTE = "unipixie_error"
ERROR_VALUE_ATTRIBUTE = "unipixie_error_m"
OBSERVED_ATTRIBUTE = "unipixie_observed"
OBSERVED_NOW_ATTRIBUTE = "unipixie_observed_now"
"""Point attribute keyed at each instant: 1 where the point was observed then, 0 where not (the point is not drawn)."""
POINTS_NODE_GROUP = "UniPixie measured points"
POINTS_NODE_GROUP_VERSION = 2
"""Version of that group's nodes (a file holding an older group gets a new one beside it)."""
POINTS_NODE_GROUP_VERSION_PROPERTY = "unipixie_version"
MEASUREMENT_PATH_PROPERTY = "unipixie_measurement"
"""Custom property on a measurement object: the file it shows."""


# --------------------------------------------------------------------------- reading motion
def closed_triangles(me) -> Optional[np.ndarray]:
    """(F, 3) int64 triangles of a mesh datablock when they form a closed, consistently oriented
    surface, else ``None``."""
    me.calc_loop_triangles()
    nt = len(me.loop_triangles)
    if nt == 0:
        return None
    tris = np.empty(nt * 3, dtype=np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    tris = tris.reshape(nt, 3).astype(np.int64)
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    if np.any(counts != 2) or np.any(dcounts != 1):
        return None
    return tris


def measurement_from_object(obj, frame_start: Optional[int] = None, frame_end: Optional[int] = None, scene=None,
                            scenario=None, material=None, progress=None):
    """The object's vertex motion over ``frame_start..frame_end`` (scene range by default) as a Measurement.

    times: (frame − frame_start) / fps seconds.  rest_positions: the undeformed mesh (no shape keys
    or modifiers) placed by the object's transform at the first frame.  faces: the mesh's
    triangles when they form a closed surface (else the solid is the convex hull, with a warning).
    scenario: a :class:`~unipixie.solvers.scenario.Scenario` (default: from the scene and the object's
    bake settings — gravity, ground object, clamp, initial velocities).  material: a
    :class:`~unipixie.core.measurement.MeasuredMaterial` (default: the object's homogeneous bake
    material, E / ν / density).  The scene's current frame is restored afterwards.
    """
    from ..measurement import MeasuredMaterial, Measurement

    if obj is None or obj.type != "MESH":
        raise UserError("select a mesh object whose motion is the measurement")
    scene = scene or bpy.context.scene
    f0 = scene.frame_start if frame_start is None else int(frame_start)
    f1 = scene.frame_end if frame_end is None else int(frame_end)
    if f1 - f0 < 3:
        raise UserError(f"frames {f0}..{f1}: a measurement needs at least 4 frames")
    scale = unit_scale(scene)
    n_rest = len(obj.data.vertices)
    if n_rest == 0:
        raise UserError(f"object '{obj.name}' has no vertices")
    old = scene.frame_current
    frames = np.arange(f0, f1 + 1)
    pos = np.empty((len(frames), n_rest, 3))
    try:
        for i, f in enumerate(frames):
            scene.frame_set(int(f))
            p = world_vertices(obj, scene, bpy.context.evaluated_depsgraph_get())
            if len(p) != n_rest:
                raise UserError(f"object '{obj.name}': its evaluated mesh has {len(p)} vertices at frame {f} but the "
                                f"mesh has {n_rest}; a modifier changes the topology (apply or disable it)")
            pos[i] = p
            if progress is not None:
                progress.step(1.0 / len(frames), f"reading frame {f}")
        scene.frame_set(int(f0))
        co = np.empty(n_rest * 3, dtype=np.float32)
        obj.data.vertices.foreach_get("co", co)
        m = np.array(obj.matrix_world, dtype=np.float64)
        rest = (co.reshape(n_rest, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]) * scale
    finally:
        scene.frame_set(old)
    faces = closed_triangles(obj.data)
    warnings = [] if faces is not None else [f"object '{obj.name}' is not a closed surface: the solid is taken as "
                                             "the convex hull of its vertices"]
    if scenario is None:
        scenario = scenario_from_scene(obj, scene)
    if material is None:
        s = getattr(obj, "unipixie", None)
        if s is not None and hasattr(s, "bake_E"):
            material = MeasuredMaterial(float(s.bake_E), float(s.bake_nu), float(s.bake_density),
                                        str(getattr(s, "bake_material_class", "jelly") or "jelly"))
    times = (frames - f0) / scene_fps(scene)
    meas = Measurement(positions=pos, times=times, scenario=scenario, rest_positions=rest, faces=faces,
                       material=material, source=f"Blender object '{obj.name}' frames {f0}-{f1}")
    meas.warnings.extend(warnings)
    return meas


# --------------------------------------------------------------------------- showing a measurement
def _points_node_group():
    """The Geometry Nodes group that draws each vertex as a small sphere (an ico sphere instanced on the vertex and
    realised, so that the vertices' attributes, the error colours among them, colour its faces in Solid shading and
    in every render engine).  Input "Radius" (m)."""
    ng = bpy.data.node_groups.get(POINTS_NODE_GROUP)
    if ng is not None and ng.bl_idname == "GeometryNodeTree" and ng.get(POINTS_NODE_GROUP_VERSION_PROPERTY) == \
            POINTS_NODE_GROUP_VERSION:
        return ng
    ng = bpy.data.node_groups.new(POINTS_NODE_GROUP, "GeometryNodeTree")
    ng[POINTS_NODE_GROUP_VERSION_PROPERTY] = POINTS_NODE_GROUP_VERSION
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Radius", in_out="INPUT", socket_type="NodeSocketFloat")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gi = ng.nodes.new("NodeGroupInput")
    go = ng.nodes.new("NodeGroupOutput")
    m2p = ng.nodes.new("GeometryNodeMeshToPoints")
    sphere = ng.nodes.new("GeometryNodeMeshIcoSphere")
    sphere.inputs["Subdivisions"].default_value = 1
    inst = ng.nodes.new("GeometryNodeInstanceOnPoints")
    # drawn only where observed at this instant (the keyed OBSERVED_NOW_ATTRIBUTE; every point where it is missing)
    seen = ng.nodes.new("GeometryNodeInputNamedAttribute")
    seen.data_type = "FLOAT"
    seen.inputs["Name"].default_value = OBSERVED_NOW_ATTRIBUTE
    over = ng.nodes.new("FunctionNodeCompare")
    over.data_type, over.operation = "FLOAT", "GREATER_THAN"
    over.inputs["B"].default_value = 0.5
    missing = ng.nodes.new("FunctionNodeBooleanMath")
    missing.operation = "NOT"
    either = ng.nodes.new("FunctionNodeBooleanMath")
    either.operation = "OR"
    ng.links.new(seen.outputs["Attribute"], over.inputs["A"])
    ng.links.new(seen.outputs["Exists"], missing.inputs[0])
    ng.links.new(over.outputs["Result"], either.inputs[0])
    ng.links.new(missing.outputs["Boolean"], either.inputs[1])
    ng.links.new(either.outputs["Boolean"], inst.inputs["Selection"])
    for y, node in enumerate((seen, over, missing, either)):
        node.location = (-350 + 100 * y, -400 - 60 * y)
    real = ng.nodes.new("GeometryNodeRealizeInstances")
    join = ng.nodes.new("GeometryNodeJoinGeometry")
    ng.links.new(gi.outputs["Geometry"], m2p.inputs["Mesh"])
    ng.links.new(gi.outputs["Radius"], sphere.inputs["Radius"])
    ng.links.new(m2p.outputs["Points"], inst.inputs["Points"])
    ng.links.new(sphere.outputs["Mesh"], inst.inputs["Instance"])
    ng.links.new(inst.outputs["Instances"], real.inputs["Geometry"])
    # the vertices themselves first: the joined mesh keeps their mesh's active colour attribute, which a realised
    # mesh alone does not have (Solid shading colours by the active one)
    ng.links.new(real.outputs["Geometry"], join.inputs["Geometry"])
    ng.links.new(gi.outputs["Geometry"], join.inputs["Geometry"])
    ng.links.new(join.outputs["Geometry"], go.inputs["Geometry"])
    for x, node in enumerate((gi, m2p, sphere, inst, real, join, go)):
        node.location = (-600 + 250 * x, 0 if node is not sphere else -200)
    return ng


def _filled(positions: np.ndarray) -> np.ndarray:
    """Occluded samples replaced by the nearest observed sample in time (held before/after)."""
    pos = np.array(positions, dtype=np.float64)
    T, N, _ = pos.shape
    obs = np.isfinite(pos[..., 0])
    idx = np.where(obs, np.arange(T)[:, None], -1)
    last = np.maximum.accumulate(idx, axis=0)
    nxt = np.where(obs, np.arange(T)[:, None], T)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    use = np.where(last >= 0, last, nxt)
    never = ~obs.any(axis=0)
    use = np.clip(use, 0, T - 1)
    out = pos[use, np.arange(N)[None, :]]
    out[:, never] = 0.0
    return out


def _set_linear(id_data, path: str) -> None:
    ad = id_data.animation_data
    if ad is None or ad.action is None:
        return
    fcurves = []
    try:
        from bpy_extras import anim_utils

        bag = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
        if bag is not None:
            fcurves = list(bag.fcurves)
    except Exception:  # older layouts
        fcurves = list(getattr(ad.action, "fcurves", []))
    for fc in fcurves:
        if fc.data_path == path:
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"


def create_measurement_object(measurement, name: str = "Measurement", scene=None, frame_start: Optional[int] = None,
                              offset=(0.0, 0.0, 0.0), radius: Optional[float] = None, source_path: str = ""):
    """An animated point cloud of ``measurement`` (see the module docstring); returns the new object.

    frame_start: scene frame of ``times[0]`` (default: the scene's start); instants map to frames by
    the scene's fps.  offset: metres added to every position (to place it beside a bake).
    radius: point radius in metres (default 1 % of the measurement's extent).
    """
    scene = scene or bpy.context.scene
    pos = _filled(measurement.positions) + np.asarray(offset, dtype=np.float64)
    T, N, _ = pos.shape
    scale = unit_scale(scene)
    local = (pos / scale).astype(np.float32)
    rest = (np.asarray(measurement.rest, dtype=np.float64) + np.asarray(offset)) / scale
    me = bpy.data.meshes.new(name)
    me.vertices.add(N)
    me.vertices.foreach_set("co", rest.astype(np.float32).ravel())
    me.update()
    obs_attr = me.attributes.new(OBSERVED_ATTRIBUTE, "FLOAT", "POINT")
    obs_attr.data.foreach_set("value", measurement.observed.mean(axis=0).astype(np.float32))
    observed = measurement.observed  # (T, N) bool
    now = me.attributes.new(OBSERVED_NOW_ATTRIBUTE, "FLOAT", "POINT")
    now.data.foreach_set("value", observed[0].astype(np.float32))
    obj = bpy.data.objects.new(name, me)
    scene.collection.objects.link(obj)
    obj[MEASUREMENT_PATH_PROPERTY] = str(source_path or measurement.source)
    basis = obj.shape_key_add(name="Basis", from_mix=False)
    key = me.shape_keys
    key.use_relative = False
    blocks = []
    for t in range(T):
        kb = obj.shape_key_add(name=f"t={measurement.times[t]:.4f}s", from_mix=False)
        kb.data.foreach_set("co", local[t].ravel())
        blocks.append(kb)
    del basis
    fps = scene_fps(scene)
    f0 = scene.frame_start if frame_start is None else int(frame_start)
    frames = f0 + (measurement.times - measurement.times[0]) * fps
    for t, kb in enumerate(blocks):
        key.eval_time = float(kb.frame)
        key.keyframe_insert("eval_time", frame=float(frames[t]))
    _set_linear(key, "eval_time")
    partly = np.flatnonzero(~observed.all(axis=0))
    if len(partly):  # a curve for each point that is not observed at some instant (constant between instants)
        action, slot, bag = layered_action(f"{PREFIX} observed {me.name}", "MESH", me.name)
        assign_action(me, action, slot)
        for i in partly:
            set_keys(bag.fcurves.new(f'attributes["{OBSERVED_NOW_ATTRIBUTE}"].data[{i}].value'),
                     frames.astype(np.float32), observed[:, i].astype(np.float32), "CONSTANT")
    ext = float(np.max(np.ptp(np.asarray(measurement.rest), axis=0))) / scale
    ng = _points_node_group()
    mod = obj.modifiers.new("UniPixie points", "NODES")
    mod.node_group = ng
    sock = next(s for s in ng.interface.items_tree if getattr(s, "in_out", "") == "INPUT" and s.name == "Radius")
    mod[sock.identifier] = float(radius / scale if radius else 0.01 * max(ext, 1e-6))
    return obj


# --------------------------------------------------------------------------- error colours
def error_colours(values: np.ndarray, vmax: Optional[float] = None) -> np.ndarray:
    """(N,) errors in metres -> (N, 4) float32 linear RGBA (viridis; NaN → grey)."""
    from matplotlib import colormaps

    v = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(v)
    top = float(vmax) if vmax else (float(np.max(v[finite])) if finite.any() else 1.0)
    top = top if top > 0 else 1.0
    rgba = colormaps["viridis"](np.clip(np.where(finite, v, 0.0) / top, 0.0, 1.0)).astype(np.float32)
    rgba[:, :3] = np.where(rgba[:, :3] <= 0.04045, rgba[:, :3] / 12.92, ((rgba[:, :3] + 0.055) / 1.055) ** 2.4)
    rgba[~finite] = (0.5, 0.5, 0.5, 1.0)
    return rgba


def write_error_attribute(obj, per_point_error: np.ndarray, vmax: Optional[float] = None,
                          name: str = ERROR_COLOR_ATTRIBUTE) -> str:
    """Write per-point errors (N,) metres onto ``obj``'s vertices: a colour attribute and a float attribute.

    Replaces earlier attributes of the same names (nothing else on the mesh is touched); makes the
    colour attribute the active one so Solid shading with "Attribute" colour shows it.
    Returns the colour attribute's name.
    """
    if obj is None or obj.type != "MESH":
        raise UserError("the error can only be written onto a mesh object")
    me = obj.data
    err = np.asarray(per_point_error, dtype=np.float64).reshape(-1)
    if len(me.vertices) != len(err):
        raise UserError(f"object '{obj.name}' has {len(me.vertices)} vertices but the error has {len(err)} points; "
                        "pick the object the measurement was made from (or its point cloud)")
    remove_attributes(me, (name, ERROR_VALUE_ATTRIBUTE))
    col = me.color_attributes.new(name, "FLOAT_COLOR", "POINT")
    col.data.foreach_set("color", error_colours(err, vmax).ravel())
    val = me.attributes.new(ERROR_VALUE_ATTRIBUTE, "FLOAT", "POINT")
    val.data.foreach_set("value", np.where(np.isfinite(err), err, np.nan).astype(np.float32))
    me.color_attributes.active_color = me.color_attributes[name]
    try:
        me.color_attributes.render_color_index = me.color_attributes.active_color_index
    except AttributeError:
        pass
    me.update()
    return name


def remove_error_attribute(obj) -> bool:
    """Remove what :func:`write_error_attribute` wrote on ``obj``'s mesh (both attributes); True if there was any."""
    if obj is None or obj.type != "MESH":
        raise UserError("the error can only be removed from a mesh object")
    me = obj.data
    found = remove_attributes(me, (ERROR_COLOR_ATTRIBUTE, ERROR_VALUE_ATTRIBUTE))
    me.update()
    return found


def remove_attributes(me, names) -> bool:
    """Remove the attributes ``names`` from the mesh datablock ``me`` where it has them; True if it had any."""
    found = False
    for attr_name in names:
        old = me.attributes.get(attr_name)
        if old is not None:
            me.attributes.remove(old)
            found = True
    return found
