"""The demo's Blender scene: built-in objects, ground, camera, labels, and frame renders.

Used by :mod:`unipixie.core.demo` (``unipixie demo``).  Everything here starts from an empty scene of
the current Blender session (the command line's bpy module), which the demo then saves.

* :func:`import_solid` — a procedural object's ``.glb`` (one textured mesh per part) as *one* closed
  mesh object: the parts are joined, welded and united with Blender's exact Boolean (self-union), so
  overlapping parts do not leave holes or double layers inside — every solver fills the inside of the
  surface with material — while UVs and the parts' materials are kept for rendering.
* :func:`add_ground`, :func:`add_camera`, :func:`add_label`, :func:`duplicate`.
* :func:`render_frames` — Workbench renders of chosen frames (textures shown), for the contact sheet.
* :func:`read_bake_scene` — what a bake of a saved demo object simulates, per solver, without baking (for
  ``unipixie bench demo_plant``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import bpy
import numpy as np

from ..atomic_io import atomic_path
from ..errors import UserError
from .context_safety import active_and_selected
from .scene_import import quiet_blender_output


def reset(frames: int, fps: int) -> None:
    """An empty scene: metres, gravity on, frames 1..``frames`` at ``fps``."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 1.0
    scene.use_gravity = True
    scene.frame_start, scene.frame_end = 1, int(frames)
    scene.render.fps, scene.render.fps_base = int(fps), 1.0
    world = bpy.data.worlds.new("UniPixie demo")
    world.color = (0.78, 0.8, 0.84)          # the Workbench background
    scene.world = world
    scene.frame_set(1)


def import_solid(glb_path, name: str):
    """Import a ``.glb`` and make one closed mesh object ``name`` from all its meshes (see module docstring)."""
    import bmesh

    before = set(bpy.data.objects)
    with quiet_blender_output():
        result = bpy.ops.import_scene.gltf(filepath=str(glb_path))
    if "FINISHED" not in result:
        raise UserError(f"{glb_path}: Blender's glTF importer failed")
    new = [o for o in bpy.data.objects if o not in before]
    meshes = [o for o in new if o.type == "MESH"]
    if not meshes:
        raise UserError(f"{glb_path}: no mesh in the file")
    for o in new:
        if o.type != "MESH":
            bpy.data.objects.remove(o)
    base = meshes[0]
    if len(meshes) > 1:
        with active_and_selected(base, meshes):   # no context override: see .context_safety
            bpy.ops.object.join()
    base.name = base.data.name = name
    bm = bmesh.new()
    bm.from_mesh(base.data)
    bmesh.ops.remove_doubles(bm, verts=bm.verts, dist=1e-7)   # the glTF export splits vertices at every face
    bm.to_mesh(base.data)
    bm.free()
    empty = bpy.data.collections.new("UniPixie union operand")
    mod = base.modifiers.new("UniPixie union", "BOOLEAN")
    mod.operation, mod.operand_type, mod.collection, mod.solver = "UNION", "COLLECTION", empty, "EXACT"
    mod.use_self = True
    depsgraph = bpy.context.evaluated_depsgraph_get()
    united = bpy.data.meshes.new_from_object(base.evaluated_get(depsgraph), preserve_all_data_layers=True,
                                             depsgraph=depsgraph)
    base.modifiers.remove(mod)
    bpy.data.collections.remove(empty)
    old = base.data
    base.data = united
    united.name = name
    bpy.data.meshes.remove(old)
    # the exact Boolean leaves sliver faces where parts meet: dissolve them (the solvers drop zero-area faces,
    # which would open the surface)
    co = np.empty(len(united.vertices) * 3)
    united.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    tol = 1e-5 * float(np.max(co.max(0) - co.min(0)))
    bm = bmesh.new()
    bm.from_mesh(united)
    bmesh.ops.dissolve_degenerate(bm, dist=tol, edges=bm.edges)
    bmesh.ops.remove_doubles(bm, verts=bm.verts, dist=tol)
    bm.to_mesh(united)
    bm.free()
    for poly in united.polygons:
        poly.use_smooth = True
    return base


def part_vertex_group(obj, part: str, group: str) -> int:
    """A vertex group (weight 1) of the vertices of the faces whose material is named ``part``; returns its size."""
    slot = next((i for i, m in enumerate(obj.data.materials) if m is not None and m.name.split(".")[0] == part), None)
    if slot is None:
        raise UserError(f"'{obj.name}' has no material named {part!r}")
    me = obj.data
    mat_idx = np.empty(len(me.polygons), dtype=np.int32)
    me.polygons.foreach_get("material_index", mat_idx)
    verts = sorted({v for p, m in zip(me.polygons, mat_idx) if m == slot for v in p.vertices})
    vg = obj.vertex_groups.get(group) or obj.vertex_groups.new(name=group)
    vg.add(verts, 1.0, "REPLACE")
    return len(verts)


def place_on_ground(obj, x: float, y: float, height: float = 0.0) -> None:
    """Move ``obj`` so its lowest point is ``height`` metres above z = 0 at (x, y) (its bounding box centre)."""
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(0), co.max(0)
    obj.location = (x - 0.5 * (lo[0] + hi[0]), y - 0.5 * (lo[1] + hi[1]), height - lo[2])
    bpy.context.view_layer.update()


def duplicate(obj, name: str, x: float, y: float, height: float = 0.0):
    """A full copy of ``obj`` (its own mesh data, same materials, ID properties and settings) placed at (x, y)."""
    copy = obj.copy()
    copy.data = obj.data.copy()
    copy.name = copy.data.name = name
    (obj.users_collection[0] if obj.users_collection else bpy.context.scene.collection).objects.link(copy)
    place_on_ground(copy, x, y, height)
    return copy


def add_ground(size: float = 20.0):
    bpy.ops.mesh.primitive_plane_add(size=size, location=(0.0, 0.0, 0.0))
    ground = bpy.context.active_object
    ground.name = "Ground"
    mat = bpy.data.materials.new("Ground")
    mat.diffuse_color = (0.55, 0.56, 0.58, 1.0)
    ground.data.materials.append(mat)
    return ground


def add_label(text: str, location, size: float = 0.05):
    cu = bpy.data.curves.new(f"Label {text}", "FONT")
    cu.body = text
    cu.size = size
    cu.align_x = "CENTER"
    label = bpy.data.objects.new(cu.name, cu)
    bpy.context.scene.collection.objects.link(label)
    label.location = location
    label.rotation_euler = (math.pi / 2, 0.0, 0.0)
    mat = bpy.data.materials.new(f"Label {text}")
    mat.diffuse_color = (0.05, 0.05, 0.05, 1.0)
    cu.materials.append(mat)
    return label


def add_camera(target, distance: float, elevation_deg: float = 14.0, lens: float = 40.0):
    """A camera looking at ``target`` (3,) from the front (−y) and a little above."""
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    bpy.context.scene.collection.objects.link(cam)
    cam.data.lens = lens
    e = math.radians(elevation_deg)
    t = np.asarray(target, dtype=np.float64)
    cam.location = (t[0], t[1] - distance * math.cos(e), t[2] + distance * math.sin(e))
    cam.rotation_euler = (math.pi / 2 - e, 0.0, 0.0)
    bpy.context.scene.camera = cam
    return cam


def render_frames(frames: Sequence[int], folder, size=(640, 360), hide=()) -> list:
    """Workbench renders (studio light, textures, shadows) of ``frames`` into ``folder``; returns the PNG paths.

    hide: objects not to render (e.g. field displays).  The scene's render settings and current frame are
    restored afterwards.
    """
    scene = bpy.context.scene
    if scene.camera is None:
        raise UserError("the scene has no camera to render the frames with")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    r, shading = scene.render, scene.display.shading
    saved = (r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage, r.filepath,
             shading.light, shading.color_type, shading.show_shadows, scene.frame_current)
    hidden = [(o, o.hide_render) for o in hide]
    out = []
    try:
        r.engine = "BLENDER_WORKBENCH"
        r.resolution_x, r.resolution_y, r.resolution_percentage = int(size[0]), int(size[1]), 100
        r.image_settings.file_format = "PNG"
        shading.light, shading.color_type, shading.show_shadows = "STUDIO", "TEXTURE", True
        for o, _ in hidden:
            o.hide_render = True
        for f in frames:
            scene.frame_set(int(f))
            path = folder / f"frame_{int(f):04d}.png"
            with atomic_path(path) as tmp:  # the picture is checked whole before it takes its name
                r.filepath = str(tmp)
                with quiet_blender_output():
                    bpy.ops.render.render(write_still=True)
            out.append(path)
    finally:
        (r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage, r.filepath,
         shading.light, shading.color_type, shading.show_shadows, current) = saved
        for o, h in hidden:
            o.hide_render = h
        scene.frame_set(current)
    return out


def save(path) -> None:
    """Save the session as ``path`` (relative paths remapped), quietly, atomically and verified; ``path``
    becomes the session's file (the bakes put their PC2 caches beside it)."""
    from .blend_file import save_blend

    save_blend(path, quiet=True, as_session_file=True)


def mesh_volume(obj) -> float:
    """Volume (m³) enclosed by the object's mesh at rest (world space, scene units × unit scale)."""
    from .bake import read_object

    import trimesh

    bo = read_object(obj)
    return float(abs(trimesh.Trimesh(bo.rest_world, bo.triangles, process=False).volume))


def read_bake_scene(blend, object_name: str, settings, solvers: Sequence[str]) -> dict:
    """Open ``blend`` (it replaces the session's file) and return what a bake of ``object_name`` with its recorded
    prediction would simulate with each of ``solvers``, without baking: ``{"object", "alpha", "size_m", "fps",
    "times" (T,) s, "scenario", "effects", solver: {"body", "spec" (the resolved material), "settings"}}``.
    ``settings``: the :class:`~unipixie.core.pipeline.PipelineSettings` the prediction was made with (its model)."""
    from ..atomic_io import check_blend
    from ..bake.body import build_body
    from . import pipeline as pio
    from .bake import read_object, registered_properties, scenario_from_scene

    blend = Path(blend)
    if not blend.is_file():
        raise UserError(f"{blend}: no such .blend file (run 'unipixie demo' first)")
    check_blend(blend)
    with quiet_blender_output():
        bpy.ops.wm.open_mainfile(filepath=str(blend.resolve()))
    obj = bpy.data.objects.get(object_name)
    if obj is None:
        raise UserError(f"{blend}: no object named {object_name!r}")
    with registered_properties():
        scene = bpy.context.scene
        baked = read_object(obj, scene)
        out = {"object": object_name, "size_m": float(baked.size), "scenario": scenario_from_scene(obj, scene)}
        for solver in solvers:
            options = pio.bake_options(obj, scene, solver=solver)
            options.material = pio.model_source(obj, settings, options.material)
            body, _ = build_body(baked, solver)
            resolved = options.material.resolve(baked, options.alpha, solver)
            out[solver] = {"body": body, "spec": resolved.spec, "settings": dict(resolved.settings)}
        out.update(alpha=float(options.alpha), times=np.asarray(options.times(), np.float64), fps=float(options.fps),
                   effects=list(options.effects))
    return out
