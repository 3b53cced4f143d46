"""Operators "Render views" and "Compute features" on the active object, and their sub-panel.

Both run as jobs (progress bar, Esc cancels after the current view) and call
:mod:`unipixie.core.features`; results go to the cache and their paths are
stored on the object (``object.unipixie_features``, saved with the .blend).
The feature model is the one the chosen model checkpoint expects (its feature
recipe's ``extractor``, else its config's ``feature_model``), as for *Run all*:
the render-pass appearance extractor (``appearance-gbuffer-v1``, Cycles' passes,
no weights, not CLIP — what the shipped model is trained on), the offline
extractor (``offline-random-vit-w32``, an untrained random ViT, not CLIP) or CLIP (e.g. ViT-B-16, from the
*CLIP weights* preference or the default weights folder that *Fetch CLIP
weights* fills).  The sub-panel says which, and offers the fetch when the
weights are missing.
"""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, IntProperty, PointerProperty, StringProperty

from ..core import extractors
from ..core.blender_io.scene_import import GEOMETRY_TYPES
from ..core.errors import UserError
from ..core.features import DEFAULT_RESOLUTION
from .jobs import JobOperator
from .preferences import draw_extractor, get_preferences

ENGINE_ITEMS = [("cycles", "Cycles", "Path tracing with the object's own materials (CPU by default)"),
                ("workbench", "Workbench", "Fast studio-lit preview renders")]


class UniPixieFeatureState(bpy.types.PropertyGroup):
    """What the feature operators produced for an object (paths into the cache)."""

    views_path: StringProperty(name="Views", subtype="FILE_PATH", description="Cached rendered views (.npz)")
    sheet_path: StringProperty(name="View sheet", subtype="FILE_PATH", description="PNG contact sheet of the views")
    grid_path: StringProperty(name="Feature grid", subtype="FILE_PATH", description="Cached feature grid (.npz)")
    slices_path: StringProperty(name="Feature slices", subtype="FILE_PATH",
                                description="PNG of PCA-coloured slices through the feature grid")
    feature_model: StringProperty(name="Feature model", description="The extractor that made the features")
    view_count: IntProperty(name="Views rendered", default=0)
    occupied_voxels: IntProperty(name="Occupied voxels", default=0)


def _options(op, context):
    """The operator's render options with the extractor the model expects (its recipe / config, as Run all)."""
    from dataclasses import replace

    from .operators_pipeline import pipeline_settings

    prefs = get_preferences(context)
    model_options = pipeline_settings(context).feature_options()
    return replace(model_options, view_count=op.view_count or int(prefs.default_view_count), resolution=op.resolution,
                   engine=op.engine, render_device="auto")


def _poll_object(context) -> bool:
    obj = getattr(context, "active_object", None)
    return obj is not None and obj.type in GEOMETRY_TYPES


class _FeatureOperatorMixin:
    view_count: IntProperty(name="Views", default=0, min=0, max=256,
                            description="Number of rendered views (0: the add-on preference, default 24)")
    resolution: IntProperty(name="Resolution", default=DEFAULT_RESOLUTION, min=32, max=1024,
                            description="Square render size in pixels (224 is the ViT's input)")
    engine: EnumProperty(name="Engine", items=ENGINE_ITEMS, default="cycles")

    @classmethod
    def poll(cls, context):
        return _poll_object(context)

    def _begin(self, context):
        """The active object (a mesh, else a UserError), remembered by name for :meth:`_target`."""
        obj = context.active_object
        if obj is None or obj.type not in GEOMETRY_TYPES:
            raise UserError("select a mesh object first")
        self._object_name = obj.name
        return obj

    def _target(self):
        return bpy.data.objects.get(getattr(self, "_object_name", "") or "")

    def job_target(self, context):
        return self._target() or getattr(context, "active_object", None)


class UNIPIXIE_OT_render_views(_FeatureOperatorMixin, JobOperator, bpy.types.Operator):
    """Render the active object's views (normalised into the unit cube, cameras on a sphere) into the cache"""

    bl_idname = "unipixie.render_views"
    bl_label = "Render views"
    bl_options = {"REGISTER"}

    def make_job(self, context):
        from ..core.blender_io.render import describe_subject
        from ..core.features import render_stage, save_view_sheet

        obj = self._begin(context)
        options = _options(self, context)
        fingerprint = describe_subject([obj]).fingerprint
        views, path = yield from render_stage([obj], options, fingerprint)
        sheet = save_view_sheet(views, path.with_name(path.stem + "_sheet.png"))
        return views.count, path, sheet

    def finish(self, context, result):
        count, path, sheet = result
        obj = self._target()
        if obj is not None:
            state = obj.unipixie_features
            state.views_path, state.sheet_path, state.view_count = str(path), str(sheet), int(count)
            obj.unipixie.status = f"{count} views rendered"
        self.report({"INFO"}, f"rendered {count} views; sheet: {sheet}")
        return {"FINISHED"}


class UNIPIXIE_OT_compute_features(_FeatureOperatorMixin, JobOperator, bpy.types.Operator):
    """Render views (or reuse cached ones), extract dense features and lift them into the 64³ feature grid"""

    bl_idname = "unipixie.compute_features"
    bl_label = "Compute features"
    bl_options = {"REGISTER"}

    def make_job(self, context):
        from ..core.features import features_job, save_feature_slices

        obj = self._begin(context)
        result = yield from features_job([obj], _options(self, context))
        slices = result.grid_path.with_name(result.grid_path.stem + "_slices.png")
        if not slices.is_file():
            save_feature_slices(result.grid, slices)
        return result, slices

    def finish(self, context, outcome):
        result, slices = outcome
        grid = result.grid
        obj = self._target()
        if obj is not None:
            state = obj.unipixie_features
            state.grid_path, state.slices_path = str(result.grid_path), str(slices)
            state.feature_model = grid.feature_model
            state.occupied_voxels = int(grid.occupancy.sum())
            if result.views_path is not None:
                state.views_path = str(result.views_path)
                state.view_count = int(grid.meta.get("view_count", 0))
            obj.unipixie.status = "features ready"
        label = extractors.label(grid.feature_model)
        msg = (f"{int(grid.occupancy.sum())} voxels, D = {grid.dim}, {label}"
               + (" (from the cache)" if result.cache_hit else ""))
        for w in result.warnings:
            self.report({"WARNING"}, w)
        self.report({"INFO"}, msg)
        return {"FINISHED"}


class VIEW3D_PT_unipixie_features(bpy.types.Panel):
    bl_idname = "VIEW3D_PT_unipixie_features"
    bl_label = "Features"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "UniPixie"
    bl_parent_id = "VIEW3D_PT_unipixie"

    @classmethod
    def poll(cls, context):
        return _poll_object(context)

    def draw(self, context):
        layout = self.layout
        state = context.active_object.unipixie_features
        draw_extractor(layout, context)
        row = layout.row(align=True)
        row.operator(UNIPIXIE_OT_render_views.bl_idname, icon="RENDER_STILL")
        row.operator(UNIPIXIE_OT_compute_features.bl_idname, icon="LIGHTPROBE_VOLUME")
        if state.view_count:
            layout.label(text=f"{state.view_count} views rendered")
        if state.grid_path:
            layout.label(text=f"{state.occupied_voxels} voxels, {state.feature_model}")
            if extractors.name_of(state.feature_model) != "clip":
                layout.label(text=extractors.description(state.feature_model), icon="INFO")


CLASSES = (UniPixieFeatureState, UNIPIXIE_OT_render_views, UNIPIXIE_OT_compute_features, VIEW3D_PT_unipixie_features)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    bpy.types.Object.unipixie_features = PointerProperty(type=UniPixieFeatureState)


def unregister():
    if hasattr(bpy.types.Object, "unipixie_features"):
        del bpy.types.Object.unipixie_features
    _unregister_classes()
