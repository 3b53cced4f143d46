"""Properties stored on objects and on the window manager."""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, FloatProperty, PointerProperty, StringProperty

SOLVER_ITEMS = [
    ("mpm", "MPM", "Material Point Method: large deformation, contact, plasticity"),
    ("lbs", "LBS", "Reduced-order linear blend skinning: fast elastic motion"),
    ("spring_mass", "Spring-mass", "Anchors joined by springs: fast, approximate"),
]
DEVICE_ITEMS = [("cpu", "CPU", "Run on the CPU"), ("cuda", "CUDA", "Run on the first NVIDIA GPU")]


class UniPixieObjectSettings(bpy.types.PropertyGroup):
    """Per-object UniPixie settings (saved with the .blend)."""

    alpha: FloatProperty(name="Softness ↔ stiffness (α)", min=0.0, max=1.0, default=0.5,
                         description="0 = the softest plausible material, 1 = the stiffest")
    solver: EnumProperty(name="Solver", items=SOLVER_ITEMS, default="mpm")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="cpu")
    status: StringProperty(name="Status", default="")
    last_error: StringProperty(name="Last error", default="")


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
