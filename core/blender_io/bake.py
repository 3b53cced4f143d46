"""Baking into Blender data: reading the object and scene, writing the motion, clearing a bake.

Everything Blender-free (the body, the material, the solver run, PC2 files, jobs) is in
:mod:`unipixie.core.bake`; this module turns Blender data into its inputs and its outputs into
Blender data:

* :func:`read_object` — the mesh as a :class:`~unipixie.core.bake.BakeObject` (refuses non-mesh,
  empty, linked or edit-mode objects before anything changes).
* :func:`scenario_from_scene` — gravity from the scene's gravity settings, the ground plane from a
  picked object, a clamp box from a picked object's bounds or a vertex group's bounds, the initial
  velocity from the object's properties.
* Writers — shape keys (one per frame, keyed 0/1/0), a Mesh Cache modifier on a PC2 file, an
  armature (LBS handles → bones) and a particle object (MPM) — all with bulk ``foreach_set`` calls
  and Blender 5.0 layered actions (``action.layers[0].strips[0].channelbag(slot).fcurves``).
* :func:`clear_bake` — removes exactly what a bake added (its record is a JSON ID property
  ``unipixie_bake`` on the object).
* :func:`bake_steps` — the whole bake as a generator of ``(fraction, status)`` for the modal
  operator (the simulation runs in a worker thread; closing the generator cancels it and removes
  anything half-written); :func:`bake_object` runs it to the end (Python API);
  :func:`unipixie.core.blender_io.bake_jobs.run_jobs` opens scenes, bakes and saves (command line and farms).
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional, Sequence

import bpy
import numpy as np

from .. import bake as core_bake
from .. import property_registration
from ..bake import (BAKE_RECORD_KEY, BakeJob, BakeObject, BakeOptions, FieldFileSource, HomogeneousSource, ModelSource,
                    SimulationResult)
from ..errors import UserError
from .context_safety import active_and_selected
from ..progress import Progress, silent

PREFIX = "UniPixie"
"""Names of everything a bake adds start with this (shape keys, modifiers, objects, actions)."""
_INTERP_CODE = {"CONSTANT": 0, "LINEAR": 1}


# =========================================================================== reading
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


def object_settings(obj):
    """The object's UniPixie settings (``obj.unipixie``), or ``None`` when the add-on's properties are absent."""
    return getattr(obj, "unipixie", None)


@contextlib.contextmanager
def registered_properties():
    """Make ``Object.unipixie`` available (registering the add-on's properties for the duration if needed).

    The command line runs bpy without the add-on; its properties are still stored in the .blend and
    become readable once the property group is registered.  The property group is the add-on's, above core:
    the package root hands core the way to register it (:mod:`unipixie.core.property_registration`).
    """
    if hasattr(bpy.types.Object, "unipixie"):
        yield
        return
    unregister = property_registration.registrar()()
    try:
        yield
    finally:
        unregister()


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
    from ...solvers.scenario import Scenario

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


def material_source_from_settings(obj):
    """The material source chosen in the object's panel settings (homogeneous defaults without the add-on)."""
    s = object_settings(obj)
    if s is None:
        return HomogeneousSource()
    kind = s.bake_material_source
    if kind == "field":
        return FieldFileSource(bpy.path.abspath(s.bake_material_file) if s.bake_material_file else "")
    if kind == "model":
        return ModelSource()
    return HomogeneousSource(E=s.bake_E, nu=s.bake_nu, density=s.bake_density, material=s.bake_material_class)


def scene_fps(scene) -> float:
    return float(scene.render.fps) / float(scene.render.fps_base or 1.0)


def options_from_settings(obj, scene=None, **overrides) -> BakeOptions:
    """:class:`BakeOptions` from the object's panel settings and the scene (frame range, fps, cache folder)."""
    scene = scene or bpy.context.scene
    s = object_settings(obj)
    kw = dict(frames=(scene.frame_start, scene.frame_end), fps=scene_fps(scene),
              material=material_source_from_settings(obj))
    if s is not None:
        kw.update(solver=s.solver, alpha=float(s.alpha), device=s.device, output=s.bake_output,
                  interpolation=s.bake_interpolation, particles=bool(s.bake_particles) and s.solver == "mpm",
                  effects=[e for e in (x.strip() for x in s.bake_effects.split(";")) if e])
        if s.use_bake_frame_range:
            kw["frames"] = (s.bake_frame_start, s.bake_frame_end)
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return BakeOptions(**kw)


# =========================================================================== writing helpers
def _layered_action(name: str, id_type: str, slot_name: str):
    """A new Blender 5.0 layered action with one slot, one layer and one keyframe strip; returns (action, slot, channelbag)."""
    action = bpy.data.actions.new(name)
    slot = action.slots.new(id_type=id_type, name=slot_name)
    strip = action.layers.new("UniPixie").strips.new(type="KEYFRAME")
    return action, slot, strip.channelbag(slot, ensure=True)


def _set_keys(fcurve, frames: np.ndarray, values: np.ndarray, interpolation: str) -> None:
    """Keyframes in bulk: ``keyframe_points.add`` + ``foreach_set`` (no per-keyframe Python)."""
    n = len(frames)
    kp = fcurve.keyframe_points
    kp.add(n)
    co = np.empty(2 * n, dtype=np.float32)
    co[0::2] = frames
    co[1::2] = values
    kp.foreach_set("co", co)
    kp.foreach_set("interpolation", np.full(n, _INTERP_CODE[interpolation], dtype=np.int32))
    fcurve.update()


def _assign_action(id_block, action, slot) -> None:
    ad = id_block.animation_data or id_block.animation_data_create()
    ad.action = action
    ad.action_slot = slot


def _unique(existing, base: str) -> str:
    if base not in existing:
        return base
    k = 1
    while f"{base}.{k:03d}" in existing:
        k += 1
    return f"{base}.{k:03d}"


def _move_first(obj, mod) -> None:
    idx = list(obj.modifiers).index(mod)
    if idx:
        obj.modifiers.move(idx, 0)


def _collection_of(obj):
    cols = list(obj.users_collection)
    return cols[0] if cols else bpy.context.scene.collection


@dataclass
class WriteRecord:
    """What a bake created (kept as it is written so a failure or Esc can remove it)."""

    obj_name: str
    shape_keys: list = field(default_factory=list)
    created_key: bool = False
    modifiers: list = field(default_factory=list)
    vertex_groups: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    objects: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    armatures: list = field(default_factory=list)
    node_groups: list = field(default_factory=list)
    files: list = field(default_factory=list)
    folders: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def cache_folder(obj_name: str, options: BakeOptions, record: WriteRecord) -> tuple[Path, list[str]]:
    """Folder for PC2 files: ``options.cache_dir``, else ``<blend>_unipixie/`` next to the saved .blend,
    else the UniPixie cache (with a warning to save and re-bake)."""
    notes = []
    if options.cache_dir:
        folder = Path(options.cache_dir)
    elif bpy.data.filepath:
        blend = Path(bpy.data.filepath)
        folder = blend.parent / f"{blend.stem}_unipixie"
    else:
        from ..paths import cache_dir

        folder = cache_dir("bakes")
        notes.append(f"the .blend is not saved: the PC2 cache for '{obj_name}' is in {folder}; save the .blend and "
                     "re-bake to keep the cache next to it")
    if not folder.exists():
        folder.mkdir(parents=True)
        record.folders.append(str(folder))
    return folder, notes


def _pc2_path(folder: Path, name: str, suffix: str = "") -> Path:
    stem = core_bake.safe_name(name) + suffix
    path = folder / f"{stem}.pc2"
    k = 1
    while path.exists():
        path = folder / f"{stem}.{k:03d}.pc2"
        k += 1
    return path


# --------------------------------------------------------------------------- shape keys
def write_shape_keys(obj, local: np.ndarray, frames: np.ndarray, interpolation: str, record: WriteRecord,
                     chunk: int = 32) -> Iterator[float]:
    """One shape key per frame (keyed 0 → 1 → 0 around its frame), yielding the fraction written.

    local: (T, N, 3) float32 object-local positions; frames: (T,) scene frames.  At every integer
    frame exactly one key has value 1, so the evaluated mesh is that frame's positions; the last key
    stays at 1 after the end (the final state is held) and before the start the first key (= rest).
    """
    T, N, _ = local.shape
    if obj.data.shape_keys is not None:
        raise UserError(f"object '{obj.name}' already has shape keys; use the Mesh Cache output")
    basis = obj.shape_key_add(name=f"{PREFIX} Basis", from_mix=False)
    record.created_key = True
    record.shape_keys.append(basis.name)
    key = obj.data.shape_keys
    key.use_relative = True
    names = []
    for t0 in range(0, T, chunk):
        for t in range(t0, min(T, t0 + chunk)):
            kb = obj.shape_key_add(name=f"{PREFIX} {int(frames[t]):04d}", from_mix=False)
            kb.data.foreach_set("co", local[t].ravel())
            kb.value = 0.0
            kb.slider_min = 0.0
            names.append(kb.name)
            record.shape_keys.append(kb.name)
        yield 0.9 * min(T, t0 + chunk) / T
    action, slot, bag = _layered_action(f"{PREFIX} {obj.name} shape keys", "KEY", key.name)
    record.actions.append(action.name)
    f = frames.astype(np.float64)
    for t, name in enumerate(names):
        fc = bag.fcurves.new(f'key_blocks["{bpy.utils.escape_identifier(name)}"].value')
        lo, hi = max(t - 1, 0), min(t + 1, T - 1)
        kf = f[lo:hi + 1]
        vals = (np.arange(lo, hi + 1) == t).astype(np.float32)  # the last key holds 1 after the end
        _set_keys(fc, kf, vals, interpolation)
    _assign_action(key, action, slot)
    yield 1.0


# --------------------------------------------------------------------------- Mesh Cache (PC2)
def write_mesh_cache(obj, local: np.ndarray, frames: np.ndarray, interpolation: str, folder: Path,
                     record: WriteRecord, suffix: str = "") -> Iterator[float]:
    """A PC2 file (written atomically) and a Mesh Cache modifier first in the stack reading it."""
    path = _pc2_path(folder, obj.name, suffix)
    core_bake.write_pc2(path, local, start_frame=float(frames[0]), sample_rate=1.0)
    record.files.append(str(path))
    yield 0.8
    mod = obj.modifiers.new(name=_unique({m.name for m in obj.modifiers}, f"{PREFIX} Mesh Cache"), type="MESH_CACHE")
    record.modifiers.append(mod.name)
    mod.cache_format = "PC2"
    # relative to the .blend where it is saved (Blender remaps relative paths on "Save As")
    mod.filepath = bpy.path.relpath(str(path)) if bpy.data.filepath else str(path)
    mod.frame_start = float(frames[0])
    mod.frame_scale = 1.0
    mod.play_mode = "SCENE"
    mod.time_mode = "FRAME"
    mod.deform_mode = "OVERWRITE"
    mod.interpolation = "LINEAR" if interpolation == "LINEAR" else "NONE"
    mod.forward_axis = "POS_Y"
    mod.up_axis = "POS_Z"
    _move_first(obj, mod)
    yield 1.0


# --------------------------------------------------------------------------- armature (LBS)
@contextlib.contextmanager
def _edit_mode(arm_obj):
    """Edit mode on ``arm_obj`` (to add its bones) as the view layer's active object; the previous mode,
    active object and selection are restored after.  No context override (see
    :mod:`unipixie.core.blender_io.context_safety`: the bake's simulation thread may still be running)."""
    prev_active = bpy.context.view_layer.objects.active
    prev_mode = prev_active.mode if prev_active is not None else "OBJECT"
    if prev_active is not None and prev_mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    with active_and_selected(arm_obj):
        bpy.ops.object.mode_set(mode="EDIT")
        try:
            yield
        finally:
            bpy.ops.object.mode_set(mode="OBJECT")


def _add_ground_lift(obj, bo: BakeObject, ground_height: float, record: WriteRecord) -> None:
    """A Geometry Nodes modifier right after the bake's Armature that lifts every vertex below the world
    plane z = ``ground_height`` (metres) straight up onto it, as the LBS solver does with its tracked
    points (:func:`unipixie.core.bake.plan_armature`).

    The object's transform at bake time is folded into the node constants: world z = a·p + b of the
    local position p, and a world lift dz is the local offset dz·c with c = S⁻¹ e_z (S the object's
    world-from-local map, Blender units).  The node group is the bake's own and is removed with it.
    """
    S = np.asarray(bo.matrix_world, dtype=np.float64)
    a, b = S[2, :3], float(S[2, 3])
    c = np.linalg.inv(S[:3, :3])[:, 2]
    h = float(ground_height) / bo.unit_scale
    name = _unique(bpy.data.node_groups.keys(), f"{PREFIX} {obj.name} ground")
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    record.node_groups.append(ng.name)
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = ng.nodes, ng.links
    gi, go = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    position = nodes.new("GeometryNodeInputPosition")
    height = nodes.new("ShaderNodeVectorMath")
    height.operation = "DOT_PRODUCT"
    height.inputs[1].default_value = tuple(float(v) for v in a)
    links.new(position.outputs["Position"], height.inputs[0])
    world_z = nodes.new("ShaderNodeMath")
    world_z.operation = "ADD"
    links.new(height.outputs["Value"], world_z.inputs[0])
    world_z.inputs[1].default_value = b
    depth = nodes.new("ShaderNodeMath")
    depth.operation = "SUBTRACT"
    depth.inputs[0].default_value = h
    links.new(world_z.outputs["Value"], depth.inputs[1])
    lift = nodes.new("ShaderNodeMath")
    lift.operation = "MAXIMUM"
    links.new(depth.outputs["Value"], lift.inputs[0])
    lift.inputs[1].default_value = 0.0
    offset = nodes.new("ShaderNodeVectorMath")
    offset.operation = "SCALE"
    offset.inputs[0].default_value = tuple(float(v) for v in c)
    links.new(lift.outputs["Value"], offset.inputs["Scale"])
    move = nodes.new("GeometryNodeSetPosition")
    links.new(gi.outputs["Geometry"], move.inputs["Geometry"])
    links.new(offset.outputs["Vector"], move.inputs["Offset"])
    links.new(move.outputs["Geometry"], go.inputs["Geometry"])
    for i, node in enumerate((gi, position, height, world_z, depth, lift, offset, move, go)):
        node.location = (200 * i, 0)
    mod = obj.modifiers.new(name=_unique({m.name for m in obj.modifiers}, f"{PREFIX} Ground"), type="NODES")
    record.modifiers.append(mod.name)
    mod.node_group = ng
    arm_index = next(i for i, m in enumerate(obj.modifiers) if m.type == "ARMATURE" and m.name in record.modifiers)
    obj.modifiers.move(list(obj.modifiers).index(mod), arm_index + 1)


def write_armature(obj, bo: BakeObject, plan: core_bake.ArmaturePlan, frames: np.ndarray, interpolation: str,
                   record: WriteRecord) -> Iterator[float]:
    """An armature object (child of ``obj``, so it follows the object) with one parent/child bone chain
    per blend bone (:class:`~unipixie.core.bake.ArmaturePlan`), a vertex group per deforming bone
    holding the weights, an Armature modifier first in ``obj``'s stack (linear blending), and the
    bones keyed at every frame.  The channels are recomputed from the bone heads as Blender stored
    them, so the rounding of the rest pose adds no error.
    """
    name = _unique(bpy.data.objects.keys(), f"{PREFIX} {obj.name} rig")
    arm = bpy.data.armatures.new(name)
    record.armatures.append(arm.name)
    arm_obj = bpy.data.objects.new(name, arm)
    record.objects.append(arm_obj.name)
    _collection_of(obj).objects.link(arm_obj)
    arm_obj.parent = obj
    arm_obj.matrix_parent_inverse.identity()
    arm_obj.matrix_basis.identity()
    arm.display_type = "STICK"
    arm_obj.show_in_front = True
    B = plan.bone_count
    taken = {g.name for g in obj.vertex_groups}
    deform_names = []
    for b in range(B):
        n = _unique(taken, f"{PREFIX} handle {plan.labels[b]}")
        taken.add(n)
        deform_names.append(n)
    with _edit_mode(arm_obj):
        for b in range(B):
            head = tuple(float(v) for v in plan.heads[b])
            parent = arm.edit_bones.new(f"{deform_names[b]} (stretch)")
            parent.head, parent.tail, parent.roll = head, (head[0], head[1] + plan.bone_length, head[2]), 0.0
            parent.use_deform = False
            child = arm.edit_bones.new(deform_names[b])
            child.head, child.tail, child.roll = head, (head[0], head[1] + 0.6 * plan.bone_length, head[2]), 0.0
            child.parent = parent
            child.use_connect = False
            child.use_inherit_rotation = True
            child.inherit_scale = "FULL"
            child.use_local_location = True
            child.use_deform = True
            deform_names[b] = child.name
    yield 0.2
    heads = np.array([np.array(arm.bones[n].head_local, dtype=np.float64) for n in deform_names])
    loc, Uq, scale, Vq = core_bake.chain_channels(plan.local_maps, heads)
    for b, bname in enumerate(deform_names):
        vg = obj.vertex_groups.new(name=bname)
        record.vertex_groups.append(vg.name)
        w = plan.weights[:, b]
        nz = np.nonzero(w > 0)[0]
        full = nz[w[nz] >= 1.0]
        if len(full):
            vg.add(full.tolist(), 1.0, "REPLACE")
        add = vg.add
        part = nz[w[nz] < 1.0]
        for i, wi in zip(part.tolist(), w[part].tolist()):
            add((i,), wi, "REPLACE")  # Blender has no bulk setter for vertex-group weights
    yield 0.5
    mod = obj.modifiers.new(name=_unique({m.name for m in obj.modifiers}, f"{PREFIX} Armature"), type="ARMATURE")
    record.modifiers.append(mod.name)
    mod.object = arm_obj
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    mod.use_deform_preserve_volume = False
    mod.use_multi_modifier = False
    _move_first(obj, mod)
    if plan.ground_height is not None:
        _add_ground_lift(obj, bo, plan.ground_height, record)
    action, slot, bag = _layered_action(f"{PREFIX} {obj.name} rig", "OBJECT", arm_obj.name)
    record.actions.append(action.name)
    f = frames.astype(np.float64)
    for b, child in enumerate(deform_names):
        parent = arm.bones[child].parent.name
        for bname, channels in ((parent, (("location", loc[:, b]), ("rotation_quaternion", Uq[:, b]),
                                          ("scale", scale[:, b]))),
                                (child, (("rotation_quaternion", Vq[:, b]),))):
            arm_obj.pose.bones[bname].rotation_mode = "QUATERNION"
            base = f'pose.bones["{bpy.utils.escape_identifier(bname)}"]'
            for prop, values in channels:
                for i in range(values.shape[1]):
                    fc = bag.fcurves.new(f"{base}.{prop}", index=i, group_name=bname)
                    _set_keys(fc, f, values[:, i], interpolation)
    _assign_action(arm_obj, action, slot)
    yield 1.0


# --------------------------------------------------------------------------- particles (MPM)
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
    name = _unique(bpy.data.objects.keys(), f"{PREFIX} {obj.name} particles")
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
    _collection_of(obj).objects.link(pobj)
    pobj.display_type = "WIRE"
    yield 0.2
    local = world_bu.astype(np.float32)
    mode = (options.output if options.output in ("shape_keys", "mesh_cache")
            else core_bake.vertex_output(P, len(frames), False, False, []))
    if mode == "shape_keys":
        for f in write_shape_keys(pobj, local, frames, options.interpolation, record):
            yield 0.2 + 0.8 * f
    else:
        folder, more = cache_folder(obj.name, options, record)
        notes.extend(more)
        for f in write_mesh_cache(pobj, local, frames, options.interpolation, folder, record, suffix="_particles"):
            yield 0.2 + 0.8 * f


# =========================================================================== removal
# PC2 files removed by clear_bake go to a session trash so that Ctrl-Z (which restores the Mesh Cache
# modifier) can bring them back: the add-on calls restore_trashed_files() after undo/redo.
_TRASHED: dict = {}


def _trash(path: Path) -> None:
    from ..paths import cache_dir

    folder = cache_dir("bake_trash")
    target = folder / f"{len(_TRASHED):06d}_{os.getpid()}_{path.name}"
    key = os.path.normpath(str(path.resolve()))
    _move(path, target)  # a rename when on the same file system
    _TRASHED[key] = target


def _move(src: Path, dst: Path) -> None:
    import shutil

    shutil.move(str(src), str(dst))


def restore_trashed_files() -> int:
    """Put back PC2 files that a cleared bake removed if a Mesh Cache modifier refers to them again
    (after Ctrl-Z).  Returns how many were restored."""
    restored = 0
    for obj in bpy.data.objects:
        for m in obj.modifiers:
            if m.type == "MESH_CACHE" and m.filepath:
                path = os.path.normpath(bpy.path.abspath(m.filepath))
                src = _TRASHED.get(path)
                if src is not None and not os.path.exists(path) and Path(src).is_file():
                    os.makedirs(os.path.dirname(path), exist_ok=True)
                    _move(Path(src), Path(path))
                    del _TRASHED[path]
                    restored += 1
    return restored


def empty_trash() -> None:
    """Delete the PC2 files kept for undo (a new file was loaded: the undo history is gone)."""
    for src in list(_TRASHED.values()):
        with contextlib.suppress(OSError):
            Path(src).unlink()
    _TRASHED.clear()


def _remove_recorded(obj, rec: dict, keep_for_undo: bool = False) -> None:
    """Remove everything listed in a bake record (tolerates parts already gone).

    ``keep_for_undo``: PC2 files go to a session trash (see :func:`restore_trashed_files`) instead of
    being deleted."""
    data = bpy.data
    # actions first (they reference the ids)
    for name in rec.get("actions", []):
        act = data.actions.get(name)
        if act is not None:
            data.actions.remove(act)
    if obj is not None:
        if rec.get("created_key") and obj.data.shape_keys is not None:
            obj.shape_key_clear()
        for name in rec.get("modifiers", []):
            m = obj.modifiers.get(name)
            if m is not None:
                obj.modifiers.remove(m)
        for name in rec.get("vertex_groups", []):
            g = obj.vertex_groups.get(name)
            if g is not None:
                obj.vertex_groups.remove(g)
    for name in rec.get("objects", []):
        o = data.objects.get(name)
        if o is not None:
            if o.type == "MESH" and o.data is not None and o.data.shape_keys is not None:
                o.shape_key_clear()
            data.objects.remove(o)
    for name in rec.get("meshes", []):
        m = data.meshes.get(name)
        if m is not None and m.users == 0:
            data.meshes.remove(m)
    for name in rec.get("armatures", []):
        a = data.armatures.get(name)
        if a is not None and a.users == 0:
            data.armatures.remove(a)
    for name in rec.get("node_groups", []):
        g = data.node_groups.get(name)
        if g is not None and g.users == 0:
            data.node_groups.remove(g)
    for path in rec.get("files", []):
        p = Path(path)
        if p.suffix == ".pc2" and p.is_file():
            if keep_for_undo:
                _trash(p)
            else:
                p.unlink()
    for folder in rec.get("folders", []):
        with contextlib.suppress(OSError):
            os.rmdir(folder)  # only when empty


def bake_record(obj) -> Optional[dict]:
    """The record of the bake on ``obj`` (what it added), or ``None`` if it has none."""
    if obj is None:
        return None
    return core_bake.parse_record(obj.get(BAKE_RECORD_KEY))


def clear_bake(obj) -> dict:
    """Remove everything the bake on ``obj`` added: shape keys, their action, modifiers, vertex groups,
    the armature or particle objects with their data and actions, and the PC2 files it wrote.

    The original mesh data is untouched.  Returns the record that was cleared; an object without a
    bake is a :class:`UserError`.
    """
    if obj is None:
        raise UserError("no object selected")
    rec = bake_record(obj)
    if rec is None:
        raise UserError(f"object '{obj.name}' has no UniPixie bake to clear")
    if obj.library is not None:
        raise UserError(f"'{obj.name}' is linked from another file and cannot be changed")
    # the Mesh Cache path may have been made relative since the bake: resolve it from the modifier
    files = set(rec.get("files", []))
    for name in rec.get("modifiers", []):
        m = obj.modifiers.get(name)
        if m is not None and m.type == "MESH_CACHE" and m.filepath:
            files.add(os.path.normpath(bpy.path.abspath(m.filepath)))
    for oname in rec.get("objects", []):
        o = bpy.data.objects.get(oname)
        if o is not None:
            for m in o.modifiers:
                if m.type == "MESH_CACHE" and m.filepath:
                    files.add(os.path.normpath(bpy.path.abspath(m.filepath)))
    rec = {**rec, "files": sorted(files)}
    _remove_recorded(obj, rec, keep_for_undo=True)
    if BAKE_RECORD_KEY in obj:
        del obj[BAKE_RECORD_KEY]
    s = object_settings(obj)
    if s is not None:
        s.status = ""
    return rec


# =========================================================================== the whole bake
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
    mode, more = core_bake.choose_output(options.solver, options.output, bo.vertex_count, len(frames),
                                         has_other_shape_keys=own_keys, mesh_shared=me.users > 1)
    notes.extend(more)
    if bake_record(obj) is not None:
        clear_bake(obj)
    plan = None
    if mode == "armature":
        if traj.handle_transforms is None or result.skinning_weights is None:
            reason = "the LBS run returned no handle transforms / vertex weights"
        else:
            plan, reason = core_bake.plan_armature(bo, result.skinning_weights, traj.handle_transforms, traj.positions,
                                                   options.armature_tolerance, result.ground_height)
        if plan is None:
            fallback = core_bake.vertex_output(bo.vertex_count, len(frames), me.shape_keys is not None, me.users > 1, [])
            notes.append(f"LBS handles baked per vertex ({fallback.replace('_', ' ')}) instead of an armature: {reason}")
            mode = fallback
    record = WriteRecord(obj.name)
    done = False
    try:
        if mode == "armature":
            for f in write_armature(obj, bo, plan, frames, options.interpolation, record):
                yield 0.9 * f, "writing the armature"
        else:
            local = core_bake.trajectory_to_local(bo, traj.positions)
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
        obj[BAKE_RECORD_KEY] = core_bake.make_record(
            **record.to_dict(), mode=mode, solver=options.solver, frames=[int(frames[0]), int(frames[-1])],
            fps=options.fps, alpha=options.alpha, material=result.material_description,
            material_source=options.material.to_dict(), effects=core_bake.effects_to_json(options.effects),
            device=options.device, notes=notes, armature_error=rep.armature_error,
            simulate_seconds=result.seconds, write_seconds=rep.write_seconds, **(report or {}))
        done = True
        return rep
    finally:
        if not done:
            _remove_recorded(obj, record.to_dict())


def bake_steps(obj, options: Optional[BakeOptions] = None, scenario=None, scene=None,
               wait: float = 0.05) -> Iterator[tuple[float, str]]:
    """The whole bake of ``obj`` as a generator of ``(fraction, status)``; its return value is a :class:`BakeReport`.

    Reads and checks everything first (bad input changes nothing), runs the simulation in a worker
    thread (the caller yields to Blender between polls), then writes.  Closing the generator (Esc)
    cancels the simulation and removes anything written.
    """
    scene = scene or bpy.context.scene
    bo = read_object(obj, scene)
    options = options or options_from_settings(obj, scene)
    scenario = scenario if scenario is not None else scenario_from_scene(obj, scene)
    own_keys = obj.data.shape_keys is not None and bake_record(obj) is None
    core_bake.choose_output(options.solver, options.output, bo.vertex_count, options.frames.count,
                            has_other_shape_keys=own_keys, mesh_shared=obj.data.users > 1)  # refuse before simulating
    yield 0.0, "starting"
    run = core_bake.BackgroundRun(lambda progress: core_bake.simulate(bo, scenario, options, progress),
                                  description=f"{options.solver} bake").start()
    try:
        while not run.wait(wait):
            yield 0.85 * run.fraction, run.status or "simulating"
    finally:
        if not run.done:
            run.cancel(wait=True)
    result = run.result()
    yield 0.85, "writing"
    gen = write_result(obj, bo, result, options)
    try:
        while True:
            try:
                frac, status = next(gen)
            except StopIteration as stop:
                report = stop.value
                break
            yield 0.85 + 0.15 * frac, status
    finally:
        gen.close()  # on Esc: the writer removes what it wrote
    s = object_settings(obj)
    if s is not None:
        s.status = f"baked: {report.mode.replace('_', ' ')}, frames {report.frames[0]}-{report.frames[1]}"
    return report


def bake_object(obj, options: Optional[BakeOptions] = None, scenario=None, progress: Optional[Progress] = None,
                scene=None) -> BakeReport:
    """Bake ``obj`` to the end (Python API for pipeline scripts).

    options: :class:`~unipixie.core.bake.BakeOptions` (default: the object's panel settings and the
    scene's frame range); scenario: a :class:`~unipixie.solvers.scenario.Scenario` (default: from the
    scene, see :func:`scenario_from_scene`).  ``progress`` receives the fraction and can cancel.
    """
    progress = progress or silent()
    gen = bake_steps(obj, options, scenario, scene)
    last = 0.0
    try:
        while True:
            try:
                frac, status = next(gen)
            except StopIteration as stop:
                return stop.value
            progress.step(max(0.0, frac - last) * progress.total, status)
            last = max(last, frac)
    finally:
        gen.close()


# =========================================================================== jobs (command line / farms)
def options_for_job(job: BakeJob, obj, scene) -> tuple[BakeOptions, object]:
    """A job's :class:`BakeOptions` and scenario: the job's values over the object's panel settings."""
    s = object_settings(obj)
    material = job.material
    if material is None:
        if job.alpha is not None:
            material = ModelSource()
        else:
            material = material_source_from_settings(obj)
    frames = job.frames or ((s.bake_frame_start, s.bake_frame_end) if s is not None and s.use_bake_frame_range
                            else (scene.frame_start, scene.frame_end))
    alpha = job.alpha if job.alpha is not None else (float(s.alpha) if s is not None else None)
    options = BakeOptions(solver=job.solver, frames=frames, fps=scene_fps(scene), material=material, alpha=alpha,
                          effects=list(job.effects), device=job.device, output=job.output,
                          interpolation=job.interpolation, particles=job.particles,
                          armature_tolerance=job.armature_tolerance, solver_settings=job.solver_settings,
                          cache_dir=str(Path(job.out).resolve().parent / f"{Path(job.out).stem}_unipixie"))
    sc = job.scenario or {}
    ground_obj = None
    use_ground = None
    if "ground" in sc and isinstance(sc["ground"], str):
        ground_obj = bpy.data.objects.get(sc["ground"])
        if ground_obj is None:
            raise UserError(f"ground object '{sc['ground']}' not found in {job.scene}")
    clamp_obj = None
    clamp_group = ""
    if isinstance(sc.get("clamp"), str):
        clamp_obj = bpy.data.objects.get(sc["clamp"])
        if clamp_obj is None:
            raise UserError(f"clamp object '{sc['clamp']}' not found in {job.scene}")
    if isinstance(sc.get("clamp_group"), str):
        clamp_group = sc["clamp_group"]
    if "ground" in sc and not isinstance(sc["ground"], str):
        use_ground = False  # no ground, or an explicit height set below
    scenario = scenario_from_scene(obj, scene, ground_object=ground_obj, use_ground=use_ground,
                                   clamp_object=clamp_obj, clamp_group=clamp_group)
    numeric = {k: v for k, v in sc.items() if k in ("gravity", "initial_velocity", "initial_angular_velocity", "pinned_box")}
    if isinstance(sc.get("ground"), dict):
        numeric["ground"] = sc["ground"]
    if numeric:
        from ...solvers.scenario import Scenario

        d = scenario.to_dict()
        d.update(numeric)
        scenario = Scenario.from_dict(d)
    return options, scenario


def blend_object_names(path) -> list[str]:
    """Names of the objects stored in a .blend file, read without opening it (the current file is untouched)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"scene file not found: {path}")
    if path.suffix.lower() != ".blend":
        raise UserError(f"{path}: the scene must be a .blend file")
    if bpy.data.filepath and os.path.samefile(bpy.data.filepath, path):
        return [o.name for o in bpy.data.objects]  # Blender cannot "load from" the open file
    try:
        with bpy.data.libraries.load(str(path.resolve())) as (data_from, _data_to):
            names = list(data_from.objects)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable .blend file ({exc})") from None
    return names


def time_writes(bo: BakeObject, result: SimulationResult, options: BakeOptions, modes: Sequence[str],
                repeats: int = 3) -> dict:
    """Median wall time (s) of writing ``result`` as each output mode, in a fresh empty scene (benchmark).

    Returns ``{mode: (seconds, runs)}``; a mode the writer had to replace (an LBS motion that bones
    cannot represent) is left out.  Everything written is cleared again.
    """
    import statistics
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory(prefix="unipixie-bench-bake-") as tmp:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        me = bpy.data.meshes.new(bo.name)
        me.from_pydata(bo.rest_local.tolist(), [], bo.triangles.tolist())
        me.update()
        obj = bpy.data.objects.new(bo.name, me)
        bpy.context.scene.collection.objects.link(obj)
        for mode in modes:
            times = []
            for _ in range(repeats):
                opts = BakeOptions(**{**options.__dict__, "output": mode, "cache_dir": tmp})
                t0 = time.perf_counter()
                gen = write_result(obj, bo, result, opts)
                while True:
                    try:
                        next(gen)
                    except StopIteration as stop:
                        rep = stop.value
                        break
                times.append(time.perf_counter() - t0)
                clear_bake(obj)
                if rep.mode != mode:
                    times = []
                    break
            if times:
                out[mode] = (statistics.median(times), len(times))
        empty_trash()
    return out
