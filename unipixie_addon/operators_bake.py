"""Operators "Simulate & bake" / "Clear bake" and the bake sub-panel.

UI only.  *Simulate & bake* (``unipixie.bake``) is the pipeline's bake step — the same job
(:class:`~unipixie.unipixie_addon.operators_pipeline.BakeJob`: :func:`unipixie.core.blender_io.pipeline.bake_step`,
with the object's own prediction when its material source is the model), which the job runner drives
(progress bar, status text, Esc cancels and removes anything half-written) — with an optional solver override.
*Clear bake* is :func:`unipixie.core.blender_io.bake.clear_bake`.  Both operators are undoable (Ctrl-Z).
"""

from __future__ import annotations

import bpy

from ..core.blender_io import bake as bio
from .operators_pipeline import BakeJob
from .panels import draw_frame_range
from .properties import SOLVER_ITEMS


class UNIPIXIE_OT_bake(BakeJob, bpy.types.Operator):
    """Simulate the active mesh with the chosen solver and bake the motion into keyframes"""

    bl_idname = "unipixie.bake"
    bl_label = "Simulate & bake"
    bl_options = {"REGISTER", "UNDO"}

    solver: bpy.props.EnumProperty(name="Solver", items=[("OBJECT", "From object", "Use the object's solver setting")]
                                   + SOLVER_ITEMS, default="OBJECT", options={"SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == "MESH" and obj.mode == "OBJECT"

    def make_job(self, context):
        return (yield from self.bake_job(context, **({} if self.solver == "OBJECT" else {"solver": self.solver})))

    def finish(self, context, result):
        return self.finish_bake(context, result)


class UNIPIXIE_OT_clear_bake(bpy.types.Operator):
    """Remove everything the UniPixie bake added to the active object (shape keys, modifiers, rig, caches)"""

    bl_idname = "unipixie.clear_bake"
    bl_label = "Clear bake"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and bio.bake_record(obj) is not None

    def execute(self, context):
        from ..core.errors import UserError

        obj = context.active_object
        try:
            rec = bio.clear_bake(obj)
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"cleared the {rec.get('mode', '').replace('_', ' ')} bake of '{obj.name}'")
        return {"FINISHED"}


class VIEW3D_PT_unipixie_bake(bpy.types.Panel):
    bl_idname = "VIEW3D_PT_unipixie_bake"
    bl_label = "Simulate & bake"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "UniPixie"
    bl_parent_id = "VIEW3D_PT_unipixie"

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == "MESH"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        s = obj.unipixie
        col = layout.column(align=True)
        col.prop(s, "bake_material_source")
        if s.bake_material_source == "homogeneous":
            col.prop(s, "bake_material_class")
            col.prop(s, "bake_E")
            col.prop(s, "bake_nu")
            col.prop(s, "bake_density")
        elif s.bake_material_source == "field":
            col.prop(s, "bake_material_file")
        else:
            col.label(text=f"Model prediction at α = {s.alpha:.2f}")
        box = layout.box()
        box.label(text="Scenario")
        box.prop(s, "bake_ground")
        box.prop(s, "bake_clamp_object")
        box.prop_search(s, "bake_clamp_group", obj, "vertex_groups")
        box.prop(s, "bake_initial_velocity")
        box.prop(s, "bake_initial_angular_velocity")
        box.prop(s, "bake_effects")
        draw_frame_range(layout, s, context.scene)
        layout.prop(s, "bake_output")
        layout.prop(s, "bake_interpolation")
        if s.solver == "mpm":
            layout.prop(s, "bake_particles")
        row = layout.row(align=True)
        row.operator("unipixie.bake", icon="PHYSICS")
        row.operator("unipixie.clear_bake", icon="TRASH")
        rec = bio.bake_record(obj)
        if rec is not None:
            layout.label(text=f"Baked: {rec.get('solver')} → {rec.get('mode', '').replace('_', ' ')}, "
                              f"frames {rec['frames'][0]}-{rec['frames'][1]}", icon="CHECKMARK")


CLASSES = (UNIPIXIE_OT_bake, UNIPIXIE_OT_clear_bake, VIEW3D_PT_unipixie_bake)


@bpy.app.handlers.persistent
def _restore_after_undo(*_args):
    bio.restore_trashed_files()


@bpy.app.handlers.persistent
def _empty_trash_on_load(*_args):
    bio.empty_trash()


_HANDLERS = ((bpy.app.handlers.undo_post, _restore_after_undo), (bpy.app.handlers.redo_post, _restore_after_undo),
             (bpy.app.handlers.load_post, _empty_trash_on_load))


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    for handlers, fn in _HANDLERS:
        if fn not in handlers:
            handlers.append(fn)


def unregister():
    for handlers, fn in _HANDLERS:
        if fn in handlers:
            handlers.remove(fn)
    _unregister_classes()
