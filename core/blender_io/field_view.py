"""The material field in the viewport: the object's voxels coloured by log E, with a legend.

:func:`show_field` builds, for a source object with a predicted α sweep, a *field object* — the outer
faces of the occupied voxels of the model's 64³ grid (:func:`unipixie.core.pipeline.voxel_surface`),
placed over the object (parented to it, in its normalised cube) — and a *legend*: a colour bar and
text labels (E in Pa) beside it.  Colours come from one colour map over the whole α sweep's range of
log10 E (:class:`~unipixie.core.pipeline.FieldColourScale`), so moving α visibly shifts them.

:func:`recolour` is what the α slider calls: it interpolates log10 E at α from the cached sweep
(no inference) and writes one colour per face corner with a single ``foreach_set`` — a few
milliseconds for ~30k voxels.  The source object itself is never changed (a colour attribute on it
would change its render fingerprint and make its features stale).

Names: the field object is ``"UniPixie field <object>"``; it, its legend bar and labels carry the ID
property :data:`FIELD_OF` = the source object's name.
"""

from __future__ import annotations

import json
from typing import Optional

import bpy
import numpy as np

from .. import pipeline as core
from ..errors import UserError

FIELD_PREFIX = "UniPixie field"
FIELD_OF = "unipixie_field_of"
"""ID property on every object of a field display: the source object's name."""
FIELD_ROLE = "unipixie_field_role"
"""``"field"``, ``"legend"`` or ``"label"``."""
FIELD_SWEEP = "unipixie_field_sweep"
FIELD_SCALE = "unipixie_field_scale"
COLOUR_ATTRIBUTE = "unipixie_log10_E"
VOXEL_ATTRIBUTE = "unipixie_voxel"
MATERIAL_NAME = "UniPixie field colours"
LEGEND_SEGMENTS = 32
LEGEND_TICKS = 5
LEGEND_X = 0.62
"""Legend placement in the field's normalised cube (the object spans [-0.5, 0.5] along its longest axis)."""
LEGEND_WIDTH = 0.06
LABEL_SIZE = 0.05

_CACHE: dict = {}
"""Field object name → (sweep path, corner_voxel (4F,) int64, FieldColourScale)."""


# --------------------------------------------------------------------------- lookup
def display_objects(obj) -> list:
    """Every object of ``obj``'s field display (field, legend bar, labels)."""
    return [o for o in bpy.data.objects if o.get(FIELD_OF) == obj.name]


def field_object(obj):
    """The field object of ``obj`` or ``None``."""
    return next((o for o in display_objects(obj) if o.get(FIELD_ROLE) == "field"), None)


def legend_objects(obj) -> tuple:
    """(legend bar object or None, label objects bottom to top)."""
    objs = display_objects(obj)
    bar = next((o for o in objs if o.get(FIELD_ROLE) == "legend"), None)
    labels = sorted((o for o in objs if o.get(FIELD_ROLE) == "label"), key=lambda o: o.get("unipixie_tick", 0))
    return bar, labels


# --------------------------------------------------------------------------- building
def _material():
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(MATERIAL_NAME)
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeVertexColor")
    attr.layer_name = COLOUR_ATTRIBUTE
    emit = nodes.new("ShaderNodeEmission")
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(attr.outputs["Color"], emit.inputs["Color"])
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


def _link_like(new_obj, source) -> None:
    cols = list(source.users_collection) or [bpy.context.scene.collection]
    cols[0].objects.link(new_obj)


def _quad_mesh(name: str, vertices: np.ndarray, quads: np.ndarray):
    me = bpy.data.meshes.new(name)
    me.from_pydata(np.asarray(vertices, np.float64).tolist(), [], np.asarray(quads, np.int64).tolist())
    me.update()
    return me


def _set_corner_colours(me, colours: np.ndarray) -> None:
    attr = me.color_attributes.get(COLOUR_ATTRIBUTE)
    if attr is None:
        attr = me.color_attributes.new(COLOUR_ATTRIBUTE, "FLOAT_COLOR", "CORNER")
        me.color_attributes.active_color = attr
        me.color_attributes.render_color_index = me.color_attributes.active_color_index
    attr.data.foreach_set("color", np.ascontiguousarray(colours, dtype=np.float32).ravel())
    me.update_tag()


def _placement(obj):
    """(4, 4) Blender-units matrix: the normalised cube → the object's current world bounding box."""
    from ..normalise import Normalisation
    from .bake import read_object, world_vertices

    try:
        bo = read_object(obj)
        pts, us = bo.rest_world, bo.unit_scale
    except UserError:
        pts, us = world_vertices(obj), 1.0
    m = Normalisation.from_points(pts).to_world_matrix
    m[:3, :] /= us
    return m


def show_field(obj, sweep_path, alpha: float):
    """Build (or rebuild when the sweep changed) ``obj``'s field display and colour it at ``alpha``.

    sweep_path: the object's α sweep (``.npz``, :class:`~unipixie.core.model.sweep.AlphaSweep`).
    Returns the field object.
    """
    import mathutils

    sweep = core.load_sweep(sweep_path)
    scale = core.FieldColourScale.of_sweep(sweep)
    existing = field_object(obj)
    if existing is not None and existing.get(FIELD_SWEEP) == str(sweep_path):
        recolour(obj, alpha)
        return existing
    hide_field(obj)
    vertices, quads, face_voxel = core.voxel_surface(sweep.geometry, sweep.occupancy)
    name = f"{FIELD_PREFIX} {obj.name}"
    me = _quad_mesh(name, vertices, quads)
    me.attributes.new(VOXEL_ATTRIBUTE, "INT", "FACE").data.foreach_set("value", face_voxel.astype(np.int32))
    me.materials.append(_material())
    field = bpy.data.objects.new(name, me)
    field[FIELD_OF], field[FIELD_ROLE] = obj.name, "field"
    field[FIELD_SWEEP], field[FIELD_SCALE] = str(sweep_path), json.dumps(scale.to_dict())
    _link_like(field, obj)
    field.matrix_world = mathutils.Matrix(_placement(obj).tolist())
    field.parent = obj
    field.matrix_parent_inverse = obj.matrix_world.inverted()
    field.hide_select = True
    field.display.show_shadows = False
    _build_legend(obj, field, scale)
    _CACHE[field.name] = (str(sweep_path), np.repeat(face_voxel, 4), scale)
    recolour(obj, alpha)
    return field


def _build_legend(obj, field, scale: core.FieldColourScale) -> None:
    """A colour bar (``LEGEND_SEGMENTS`` quads, low E at the bottom) and ``LEGEND_TICKS`` labels beside it."""
    n = LEGEND_SEGMENTS
    z = np.linspace(-0.5, 0.5, n + 1)
    x0, x1 = LEGEND_X, LEGEND_X + LEGEND_WIDTH
    verts = np.concatenate([np.stack([np.full(n + 1, x0), np.zeros(n + 1), z], 1),
                            np.stack([np.full(n + 1, x1), np.zeros(n + 1), z], 1)])
    quads = np.array([[i, n + 1 + i, n + 2 + i, i + 1] for i in range(n)])
    me = _quad_mesh(f"{FIELD_PREFIX} legend {obj.name}", verts, quads)
    me.materials.append(_material())
    # each segment shows the colour of its centre; its 4 corners share it
    centres = (np.arange(n) + 0.5) / n
    seg = scale.lut_linear[np.rint(centres * (len(scale.lut_linear) - 1)).astype(np.int64)]
    rgba = np.concatenate([seg, np.ones((n, 1), np.float32)], 1)
    _set_corner_colours(me, np.repeat(rgba, 4, axis=0))
    bar = bpy.data.objects.new(me.name, me)
    bar[FIELD_OF], bar[FIELD_ROLE] = obj.name, "legend"
    bar["unipixie_legend_positions"] = centres.tolist()
    _link_like(bar, obj)
    bar.parent = field
    bar.hide_select = True
    texts = [(f"Young's modulus E ({core.FIELD_COLORMAP}, log scale)", 0.5 + 0.06, -1)]
    texts += [(label, pos - 0.5, i) for i, (pos, _, label) in enumerate(scale.ticks(LEGEND_TICKS))]
    for body, zpos, tick in texts:
        cu = bpy.data.curves.new(f"{FIELD_PREFIX} label {obj.name}", "FONT")
        cu.body = body
        cu.size = LABEL_SIZE
        cu.align_y = "CENTER"
        label = bpy.data.objects.new(cu.name, cu)
        label[FIELD_OF], label[FIELD_ROLE], label["unipixie_tick"] = obj.name, "label", tick
        _link_like(label, obj)
        label.parent = field
        label.location = (x1 + 0.02 if tick >= 0 else x0, 0.0, zpos)
        label.rotation_euler = (np.pi / 2, 0.0, 0.0)          # upright, facing -y (the front view)
        label.hide_select = True


# --------------------------------------------------------------------------- colouring
def _entry(field):
    hit = _CACHE.get(field.name)
    path = field.get(FIELD_SWEEP, "")
    if hit is not None and hit[0] == path:
        return hit
    me = field.data
    face_voxel = np.empty(len(me.polygons), dtype=np.int32)
    me.attributes[VOXEL_ATTRIBUTE].data.foreach_get("value", face_voxel)
    d = json.loads(field.get(FIELD_SCALE, "{}") or "{}")
    if "log10_min" in d:
        scale = core.FieldColourScale(d["log10_min"], d["log10_max"])
    else:
        scale = core.FieldColourScale.of_sweep(core.load_sweep(path))
    hit = (path, np.repeat(face_voxel.astype(np.int64), 4), scale)
    _CACHE[field.name] = hit
    return hit


def colour_by(obj, log10_E: np.ndarray) -> bool:
    """Colour ``obj``'s field display by per-voxel log10 E ((K,) in ``np.argwhere(occupancy)`` order), e.g.
    an exact prediction after "refine".  Returns False when ``obj`` has no field display."""
    field = field_object(obj)
    if field is None:
        return False
    _, corner_voxel, scale = _entry(field)
    _set_corner_colours(field.data, scale.colours_linear(np.asarray(log10_E))[corner_voxel])
    return True


def recolour(obj, alpha: float) -> bool:
    """Recolour ``obj``'s field display at ``alpha`` from the cached sweep (interpolated; no inference).
    Returns False when ``obj`` has no field display."""
    field = field_object(obj)
    if field is None:
        return False
    path, corner_voxel, scale = _entry(field)
    sweep = core.load_sweep(path)
    _set_corner_colours(field.data, scale.colours_linear(sweep.values_at("log10_E", alpha))[corner_voxel])
    return True


def corner_colours(obj) -> Optional[np.ndarray]:
    """(4F, 4) float32 colours of the field object's face corners (for checks), or ``None``."""
    field = field_object(obj)
    if field is None:
        return None
    attr = field.data.color_attributes[COLOUR_ATTRIBUTE]
    out = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", out)
    return out.reshape(-1, 4)


def legend_colours(obj) -> Optional[np.ndarray]:
    """(LEGEND_SEGMENTS, 4) float32 scene-linear colours of the legend bar, bottom to top, or ``None``."""
    bar, _ = legend_objects(obj)
    if bar is None:
        return None
    attr = bar.data.color_attributes[COLOUR_ATTRIBUTE]
    out = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", out)
    return out.reshape(-1, 4, 4)[:, 0, :]


def hide_field(obj) -> int:
    """Remove ``obj``'s field display (its objects and their data); returns how many objects were removed."""
    objs = display_objects(obj)
    for o in objs:
        _CACHE.pop(o.name, None)
        data = o.data
        bpy.data.objects.remove(o)
        if data is not None and data.users == 0:
            if isinstance(data, bpy.types.Mesh):
                bpy.data.meshes.remove(data)
            else:
                bpy.data.curves.remove(data)
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is not None and mat.users == 0:
        bpy.data.materials.remove(mat)
    return len(objs)
