"""Bake jobs on .blend files (the command line's ``unipixie bake`` and render farms): the object names of a .blend
(:func:`blend_object_names`, for wildcards), a job's options and scenario over the object's panel settings
(:func:`options_for_job`), and :func:`run_jobs`: open each scene, give the objects whose material is the model their
prediction (:mod:`.pipeline`: their model material source carries its plan), bake them (:mod:`.bake`) and save."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Optional, Sequence

import bpy

from ...solvers.registry import SOLVER_NAMES
from .. import bake as core_bake
from ..bake import BakeJob, BakeOptions, ModelSource
from ..errors import UserError
from ..progress import Progress, silent
from .bake import (BakeReport, bake_object, material_source_from_settings, object_settings, registered_properties,
                   scenario_from_scene, scene_fps)


def options_for_job(job: BakeJob, obj, scene) -> tuple[BakeOptions, object]:
    """A job's :class:`BakeOptions` and scenario: the job's values over the object's panel settings."""
    s = object_settings(obj)
    material = job.material
    if material is None:
        if job.alpha is not None:
            material = ModelSource()
        else:
            material = material_source_from_settings(obj)
    frames = job.frames or ((s.bake_frame_start, s.bake_frame_end) if s is not None and s.use_bake_frame_range
                            else (scene.frame_start, scene.frame_end))
    alpha = job.alpha if job.alpha is not None else (float(s.alpha) if s is not None else None)
    options = BakeOptions(solver=job.solver, frames=frames, fps=scene_fps(scene), material=material, alpha=alpha,
                          effects=list(job.effects), device=job.device, output=job.output,
                          interpolation=job.interpolation, particles=job.particles,
                          armature_tolerance=job.armature_tolerance, solver_settings=job.solver_settings,
                          cache_dir=str(Path(job.out).resolve().parent / f"{Path(job.out).stem}_unipixie"))
    sc = job.scenario or {}
    ground_obj = None
    use_ground = None
    if "ground" in sc and isinstance(sc["ground"], str):
        ground_obj = bpy.data.objects.get(sc["ground"])
        if ground_obj is None:
            raise UserError(f"ground object '{sc['ground']}' not found in {job.scene}")
    clamp_obj = None
    clamp_group = ""
    if isinstance(sc.get("clamp"), str):
        clamp_obj = bpy.data.objects.get(sc["clamp"])
        if clamp_obj is None:
            raise UserError(f"clamp object '{sc['clamp']}' not found in {job.scene}")
    if isinstance(sc.get("clamp_group"), str):
        clamp_group = sc["clamp_group"]
    if "ground" in sc and not isinstance(sc["ground"], str):
        use_ground = False  # no ground, or an explicit height set below
    scenario = scenario_from_scene(obj, scene, ground_object=ground_obj, use_ground=use_ground,
                                   clamp_object=clamp_obj, clamp_group=clamp_group)
    numeric = {k: v for k, v in sc.items() if k in ("gravity", "initial_velocity", "initial_angular_velocity", "pinned_box")}
    if isinstance(sc.get("ground"), dict):
        numeric["ground"] = sc["ground"]
    if numeric:
        from ...solvers.scenario import Scenario

        d = scenario.to_dict()
        d.update(numeric)
        scenario = Scenario.from_dict(d)
    return options, scenario


def blend_object_names(path) -> list[str]:
    """Names of the objects stored in a .blend file, read without opening it (the current file is untouched)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"scene file not found: {path}")
    if path.suffix.lower() != ".blend":
        raise UserError(f"{path}: the scene must be a .blend file")
    if bpy.data.filepath and os.path.samefile(bpy.data.filepath, path):
        return [o.name for o in bpy.data.objects]  # Blender cannot "load from" the open file
    try:
        with bpy.data.libraries.load(str(path.resolve())) as (data_from, _data_to):
            names = list(data_from.objects)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable .blend file ({exc})") from None
    return names



def run_jobs(jobs: Sequence[BakeJob], progress: Optional[Progress] = None, log=print,
             allow_long: bool = False, auto: bool = True) -> list[BakeReport]:
    """Run bake jobs: for each (scene, out) group open the scene, bake its objects, save ``out``.

    Object names may be shell wildcards (resolved in the opened scene).  PC2 caches go to
    ``<out stem>_unipixie/`` next to ``out`` and are referenced relative to it.  Before any simulation
    every output is checked (not an input, also through links; writable, with room) and locked against
    a second run writing it at the same time; each ``.blend`` is saved atomically and verified
    (:func:`~unipixie.core.blender_io.blend_file.save_blend`).  allow_long: run jobs whose up-front cost
    estimate passes the long-job limit (:mod:`unipixie.core.cost`).

    Jobs whose material is the model at α without a feature-grid file get the object's own prediction
    (:func:`~unipixie.core.blender_io.pipeline.prepare_model_material`), carried by their material source as its
    plan: ``auto`` runs whatever the object
    lacks first — render views, features, the prediction at the jobs' α values — with the panel's steps, cache
    and feature recipe, logging each step with its time; ``auto=False`` computes nothing and refuses an object
    without a current recorded prediction.
    """
    from ..atomic_io import check_writable, locked
    from .blend_file import save_blend

    progress = progress or silent()
    reports: list[BakeReport] = []
    groups = core_bake.group_jobs(jobs)
    core_bake.check_job_outputs(jobs)
    for group in groups:  # before any simulation: every output can be written
        scene_path = Path(group[0].scene)
        if not scene_path.is_file():
            raise UserError(f"scene file not found: {scene_path}")
        if scene_path.suffix.lower() != ".blend":
            raise UserError(f"{scene_path}: the scene must be a .blend file")
        out = Path(group[0].out)
        if out.suffix.lower() != ".blend":
            raise UserError(f"{out}: the output must be a .blend file")
        check_writable(out, 2 * scene_path.stat().st_size, what="output")
    with locked([g[0].out for g in groups], what="output"):
        for group in groups:
            scene_path = Path(group[0].scene)
            out = Path(group[0].out)
            bpy.ops.wm.open_mainfile(filepath=str(scene_path.resolve()))
            with registered_properties():
                scene = bpy.context.scene
                names = [o.name for o in bpy.data.objects]
                planned = []
                for job in group:
                    for name in core_bake.select_objects([job.object], names):
                        obj = bpy.data.objects[name]
                        j = BakeJob(**{**job.__dict__, "object": name})
                        options, scenario = options_for_job(j, obj, scene)
                        options.allow_long = bool(allow_long)
                        planned.append((obj, j, options, scenario))
                prepared = _prepare_model_materials(planned, auto, log)
                for obj, j, options, scenario in planned:
                    if obj.name in prepared and options.material.kind == "model" and not options.material.features:
                        options.material = dataclasses.replace(options.material, plan=prepared[obj.name][1])
                    log(f"baking {j.describe()}")
                    sub = progress.sub(1.0, 1.0, obj.name)
                    rep = bake_object(obj, options, scenario, progress=sub, scene=scene)
                    for n in rep.notes:
                        log(f"  note: {n}")
                    log(f"  {rep.summary()}")
                    if obj.name in prepared:
                        from .pipeline import note_bake

                        note_bake(obj, options, prepared[obj.name][0])
                    reports.append(rep)
                save_blend(out)
                log(f"saved {out}")
    return reports


def _prepare_model_materials(planned, auto: bool, log) -> dict:
    """For the planned ``(obj, job, options, scenario)`` whose material is the model without a feature-grid file:
    the object's prediction at the jobs' α values with the heads their solvers need (one pass per object).
    Returns ``{object name: (fingerprint, ModelPlan)}`` of the objects prepared."""
    from ..pipeline import PipelineSettings, cuda_available
    from . import pipeline as pio

    wanted: dict = {}
    for obj, job, options, _ in planned:
        src = options.material
        if src.kind != "model" or src.features:
            continue
        device = str(job.device or "cpu")
        if device == "auto":
            device = "cuda" if cuda_available() else "cpu"
        key = (src.checkpoint or "", int(src.seed), device)
        w = wanted.setdefault(obj.name, {"obj": obj, "key": key, "alphas": set(), "heads": set()})
        if w["key"] != key:
            raise UserError(f"object '{obj.name}' is baked with two different model checkpoints, seeds or devices in "
                            "one output file; bake them into separate files")
        w["alphas"].add(float(options.alpha))
        w["heads"].update(core_bake.MODEL_HEADS[options.solver])
    prepared = {}
    for name, w in wanted.items():
        checkpoint, seed, device = w["key"]
        heads = tuple(h for h in SOLVER_NAMES if h in w["heads"])
        settings = PipelineSettings(checkpoint=checkpoint, seed=seed, device=device, heads=heads,
                                    alphas=tuple(sorted(w["alphas"]))).with_model_recipe()
        log(f"model material of '{name}' (α {', '.join(f'{a:g}' for a in sorted(w['alphas']))}):")
        prepared[name] = pio.prepare_model_material(w["obj"], settings, log=log, compute=auto)
    return prepared
