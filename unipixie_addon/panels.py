"""The UniPixie panel in the 3D view's sidebar (tab "UniPixie").

``draw()`` functions only lay out properties and operators; all state they show
is computed by operators and stored in properties, so tests can check the
panel's logic through those.
"""

from __future__ import annotations

import bpy


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
        if obj is None or obj.type != "MESH":
            layout.label(text="Select a mesh object", icon="INFO")
        else:
            settings = obj.unipixie
            layout.prop(settings, "alpha", slider=True)
            row = layout.row()
            row.prop(settings, "solver", expand=True)
            layout.prop(settings, "device")
            if settings.status:
                layout.label(text=f"Status: {settings.status}")
            if settings.last_error:
                layout.label(text=settings.last_error, icon="ERROR")
        if wm.unipixie_status:
            layout.label(text=wm.unipixie_status)
        layout.operator("unipixie.check_dependencies", icon="CHECKMARK")


CLASSES = (VIEW3D_PT_unipixie,)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
