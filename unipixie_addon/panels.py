"""The UniPixie panel in the 3D view's sidebar (tab "UniPixie").

The main panel shows the pipeline's four steps in order — each a button with its state (done / stale /
not done / running, and why a step is stale) — *Run all*, the α slider with *Refine at this α* and
the material-field switch, the solver (with its measured departures from the continuum at its bake
defaults, :mod:`unipixie.core.solver_fidelity`), the effects with their parameters, the device and the frame
range.  The Features, Simulate & bake and Diagnose sub-panels hold the detailed options.

``draw()`` functions only lay out properties and operators; every state they show is computed by
operators and handlers and stored in properties (``obj.unipixie.state_<step>``, ...), so tests check the
panel's logic through those.
"""

from __future__ import annotations

import bpy

from ..core import pipeline as core
from ..core.blender_io.scene_import import GEOMETRY_TYPES
from ..core.solver_fidelity import floor_lines
from .properties import EFFECT_PANEL_PARAMS

STATE_ICONS = {core.DONE: "CHECKMARK", core.STALE: "FILE_REFRESH", core.NOT_DONE: "RADIOBUT_OFF",
               core.RUNNING: "TIME"}
STEP_ICONS = {"render": "RENDER_STILL", "features": "LIGHTPROBE_VOLUME", "predict": "SHADERFX", "bake": "PHYSICS"}


def draw_frame_range(layout, settings, scene) -> None:
    """The bake's frame range (``settings``: an object's ``unipixie``): its own start and end when
    *use_bake_frame_range* is on, else the scene's range as a label."""
    col = layout.column(align=True)
    col.prop(settings, "use_bake_frame_range")
    if settings.use_bake_frame_range:
        row = col.row(align=True)
        row.prop(settings, "bake_frame_start")
        row.prop(settings, "bake_frame_end")
    else:
        col.label(text=f"Frames {scene.frame_start}-{scene.frame_end} (scene)")


class VIEW3D_PT_unipixie(bpy.types.Panel):
    bl_idname = "VIEW3D_PT_unipixie"
    bl_label = "UniPixie"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "UniPixie"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        wm = context.window_manager
        if obj is None or obj.type not in GEOMETRY_TYPES:
            layout.label(text="Select a mesh object", icon="INFO")
        else:
            s = obj.unipixie
            col = layout.column(align=True)
            for step in core.STEPS:
                row = col.row(align=True)
                op = row.operator("unipixie.pipeline_step", text=core.STEP_LABELS[step], icon=STEP_ICONS[step])
                op.step = step
                state = getattr(s, f"state_{step}")
                row.label(text=state, icon=STATE_ICONS.get(state, "QUESTION"))
                reason = getattr(s, f"reason_{step}")
                if reason:
                    col.label(text=f"    {reason}")
            layout.operator("unipixie.run_all", icon="PLAY")

            box = layout.box()
            box.prop(s, "alpha", slider=True)
            row = box.row(align=True)
            row.operator("unipixie.refine_alpha", icon="ZOOM_IN")
            row.operator("unipixie.toggle_field", icon="COLOR", depress=s.show_field)
            if s.field_summary:
                box.label(text=s.field_summary)

            layout.row().prop(s, "solver", expand=True)
            floor = floor_lines(s.solver)       # what this solver gets wrong at its defaults, measured
            if floor:
                col = layout.column(align=True)
                col.label(text=floor[0], icon="INFO")
                for line in floor[1:]:
                    col.label(text=f"    {line}")
            layout.prop(s, "bake_material_source")

            box = layout.box()
            box.label(text="Effects")
            for name, params in EFFECT_PANEL_PARAMS.items():
                group = getattr(s.effects, name)
                box.prop(group, "use")
                if group.use:
                    for p in params:
                        box.prop(group, p.name)

            if wm.unipixie_cuda_available:
                layout.prop(s, "device")
            else:
                layout.label(text="Device: CPU (no CUDA GPU found)", icon="INFO")
            draw_frame_range(layout, s, context.scene)
            if s.status:
                layout.label(text=f"Status: {s.status}")
            if s.last_error:
                layout.label(text=s.last_error, icon="ERROR")
        if wm.unipixie_status:
            layout.label(text=wm.unipixie_status)
        row = layout.row(align=True)
        row.operator("unipixie.refresh_pipeline", icon="FILE_REFRESH")
        row.operator("unipixie.check_dependencies", icon="CHECKMARK")


CLASSES = (VIEW3D_PT_unipixie,)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
