"""Properties stored on objects and on the window manager.

Besides the settings the operators read, ``obj.unipixie`` holds what the panel shows: each pipeline
step's state (``state_<step>`` / ``reason_<step>``, written by
:func:`unipixie.unipixie_addon.operators_pipeline.refresh_object`), the field display switch and its
one-line summary.  ``obj.unipixie.effects`` has one group per effect of the registry
(:mod:`unipixie.solvers.effects`), generated from it at registration: a switch and the effect's
parameters with their units and bounds; they are kept in step with the bake's ``bake_effects`` text.
"""

from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..core import bake as _bake
from ..solvers import effects as _effects
from ..solvers import materials as _materials
from ..solvers import registry as _solvers

SOLVER_ITEMS = [(s.name, s.label, s.description) for s in _solvers.SOLVERS.values()]
DEVICE_ITEMS = [("cpu", "CPU", "Run on the CPU"), ("cuda", "CUDA", "Run on the first NVIDIA GPU")]
BAKE_MATERIAL_SOURCE_ITEMS = [(k, *_bake.MATERIAL_SOURCE_LABELS[k]) for k in _bake.MATERIAL_SOURCES]
BAKE_OUTPUT_ITEMS = [(k, *_bake.OUTPUT_LABELS[k]) for k in _bake.OUTPUT_MODES]
BAKE_INTERPOLATION_ITEMS = [(k, k.title(), f"{k.title()} between frames") for k in _bake.INTERPOLATIONS]
MATERIAL_CLASS_ITEMS = _materials.blender_enum_items()


def _on_alpha(self, context):
    from . import operators_pipeline

    operators_pipeline.on_alpha_changed(self.id_data, context)


def _on_bake_setting(self, context):
    from . import operators_pipeline

    operators_pipeline.on_settings_changed(self.id_data, context)


def _on_bake_effects(self, context):
    _effects_from_text(self)
    _on_bake_setting(self, context)


# --------------------------------------------------------------------------- effects, generated from the registry
_SYNCING = [False]
EFFECT_PANEL_PARAMS = {}
"""Effect name → the parameters its panel group shows (scalars and 3-vectors; structural ones such as a
stiffness region's box are given in the bake's effects text)."""


def _representable(cls) -> bool:
    return all(p.fittable and p.size in (1, 3) for p in cls.params)


def _text_from_effects(settings) -> None:
    """Write ``bake_effects`` from the effect switches (keeping effects the switches cannot express)."""
    if _SYNCING[0]:
        return
    keep = []
    for spec in (x.strip() for x in settings.bake_effects.split(";")):
        if spec and spec.partition(":")[0].strip() not in EFFECT_PANEL_PARAMS:
            keep.append(spec)
    specs = []
    for name, params in EFFECT_PANEL_PARAMS.items():
        group = getattr(settings.effects, name)
        if group.use:
            specs.append(_effects.get(name).spec_of({p.name: getattr(group, p.name) for p in params}))
    _SYNCING[0] = True
    try:
        settings.bake_effects = "; ".join(specs + keep)
    finally:
        _SYNCING[0] = False


def _effects_from_text(settings) -> None:
    """Set the effect switches from ``bake_effects`` (specs that do not parse are left to the bake's check)."""
    if _SYNCING[0] or not hasattr(settings, "effects"):
        return
    parsed = {}
    for spec in (x.strip() for x in settings.bake_effects.split(";")):
        if not spec:
            continue
        try:
            eff = _effects.parse(spec)
        except Exception:  # a half-typed spec: the bake reports it when run
            continue
        if eff.name in EFFECT_PANEL_PARAMS:
            parsed[eff.name] = eff
    _SYNCING[0] = True
    try:
        for name in EFFECT_PANEL_PARAMS:
            group = getattr(settings.effects, name)
            eff = parsed.get(name)
            group.use = eff is not None
            if eff is not None:
                for p in EFFECT_PANEL_PARAMS[name]:
                    v = eff.values[p.name]
                    setattr(group, p.name, tuple(float(x) for x in v) if p.size > 1 else float(v))
    finally:
        _SYNCING[0] = False


def _on_effect(self, context):
    if _SYNCING[0]:
        return
    obj = self.id_data
    _text_from_effects(obj.unipixie)
    _on_bake_setting(obj.unipixie, context)


def _effect_group(cls):
    """A PropertyGroup for one registry effect: ``use`` and one property per parameter."""
    ann = {"use": BoolProperty(name=cls.label, default=False, description=f"{cls.law}", update=_on_effect)}
    for p in EFFECT_PANEL_PARAMS[cls.name]:
        label = f"{p.name} ({p.unit})" if p.unit not in ("", "-") else p.name
        if p.size == 1:
            ann[p.name] = FloatProperty(name=label, default=float(p.default), min=float(p.lower), max=float(p.upper),
                                        description=p.description, update=_on_effect)
        else:
            ann[p.name] = FloatVectorProperty(name=label, size=p.size, default=tuple(float(x) for x in p.default),
                                              min=float(p.lower), max=float(p.upper), description=p.description,
                                              update=_on_effect)
    return type(f"UniPixieEffect_{cls.name}", (bpy.types.PropertyGroup,), {"__annotations__": ann})


def _effect_classes() -> list:
    EFFECT_PANEL_PARAMS.clear()
    for name, cls in _effects.EFFECTS.items():
        if _representable(cls):
            EFFECT_PANEL_PARAMS[name] = tuple(cls.params)
    groups = [_effect_group(_effects.EFFECTS[name]) for name in EFFECT_PANEL_PARAMS]
    container = type("UniPixieEffectSettings", (bpy.types.PropertyGroup,),
                     {"__annotations__": {name: PointerProperty(type=g) for name, g in zip(EFFECT_PANEL_PARAMS, groups)}})
    return groups + [container]


STEP_STATE_DEFAULT = "not done"


class UniPixieObjectSettings(bpy.types.PropertyGroup):
    """Per-object UniPixie settings (saved with the .blend)."""

    alpha: FloatProperty(name="Softness ↔ stiffness (α)", min=0.0, max=1.0, default=0.5, update=_on_alpha,
                         description="0 = the softest plausible material, 1 = the stiffest; moving it recolours the "
                                     "material field from the cached α sweep, and Simulate & bake uses it")
    solver: EnumProperty(name="Solver", items=SOLVER_ITEMS, default="mpm", update=_on_bake_setting)
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="cpu", update=_on_bake_setting)
    status: StringProperty(name="Status", default="")
    last_error: StringProperty(name="Last error", default="")

    # -- baking (core/bake/, unipixie_addon/operators_bake.py) ---------------------------------------
    bake_material_source: EnumProperty(
        name="Material", default="homogeneous", items=BAKE_MATERIAL_SOURCE_ITEMS, update=_on_bake_setting)
    bake_material_class: EnumProperty(name="Class", items=MATERIAL_CLASS_ITEMS,
                                      default=_bake.DEFAULT_HOMOGENEOUS["material"])
    bake_E: FloatProperty(name="Young's modulus E (Pa)", min=1.0, soft_min=1e2, soft_max=1e11,
                          default=_bake.DEFAULT_HOMOGENEOUS["E"], precision=0)
    bake_nu: FloatProperty(name="Poisson's ratio ν", min=-0.99, max=0.499, default=_bake.DEFAULT_HOMOGENEOUS["nu"])
    bake_density: FloatProperty(name="Density (kg/m³)", min=1e-3, soft_min=1.0, soft_max=2e4,
                                default=_bake.DEFAULT_HOMOGENEOUS["density"])
    bake_material_file: StringProperty(name="Material field", subtype="FILE_PATH", default="",
                                       description="A .npz material field (unipixie.material_field/1)")
    bake_ground: PointerProperty(name="Ground", type=bpy.types.Object,
                                 description="The top of this object is the ground plane (none: no ground)")
    bake_clamp_object: PointerProperty(name="Clamp object", type=bpy.types.Object,
                                       description="Material inside this object's bounding box is held fixed")
    bake_clamp_group: StringProperty(name="Clamp group", default="",
                                     description="Material inside the bounds of this vertex group is held fixed")
    bake_initial_velocity: FloatVectorProperty(name="Initial velocity", size=3, subtype="VELOCITY", unit="VELOCITY")
    bake_initial_angular_velocity: FloatVectorProperty(name="Initial angular velocity (rad/s)", size=3)
    bake_output: EnumProperty(name="Output", default="auto", items=BAKE_OUTPUT_ITEMS)
    bake_interpolation: EnumProperty(name="Interpolation", default="LINEAR", items=BAKE_INTERPOLATION_ITEMS)
    bake_particles: BoolProperty(name="Particle object", default=False,
                                 description="MPM: also make an object of the particles with E, class and velocity")
    bake_effects: StringProperty(name="Effects", default="", update=_on_bake_effects,
                                 description="Effects separated by ';', e.g. linear_drag:c=0.5; wind:acceleration=0,1,0")
    use_bake_frame_range: BoolProperty(name="Own frame range", default=False, update=_on_bake_setting,
                                       description="Bake these frames instead of the scene's frame range")
    bake_frame_start: IntProperty(name="Start", default=1, update=_on_bake_setting)
    bake_frame_end: IntProperty(name="End", default=48, update=_on_bake_setting)

    # -- the object pipeline (core/pipeline.py, unipixie_addon/operators_pipeline.py) ------------------------
    state_render: StringProperty(name="Render views", default=STEP_STATE_DEFAULT)
    state_features: StringProperty(name="Features", default=STEP_STATE_DEFAULT)
    state_predict: StringProperty(name="Predict", default=STEP_STATE_DEFAULT)
    state_bake: StringProperty(name="Simulate & bake", default=STEP_STATE_DEFAULT)
    reason_render: StringProperty(default="")
    reason_features: StringProperty(default="")
    reason_predict: StringProperty(default="")
    reason_bake: StringProperty(default="")
    show_field: BoolProperty(name="Material field", default=False,
                             description="The model's material field is shown over the object, coloured by log E")
    field_summary: StringProperty(name="Field", default="")


CLASSES = (UniPixieObjectSettings,)
_GENERATED: list = []


def register():
    _GENERATED[:] = _effect_classes()
    for cls in _GENERATED:
        bpy.utils.register_class(cls)
    UniPixieObjectSettings.__annotations__["effects"] = PointerProperty(type=_GENERATED[-1], name="Effects")
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.unipixie = PointerProperty(type=UniPixieObjectSettings)
    wm = bpy.types.WindowManager
    wm.unipixie_dependency_report = StringProperty(name="Dependency report", default="")
    wm.unipixie_status = StringProperty(name="UniPixie status", default="")
    wm.unipixie_preference_problems = StringProperty(name="Preference problems", default="")
    wm.unipixie_cuda_available = BoolProperty(name="CUDA available", default=False)
    wm.unipixie_extractor_info = StringProperty(name="Feature extractor", default="",
                                                description="Which feature extractor the model expects, and its weights")
    wm.unipixie_extractor_fetch = StringProperty(name="CLIP weights to fetch", default="",
                                                 description="The CLIP feature model whose weights are missing")


def unregister():
    wm = bpy.types.WindowManager
    for name in ("unipixie_cuda_available", "unipixie_preference_problems", "unipixie_status",
                 "unipixie_dependency_report", "unipixie_extractor_info", "unipixie_extractor_fetch"):
        if hasattr(wm, name):
            delattr(wm, name)
    if hasattr(bpy.types.Object, "unipixie"):
        del bpy.types.Object.unipixie
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
    for cls in reversed(_GENERATED):
        bpy.utils.unregister_class(cls)
    _GENERATED.clear()
