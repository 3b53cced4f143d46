"""Properties stored on objects and on the window manager."""

from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..core import bake as _bake
from ..solvers import materials as _materials

SOLVER_ITEMS = [
    ("mpm", "MPM", "Material Point Method: large deformation, contact, plasticity"),
    ("lbs", "LBS", "Reduced-order linear blend skinning: fast elastic motion"),
    ("spring_mass", "Spring-mass", "Anchors joined by springs: fast, approximate"),
]
DEVICE_ITEMS = [("cpu", "CPU", "Run on the CPU"), ("cuda", "CUDA", "Run on the first NVIDIA GPU")]
BAKE_MATERIAL_SOURCE_ITEMS = [(k, *_bake.MATERIAL_SOURCE_LABELS[k]) for k in _bake.MATERIAL_SOURCES]
BAKE_OUTPUT_ITEMS = [(k, *_bake.OUTPUT_LABELS[k]) for k in _bake.OUTPUT_MODES]
BAKE_INTERPOLATION_ITEMS = [(k, k.title(), f"{k.title()} between frames") for k in _bake.INTERPOLATIONS]
MATERIAL_CLASS_ITEMS = _materials.blender_enum_items()


class UniPixieObjectSettings(bpy.types.PropertyGroup):
    """Per-object UniPixie settings (saved with the .blend)."""

    alpha: FloatProperty(name="Softness ↔ stiffness (α)", min=0.0, max=1.0, default=0.5,
                         description="0 = the softest plausible material, 1 = the stiffest")
    solver: EnumProperty(name="Solver", items=SOLVER_ITEMS, default="mpm")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="cpu")
    status: StringProperty(name="Status", default="")
    last_error: StringProperty(name="Last error", default="")

    # -- baking (core/bake.py, unipixie_addon/operators_bake.py) -------------------------------------
    bake_material_source: EnumProperty(
        name="Material", default="homogeneous", items=BAKE_MATERIAL_SOURCE_ITEMS)
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
    bake_effects: StringProperty(name="Effects", default="",
                                 description="Effects separated by ';', e.g. linear_drag:c=0.5; wind:acceleration=0,1,0")
    use_bake_frame_range: BoolProperty(name="Own frame range", default=False,
                                       description="Bake these frames instead of the scene's frame range")
    bake_frame_start: IntProperty(name="Start", default=1)
    bake_frame_end: IntProperty(name="End", default=48)


CLASSES = (UniPixieObjectSettings,)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.unipixie = PointerProperty(type=UniPixieObjectSettings)
    wm = bpy.types.WindowManager
    wm.unipixie_dependency_report = StringProperty(name="Dependency report", default="")
    wm.unipixie_status = StringProperty(name="UniPixie status", default="")


def unregister():
    wm = bpy.types.WindowManager
    for name in ("unipixie_status", "unipixie_dependency_report"):
        if hasattr(wm, name):
            delattr(wm, name)
    if hasattr(bpy.types.Object, "unipixie"):
        del bpy.types.Object.unipixie
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
