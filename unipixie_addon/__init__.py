"""The Blender add-on: properties, operators, panels, preferences and the job runner.

UI only: every operator calls a function of :mod:`unipixie.core` (through
``core.blender_io`` for Blender data) and holds no logic of its own.  Modules
listed in ``_MODULES`` each expose ``register()`` / ``unregister()``.
"""

from __future__ import annotations

import importlib

_MODULE_NAMES = (
    "preferences",
    "properties",
    "operators_setup",
    "panels",
    "operators_bake",
    "operators_features",
    "operators_diagnose",
    "operators_pipeline",
)


def _modules():
    return [importlib.import_module(f"{__name__}.{name}") for name in _MODULE_NAMES]


def register():
    from . import preferences

    preferences.add_dependency_path()
    for mod in _modules():
        mod.register()


def unregister():
    for mod in reversed(_modules()):
        mod.unregister()
