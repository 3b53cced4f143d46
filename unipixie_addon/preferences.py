"""Add-on preferences: checkpoint, CLIP weights, cache directory, device, default view count, dependencies."""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import EnumProperty, IntProperty, StringProperty

from ..core import deps, paths

ADDON_ID = __package__.rsplit(".", 1)[0]
"""The add-on's module name (``bl_ext.<repo>.unipixie`` inside Blender, ``unipixie`` in tests)."""


def dependency_dir() -> Path:
    """Where *Install dependencies* puts packages: the extension's user directory, else the cache."""
    try:
        return Path(bpy.utils.extension_path_user(ADDON_ID, path="site-packages", create=True))
    except Exception:  # not running as an installed extension (e.g. the bpy module in tests)
        return paths.cache_dir("site-packages")


def add_dependency_path() -> None:
    deps.add_to_path(dependency_dir())


def _on_cache_dir(self, context):
    paths.set_cache_root(bpy.path.abspath(self.cache_dir) if self.cache_dir else None)
    _on_change(self, context)


def _on_change(self, context):
    store_problems(context, check_preferences(self))
    store_extractor_info(context, self)


class UNIPIXIE_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    checkpoint: StringProperty(name="Model checkpoint", subtype="FILE_PATH", update=_on_change,
                               description="Directory or model.safetensors of a UniPixie checkpoint (empty: the shipped default model in models/default)")
    clip_weights: StringProperty(name="CLIP weights", subtype="FILE_PATH", update=_on_change,
                                 description="Local OpenCLIP weights (file or directory) for a model trained on CLIP "
                                             "features; empty: the default weights folder that 'Fetch CLIP weights' "
                                             "fills. A model trained on the offline extractor needs none")
    cache_dir: StringProperty(name="Cache directory", subtype="DIR_PATH", update=_on_cache_dir,
                              description="Where renders, feature grids, predictions and bakes are cached (empty: ~/.cache/unipixie)")
    device: EnumProperty(name="Device", update=_on_change,
                         items=[("cpu", "CPU", "Extract features and run the model on the CPU"),
                                ("cuda", "CUDA GPU", "Extract features and run the model on the first NVIDIA GPU")],
                         default="cpu")
    default_view_count: IntProperty(name="Default views", default=24, min=4, max=128, update=_on_change,
                                    description="Number of rendered views for feature extraction")

    def draw(self, context):
        layout = self.layout
        for prop in ("checkpoint", "clip_weights", "cache_dir", "device", "default_view_count"):
            layout.prop(self, prop)
        draw_extractor(layout, context)
        problems = context.window_manager.unipixie_preference_problems
        for msg in problems.splitlines():
            layout.label(text=msg, icon="ERROR")
        row = layout.row()
        row.operator("unipixie.check_preferences", icon="CHECKMARK")
        row.operator("unipixie.check_dependencies", icon="CHECKMARK")
        row.operator("unipixie.install_dependencies", icon="IMPORT")
        report = context.window_manager.unipixie_dependency_report
        if report:
            layout.label(text="Last check: " + context.window_manager.unipixie_status)


def check_preferences(prefs) -> list[str]:
    """Problems with the preferences, one message each naming the preference and the remedy (empty when all
    is well): the checkpoint (missing, not a checkpoint, trained on other features than the add-on
    extracts), the CLIP weights, the cache directory, the device and the default view count."""
    from ..core.pipeline import check_settings

    return check_settings(checkpoint=bpy.path.abspath(prefs.checkpoint) if prefs.checkpoint else "",
                          clip_weights=bpy.path.abspath(prefs.clip_weights) if prefs.clip_weights else "",
                          cache_dir=bpy.path.abspath(prefs.cache_dir) if prefs.cache_dir else "",
                          device=prefs.device, view_count=prefs.default_view_count)


def store_problems(context, problems) -> None:
    wm = getattr(context, "window_manager", None)
    if wm is not None and hasattr(wm, "unipixie_preference_problems"):
        wm.unipixie_preference_problems = "\n".join(problems)


def store_extractor_info(context, prefs=None) -> None:
    """Say which feature extractor the chosen model expects and whether its weights are there (shown by
    :func:`draw_extractor`; computed here, on preference changes, loads and fetches, never in ``draw()``)."""
    from ..core.pipeline import extractor_summary

    wm = getattr(context, "window_manager", None)
    if wm is None or not hasattr(wm, "unipixie_extractor_info"):
        return
    prefs = prefs or get_preferences(context)
    text, fetch = extractor_summary(checkpoint=bpy.path.abspath(prefs.checkpoint) if prefs.checkpoint else "",
                                    clip_weights=bpy.path.abspath(prefs.clip_weights) if prefs.clip_weights else "")
    wm.unipixie_extractor_info, wm.unipixie_extractor_fetch = text, fetch


def draw_extractor(layout, context) -> None:
    """The feature extractor the model expects (and a *Fetch CLIP weights* button when its weights are missing)."""
    wm = context.window_manager
    if getattr(wm, "unipixie_extractor_info", ""):
        layout.label(text=wm.unipixie_extractor_info, icon="ERROR" if wm.unipixie_extractor_fetch else "INFO")
    row = layout.row()
    op = row.operator("unipixie.fetch_clip_weights", icon="IMPORT")
    op.model = wm.unipixie_extractor_fetch if getattr(wm, "unipixie_extractor_fetch", "") else ""


class UNIPIXIE_OT_check_preferences(bpy.types.Operator):
    """Check the add-on preferences: model checkpoint, CLIP weights, cache directory, device, view count"""

    bl_idname = "unipixie.check_preferences"
    bl_label = "Check preferences"
    bl_options = {"REGISTER"}

    def execute(self, context):
        problems = check_preferences(get_preferences(context))
        store_problems(context, problems)
        for msg in problems:
            self.report({"WARNING"}, msg)
        if not problems:
            self.report({"INFO"}, "preferences are usable")
        return {"FINISHED"}


class _Defaults:
    """Preference values used when the add-on runs without registered preferences (tests, scripts)."""

    checkpoint = ""
    clip_weights = ""
    cache_dir = ""
    device = "cpu"
    default_view_count = 24


def get_preferences(context=None):
    """The add-on's preferences, or defaults when it is not installed as an extension."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    return addon.preferences if addon is not None and addon.preferences is not None else _Defaults()


CLASSES = (UNIPIXIE_AP_preferences, UNIPIXIE_OT_check_preferences)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    try:
        prefs = get_preferences(bpy.context)
        if prefs.cache_dir:
            paths.set_cache_root(bpy.path.abspath(prefs.cache_dir))
        store_extractor_info(bpy.context, prefs)
    except Exception:  # the context is restricted while Blender starts: the preference applies when changed
        pass


def unregister():
    _unregister_classes()
