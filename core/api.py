"""The Python API for pipeline scripts: one import for every stage.

Each name here is the same function the command line and the Blender panel
call (no logic of its own); see the docs/ page named beside it::

    from unipixie.core import api

    grid = api.features_for_file("duck.glb", options=api.FeatureOptions(offline=True)).grid   # docs/features.md (Blender)
    pred = api.predict(grid, alphas=[0.0, 0.5, 1.0], checkpoint="models/default")             # docs/model.md
    field_world = api.Normalisation.of(grid).field_to_world(pred.mpm[1])                      # metres again
    traj = api.simulate("mpm", body, field_world, api.Scenario(), frame_times,                # docs/mpm.md
                        [api.parse_effect("linear_drag:c=0.5")])
    report = api.diagnose(api.load_measurement("m.npz"), "spring_mass", out_dir="report")    # docs/diagnosis.md

A bake with the model's material carries what it needs: ``api.ModelSource(features="grid.npz")`` (the model runs
on that grid) or ``api.ModelSource(plan=api.ModelPlan(grid=..., sweep=..., checkpoint=...))`` (an object's own
prediction, e.g. ``core.blender_io.pipeline.plan_of(obj, settings)``), in ``api.BakeOptions(material=...,
alpha=0.5)`` (docs/baking.md).

Blender-only entry points (``bake_object``, ``clear_bake``, ``compute_features``
on a ``bpy`` object) need the bpy module; importing this module does not
import it — each attribute is resolved on first use.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    # data types
    "FeatureGrid": ("..core.types", "FeatureGrid"),
    "MaterialField": ("..core.types", "MaterialField"),
    "Trajectory": ("..core.types", "Trajectory"),
    "Views": ("..core.types", "Views"),
    "Normalisation": ("..core.normalise", "Normalisation"),
    # features (docs/features.md)
    "FeatureOptions": ("..core.features", "FeatureOptions"),
    "compute_features": ("..core.features", "compute_features"),
    "features_for_file": ("..core.features", "features_for_file"),
    "features_from_views": ("..core.features", "features_from_views"),
    # the model (docs/model.md)
    "predict": ("..core.model.inference", "predict"),
    "Predictor": ("..core.model.inference", "Predictor"),
    # solvers (docs/mpm.md, docs/spring_mass.md, docs/lbs.md)
    "Body": ("..solvers.body", "Body"),
    "Scenario": ("..solvers.scenario", "Scenario"),
    "HomogeneousMaterial": ("..solvers.material_sampling", "HomogeneousMaterial"),
    "PointMaterial": ("..solvers.material_sampling", "PointMaterial"),
    "prepare": ("..solvers.api", "prepare"),
    "simulate": ("..solvers.api", "simulate"),
    "parse_effect": ("..solvers.effects", "parse"),
    "make_effect": ("..solvers.effects", "make"),
    "EFFECTS": ("..solvers.effects", "EFFECTS"),
    "MATERIAL_CLASSES": ("..solvers.materials", "MATERIAL_CLASSES"),
    # baking (docs/baking.md)
    "BakeOptions": ("..core.bake", "BakeOptions"),
    "HomogeneousSource": ("..core.bake", "HomogeneousSource"),
    "ModelSource": ("..core.bake", "ModelSource"),
    "ModelPlan": ("..core.model.plan", "ModelPlan"),
    "bake_object": ("..core.blender_io.bake", "bake_object"),
    "clear_bake": ("..core.blender_io.bake", "clear_bake"),
    "scenario_from_scene": ("..core.blender_io.bake", "scenario_from_scene"),
    # measurements and diagnosis (docs/diagnosis.md)
    "load_measurement": ("..core.measurement", "load"),
    "load_measurement_csv": ("..core.measurement", "load_csv"),
    "diagnose": ("..core.diagnosis.diagnose", "diagnose"),
    "synthesize_measurement": ("..core.diagnosis.synth", "synthesize"),
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    try:
        module_name, attr = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"unipixie.core.api has no attribute {name!r}") from None
    module = importlib.import_module(module_name[1:], package=__package__.rsplit(".", 1)[0]) \
        if module_name.startswith("..") else importlib.import_module(module_name)
    value = getattr(module, attr)
    globals()[name] = value
    return value


def __dir__():
    return __all__
