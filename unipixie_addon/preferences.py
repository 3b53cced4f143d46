"""Add-on preferences: checkpoint, CLIP weights, cache directory, device, default view count, dependencies."""

from __future__ import annotations

import os
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
    paths.set_cache_root(self.cache_dir or None)


class UNIPIXIE_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    checkpoint: StringProperty(name="Model checkpoint", subtype="FILE_PATH",
                               description="Directory or model.safetensors of a UniPixie checkpoint (empty: the shipped default model)")
    clip_weights: StringProperty(name="CLIP weights", subtype="FILE_PATH",
                                 description="Local OpenCLIP ViT-B-16 weights (file or directory); empty: the offline extractor")
    cache_dir: StringProperty(name="Cache directory", subtype="DIR_PATH", update=_on_cache_dir,
                              description="Where renders, feature grids, predictions and bakes are cached (empty: ~/.cache/unipixie)")
    device: EnumProperty(name="Device", items=[("cpu", "CPU", "Run solvers and the model on the CPU"),
                                               ("cuda", "CUDA GPU", "Run on the first NVIDIA GPU")], default="cpu")
    default_view_count: IntProperty(name="Default views", default=24, min=4, max=128,
                                    description="Number of rendered views for feature extraction")

    def draw(self, context):
        layout = self.layout
        for prop in ("checkpoint", "clip_weights", "cache_dir", "device", "default_view_count"):
            layout.prop(self, prop)
        for msg in check_preferences(self):
            layout.label(text=msg, icon="ERROR")
        row = layout.row()
        row.operator("unipixie.check_dependencies", icon="CHECKMARK")
        row.operator("unipixie.install_dependencies", icon="IMPORT")
        report = context.window_manager.unipixie_dependency_report
        if report:
            layout.label(text="Last check: " + context.window_manager.unipixie_status)


def check_preferences(prefs) -> list[str]:
    """Problems with the preferences, as messages (empty when all is well)."""
    problems = []
    if prefs.checkpoint and not os.path.exists(bpy.path.abspath(prefs.checkpoint)):
        problems.append(f"Checkpoint not found: {prefs.checkpoint}")
    if prefs.clip_weights and not os.path.exists(bpy.path.abspath(prefs.clip_weights)):
        problems.append(f"CLIP weights not found: {prefs.clip_weights}")
    if prefs.cache_dir:
        d = bpy.path.abspath(prefs.cache_dir)
        if os.path.exists(d) and not os.access(d, os.W_OK):
            problems.append(f"Cache directory is not writable: {prefs.cache_dir}")
    return problems


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


CLASSES = (UNIPIXIE_AP_preferences,)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
