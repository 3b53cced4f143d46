"""Writing an LBS motion as an armature: an armature object with one parent/child bone chain per blend bone of the
:class:`~unipixie.core.bake.ArmaturePlan`, vertex groups holding the weights, an Armature modifier and the bones
keyed at every frame (:func:`write_armature`); the ground lift after it when the plan needs one.

Uses bpy, :mod:`unipixie.core.bake` (the plan and its channels), :mod:`.writing`, :mod:`.ground_lift` and
:mod:`unipixie.core.blender_io.context_safety` (edit mode without a context override).
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import bpy
import numpy as np

from ...bake import ArmaturePlan, BakeObject, chain_channels
from ..context_safety import active_and_selected
from .ground_lift import add_ground_lift
from .writing import (PREFIX, WriteRecord, assign_action, collection_of, layered_action, move_first, set_keys,
                      unique_name)


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


def write_armature(obj, bo: BakeObject, plan: ArmaturePlan, frames: np.ndarray, interpolation: str,
                   record: WriteRecord) -> Iterator[float]:
    """An armature object (child of ``obj``, so it follows the object) with one parent/child bone chain
    per blend bone (:class:`~unipixie.core.bake.ArmaturePlan`), a vertex group per deforming bone
    holding the weights, an Armature modifier first in ``obj``'s stack (linear blending), and the
    bones keyed at every frame.  The channels are recomputed from the bone heads as Blender stored
    them, so the rounding of the rest pose adds no error.
    """
    name = unique_name(bpy.data.objects.keys(), f"{PREFIX} {obj.name} rig")
    arm = bpy.data.armatures.new(name)
    record.armatures.append(arm.name)
    arm_obj = bpy.data.objects.new(name, arm)
    record.objects.append(arm_obj.name)
    collection_of(obj).objects.link(arm_obj)
    arm_obj.parent = obj
    arm_obj.matrix_parent_inverse.identity()
    arm_obj.matrix_basis.identity()
    arm.display_type = "STICK"
    arm_obj.show_in_front = True
    B = plan.bone_count
    taken = {g.name for g in obj.vertex_groups}
    deform_names = []
    for b in range(B):
        n = unique_name(taken, f"{PREFIX} handle {plan.labels[b]}")
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
    loc, Uq, scale, Vq = chain_channels(plan.local_maps, heads)
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
    mod = obj.modifiers.new(name=unique_name({m.name for m in obj.modifiers}, f"{PREFIX} Armature"), type="ARMATURE")
    record.modifiers.append(mod.name)
    mod.object = arm_obj
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    mod.use_deform_preserve_volume = False
    mod.use_multi_modifier = False
    move_first(obj, mod)
    if plan.ground_height is not None:
        add_ground_lift(obj, bo, plan.ground_height, record)
    action, slot, bag = layered_action(f"{PREFIX} {obj.name} rig", "OBJECT", arm_obj.name)
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
                    set_keys(fc, f, values[:, i], interpolation)
    assign_action(arm_obj, action, slot)
    yield 1.0
