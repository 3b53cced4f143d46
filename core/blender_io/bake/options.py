"""A bake's options from Blender: the object's UniPixie settings (:func:`object_settings`, readable from the command
line through :func:`registered_properties`), the material source chosen in its panel
(:func:`material_source_from_settings`) and the whole :class:`~unipixie.core.bake.BakeOptions`
(:func:`options_from_settings`: the panel's settings and the scene's frame range and fps).

Uses bpy, :mod:`unipixie.core.bake` and the property registrar the package root hands down
(:mod:`unipixie.core.property_registration`).
"""

from __future__ import annotations

import contextlib

import bpy

from ... import property_registration
from ...bake import BakeOptions, FieldFileSource, HomogeneousSource, ModelSource


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
