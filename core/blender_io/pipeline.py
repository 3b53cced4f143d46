"""The object pipeline on Blender objects: record, fingerprint, states and the four steps as jobs.

The Blender-free logic (settings, records, staleness, the α sweep, the model's material) is
:mod:`unipixie.core.pipeline`; this module applies it to ``bpy`` objects:

* :func:`read_record` / :func:`write_record` — the object's pipeline record, an ID property
  (:data:`~unipixie.core.pipeline.RECORD_KEY`): saved with the .blend, restored by undo, copied with
  the object.
* :func:`fingerprint` — what the features depend on (evaluated geometry in the normalised cube, UVs,
  colour attributes, materials and their images), with the object's own UniPixie bake muted so that
  baking does not make the features stale; moving or uniformly scaling the object does not either.
* :func:`states` — every step's :class:`~unipixie.core.pipeline.StepState`.
* :func:`render_step`, :func:`features_step`, :func:`predict_step`, :func:`refine_step`,
  :func:`bake_step`, :func:`run_all` — job generators yielding ``(fraction, status)`` (the add-on's
  modal operators drive them; :func:`unipixie.core.jobs.run_job` runs one to its end).  Each
  records what it produced only when it finishes; closing a generator (Esc) leaves the record as it was.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator, Optional

import bpy

from .. import pipeline as core
from ..errors import UserError
from ..features import rescaled

_MUTING: set = set()
"""Names of objects whose bake is muted right now (the add-on's depsgraph handler ignores them)."""
_RUNNING: dict = {}
"""Object name → the step running on it."""


# --------------------------------------------------------------------------- record
def read_record(obj) -> core.PipelineRecord:
    return core.PipelineRecord.from_json(obj.get(core.RECORD_KEY)) if obj is not None else core.PipelineRecord()


def write_record(obj, record: core.PipelineRecord) -> None:
    obj[core.RECORD_KEY] = record.to_json()


def has_record(obj) -> bool:
    return obj is not None and core.RECORD_KEY in obj.keys()


def clear_record(obj) -> None:
    """Forget what the pipeline did for ``obj`` (the cached files stay in the cache)."""
    if has_record(obj):
        del obj[core.RECORD_KEY]


# --------------------------------------------------------------------------- fingerprint
def muting() -> bool:
    """True while a fingerprint is being taken (its temporary mute of a bake causes depsgraph updates)."""
    return bool(_MUTING)


@contextlib.contextmanager
def bake_muted(obj):
    """Temporarily switch off what a UniPixie bake added to ``obj`` (its modifiers and shape keys), so the
    evaluated mesh is the object at rest; restored on exit.  Objects without a bake are left alone."""
    from .bake import bake_record

    rec = bake_record(obj)
    if rec is None:
        yield
        return
    _MUTING.add(obj.name)
    changed_mods, changed_keys = [], []
    try:
        for name in rec.get("modifiers", []):
            m = obj.modifiers.get(name)
            if m is not None and (m.show_viewport or m.show_render):
                changed_mods.append((m, m.show_viewport, m.show_render))
                m.show_viewport = m.show_render = False
        key = obj.data.shape_keys
        if key is not None:
            for name in rec.get("shape_keys", []):
                kb = key.key_blocks.get(name)
                if kb is not None and not kb.mute:
                    changed_keys.append(kb)
                    kb.mute = True
        if changed_mods or changed_keys:
            bpy.context.view_layer.update()
        yield
    finally:
        for m, viewport, render in changed_mods:
            m.show_viewport, m.show_render = viewport, render
        for kb in changed_keys:
            kb.mute = False
        if changed_mods or changed_keys:
            bpy.context.view_layer.update()    # evaluate now, while the handler still ignores this object
        _MUTING.discard(obj.name)


def fingerprint(obj) -> str:
    """The object's placement-invariant fingerprint at rest (see the module docstring)."""
    from .render import describe_subject

    with bake_muted(obj):
        return describe_subject([obj], placement_invariant=True).fingerprint


# --------------------------------------------------------------------------- states
def bake_options(obj, scene=None, **overrides):
    """The bake's current :class:`~unipixie.core.bake.BakeOptions` from the object's settings."""
    from .bake import options_from_settings

    return options_from_settings(obj, scene or bpy.context.scene, **overrides)


def bake_inputs(obj, scene=None) -> dict:
    """The current bake settings in the bake record's form (compared with it for staleness)."""
    from .. import bake as core_bake

    o = bake_options(obj, scene)
    return core_bake.parse_record(core_bake.make_record(
        solver=o.solver, frames=[o.frames.start, o.frames.end], fps=o.fps, alpha=o.alpha,
        material_source=o.material.to_dict(), effects=core_bake.effects_to_json(o.effects)))


def current_inputs(obj, settings: core.PipelineSettings, scene=None, fingerprint_value: Optional[str] = None
                   ) -> core.CurrentInputs:
    from .bake import bake_record

    error = ""
    fp = fingerprint_value
    if fp is None:
        try:
            fp = fingerprint(obj)
        except UserError as exc:
            error = str(exc)
    try:
        options = bake_inputs(obj, scene)
    except UserError:
        options = None       # bad bake settings (e.g. an unknown effect): the bake reports it when run
    return core.CurrentInputs(fingerprint=fp, settings=settings, bake_options=options, bake_record=bake_record(obj),
                              running=_RUNNING.get(obj.name, ""), error=error)


def states(obj, settings: core.PipelineSettings, scene=None, fingerprint_value: Optional[str] = None) -> dict:
    """``{step: StepState}`` for ``obj`` (``fingerprint_value``: reuse a fingerprint taken just before)."""
    return core.step_states(read_record(obj), current_inputs(obj, settings, scene, fingerprint_value))


def running_step(obj) -> str:
    return _RUNNING.get(obj.name, "") if obj is not None else ""


@contextlib.contextmanager
def _running(obj, step: str):
    name = obj.name
    _RUNNING[name] = step
    try:
        yield
    finally:
        if _RUNNING.get(name) == step:
            del _RUNNING[name]


def _object(name: str):
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise UserError(f"object '{name}' was deleted or renamed while UniPixie worked on it; nothing was recorded")
    return obj


def _check_object(obj) -> None:
    from .scene_import import GEOMETRY_TYPES

    if obj is None:
        raise UserError("no object selected: select the mesh object to work on")
    if obj.type not in GEOMETRY_TYPES:
        raise UserError(f"'{obj.name}' is a {obj.type.lower()} object; UniPixie works on meshes (and curves, text, "
                        "surfaces that convert to meshes)")
    if obj.mode == "EDIT":
        raise UserError(f"'{obj.name}' is in Edit Mode; switch to Object Mode first")


# --------------------------------------------------------------------------- the model material
def plan_of(obj, settings: core.PipelineSettings, record: Optional[core.PipelineRecord] = None):
    """The object's :class:`~unipixie.core.pipeline.ModelPlan` from its record (``None`` before Predict, or when
    its files left the cache): what a bake's model material source carries (:func:`model_source`)."""
    record = record or read_record(obj)
    pred, feat = record.get("predict"), record.get("features")
    if not pred or not feat or record.file("predict", "sweep") is None or record.file("features", "grid") is None:
        return None
    inputs = pred.get("inputs", {})
    return core.ModelPlan(grid=feat["grid"], sweep=pred["sweep"], checkpoint=pred.get("checkpoint", ""),
                          seed=int(inputs.get("seed", 0)), steps=int(inputs.get("steps", 15)), device=settings.device)


def model_source(obj, settings: core.PipelineSettings, source):
    """``source`` (a bake's material source) with ``obj``'s own prediction as its plan, when it is the model's
    material without a feature-grid file; other sources as they are.  An object without a prediction is a
    :class:`UserError` naming the remedy (before any simulation starts)."""
    import dataclasses

    from ..bake import no_prediction

    if source.kind != "model" or source.features:
        return source
    plan = plan_of(obj, settings)
    if plan is None:
        raise no_prediction(obj.name)
    return dataclasses.replace(source, plan=plan)


# --------------------------------------------------------------------------- steps
def _store(name: str, step: str, entry: dict, also: Optional[dict] = None):
    obj = _object(name)
    record = read_record(obj)
    record.set(step, entry)
    for k, v in (also or {}).items():
        record.set(k, v)
    write_record(obj, record)
    return obj, record


def render_step(obj, settings: core.PipelineSettings) -> Iterator[tuple[float, str]]:
    """Render the object's views into the cache (or find them there); returns the views path."""
    from ..features import render_stage, save_view_sheet, views_cache_path
    from .render import subject_fingerprint

    _check_object(obj)
    name = obj.name
    with _running(obj, "render"):
        yield 0.0, "reading the object"
        fp = fingerprint(obj)
        options = settings.feature_options()
        with bake_muted(obj):
            subject = subject_fingerprint([obj])
            cached = views_cache_path(subject, options.render_settings()).is_file()
            views, path = yield from render_stage([obj], options, subject)
        sheet = path.with_name(path.stem + "_sheet.png")
        if not sheet.is_file():
            save_view_sheet(views, sheet)
        _store(name, "render", {"inputs": settings.render_inputs(fp), "views": str(path), "sheet": str(sheet),
                                "count": int(views.count)})
        yield 1.0, f"{views.count} views ({options.engine}, {options.resolution} px)" + (" from the cache" if cached else "")
    return path


def features_step(obj, settings: core.PipelineSettings) -> Iterator[tuple[float, str]]:
    """Render (or reuse) the views, extract features and lift them into the 64³ grid (cached); returns the
    :class:`~unipixie.core.features.FeatureResult`."""
    from ..features import features_job, save_feature_slices

    _check_object(obj)
    name = obj.name
    with _running(obj, "features"):
        yield 0.0, "reading the object"
        fp = fingerprint(obj)
        inputs = settings.feature_inputs(fp)        # missing CLIP weights fail here, before rendering
        with bake_muted(obj):
            result = yield from features_job([obj], settings.feature_options())
        grid = result.grid
        slices = result.grid_path.with_name(result.grid_path.stem + "_slices.png")
        if not slices.is_file():
            save_feature_slices(grid, slices)
        also = {}
        if result.views_path is not None:
            sheet = result.views_path.with_name(result.views_path.stem + "_sheet.png")
            also["render"] = {"inputs": settings.render_inputs(fp), "views": str(result.views_path),
                              "sheet": str(sheet) if sheet.is_file() else "",
                              "count": int(grid.meta.get("view_count", settings.view_count))}
        obj, _ = _store(name, "features", {"inputs": inputs, "grid": str(result.grid_path), "slices": str(slices),
                                           "feature_model": grid.feature_model,
                                           "voxels": int(grid.occupancy.sum()), "warnings": result.warnings}, also)
        state = getattr(obj, "unipixie_features", None)     # the Features sub-panel's record, when registered
        if state is not None:
            state.grid_path, state.slices_path = str(result.grid_path), str(slices)
            state.feature_model, state.occupied_voxels = grid.feature_model, int(grid.occupancy.sum())
            if result.views_path is not None:
                state.views_path, state.view_count = str(result.views_path), int(grid.meta.get("view_count", 0))
        yield 1.0, (f"{int(grid.occupancy.sum())} voxels, D = {grid.dim}, {grid.feature_model}"
                    + (" from the cache" if result.cache_hit else ""))
    return result


def predict_step(obj, settings: core.PipelineSettings) -> Iterator[tuple[float, str]]:
    """Predict the α sweep from the object's feature grid (the model runs in a worker thread; Esc cancels);
    returns the :class:`~unipixie.core.model.sweep.AlphaSweep`."""
    _check_object(obj)
    name = obj.name
    record = read_record(obj)
    grid = record.file("features", "grid")
    if grid is None:
        raise UserError(f"'{name}' has no features yet: run Features first")
    ckpt = core.resolve_checkpoint(settings.checkpoint)
    with _running(obj, "predict"):
        sweep, path, inputs = yield from core.predict_job(grid, settings)
        _store(name, "predict", {"inputs": inputs, "sweep": str(path), "checkpoint": str(ckpt),
                                 "heads": list(core.sweep_heads(sweep)), "alphas": [float(a) for a in sweep.alphas],
                                 "seconds": float(sweep.meta.get("seconds", 0.0))})
    return sweep


def refine_step(obj, settings: core.PipelineSettings, alpha: float) -> Iterator[tuple[float, str]]:
    """Exact inference at ``alpha`` (cached; what a bake at that α uses); returns ``(Prediction, how, path)``."""
    _check_object(obj)
    name = obj.name
    plan = plan_of(obj, settings)
    if plan is None:
        raise UserError(f"'{name}' has no prediction yet: run Predict first")
    with _running(obj, "predict"):
        result = yield from core.refine_job(plan, alpha)
        obj = _object(name)
        record = read_record(obj)
        entry = dict(record.get("predict") or {})
        entry["refined"] = sorted(set(entry.get("refined", [])) | {round(float(alpha), 6)})
        record.set("predict", entry)
        write_record(obj, record)
    return result


def bake_step(obj, settings: core.PipelineSettings, scene=None, **overrides) -> Iterator[tuple[float, str]]:
    """Simulate & bake with the object's bake settings (``overrides``: BakeOptions fields, e.g. ``solver``,
    ``alpha``, ``solver_settings``); the model material source carries the object's prediction (its plan,
    :func:`model_source`).  The panel's one bake (its step and *Simulate & bake*), the demo's and scripts'.
    Returns the :class:`~unipixie.core.blender_io.bake.BakeReport`."""
    from .bake import bake_steps

    _check_object(obj)
    scene = scene or bpy.context.scene
    name = obj.name
    with _running(obj, "bake"):
        fp = fingerprint(obj)
        options = bake_options(obj, scene, **overrides)
        options.material = model_source(obj, settings, options.material)
        sweep = (read_record(obj).get("predict") or {}).get("sweep", "") if options.material.kind == "model" else ""
        report = yield from bake_steps(obj, options, scene=scene)
        _store(name, "bake", {"fingerprint": fp, "sweep": sweep, "solver": options.solver, "alpha": options.alpha})
    return report


STEP_JOBS = {"render": render_step, "features": features_step, "predict": predict_step, "bake": bake_step}
STEP_WEIGHTS = {"render": 0.3, "features": 0.1, "predict": 0.3, "bake": 0.3}
"""Share of *Run all*'s progress bar per step."""


def run_all(obj, settings: core.PipelineSettings, scene=None, **bake_overrides) -> Iterator[tuple[float, str]]:
    """Every step that is not done, in order (Render views → Features → Predict → Simulate & bake);
    returns the list of steps run.  Each finished step is recorded as it ends, so Esc keeps them."""
    _check_object(obj)
    name = obj.name
    ran = []
    start = 0.0
    for step in core.STEPS:
        obj = _object(name)
        state = states(obj, settings, scene)[step]
        span = STEP_WEIGHTS[step]
        if state.state != core.DONE:
            job = (bake_step(obj, settings, scene, **bake_overrides) if step == "bake"
                   else STEP_JOBS[step](obj, settings))
            label = core.STEP_LABELS[step]
            for fraction, status in rescaled(job, start, span):
                yield fraction, f"{label}: {status}"
            ran.append(step)
        start += span
    yield 1.0, "all steps done"
    return ran


def prepare_model_material(obj, settings: core.PipelineSettings, log=print, compute: bool = True):
    """Make ``obj``'s model material available to bakes without the panel (``unipixie bake --alpha``).

    Runs whatever of Render views → Features → Predict the object lacks — the panel's own steps, with its cache and
    the feature recipe of ``settings`` (give ``settings.with_model_recipe()`` and, for a quick first bake,
    ``alphas`` = the bakes' α values) — logging each step with its time and whether it came from the cache; a
    prediction already recorded on the object and current is used as it is.  ``compute=False`` runs nothing: a
    missing or stale prediction is a :class:`UserError` naming the remedy.  Returns ``(fingerprint, plan)``: the
    object's fingerprint (for :func:`note_bake`) and its :class:`~unipixie.core.pipeline.ModelPlan` (what the
    bakes' model material source carries)."""
    import time

    _check_object(obj)
    name = obj.name
    fp = fingerprint(obj)
    st = states(obj, settings, fingerprint_value=fp)
    todo = []
    if st["predict"].state != core.DONE:
        todo.append("predict")
        if st["features"].state != core.DONE:
            todo[:0] = ["features"] if st["render"].state == core.DONE else ["render", "features"]
    if todo and not compute:
        why = "; ".join(f"{core.STEP_LABELS[k]} {st[k].label()}" for k in ("render", "features", "predict")
                        if st[k].state != core.DONE)
        raise UserError(f"object '{name}' has no current prediction to bake with at α ({why}); give --features "
                        "GRID.npz (from 'unipixie features'), run Predict in the panel and save the .blend, or drop "
                        "--no-auto to compute the missing steps now")
    if not todo:
        log(f"  {', '.join(core.STEP_LABELS[k] for k in ('render', 'features', 'predict'))}: done (recorded in the "
            "scene)")
    for step in todo:
        t0 = time.perf_counter()
        status = ""
        job = STEP_JOBS[step](_object(name), settings)
        try:
            while True:
                try:
                    _, status = next(job)
                except StopIteration:
                    break
        finally:
            job.close()
        log(f"  {core.STEP_LABELS[step]}: {status} ({time.perf_counter() - t0:.1f} s)")
    plan = plan_of(_object(name), settings)
    if plan is None:
        raise UserError(f"object '{name}': the prediction is not in the cache any more; run the bake again")
    return fp, plan


def note_bake(obj, options, fingerprint_value: str) -> None:
    """Record on ``obj`` the pipeline's bake entry of a model-material bake made outside :func:`bake_step` (the
    command line), so the panel can tell when the bake goes stale (another prediction, an edited mesh)."""
    sweep = (read_record(obj).get("predict") or {}).get("sweep", "") if options.material.kind == "model" else ""
    _store(obj.name, "bake", {"fingerprint": fingerprint_value, "sweep": sweep, "solver": options.solver,
                              "alpha": options.alpha})


def run_to_end(job, progress=None):
    """Drive a step generator to its end (command line, demo, tests); ``progress`` may cancel."""
    from ..jobs import run_job

    return run_job(job, progress)


def copy_pipeline(source, target) -> None:
    """Give ``target`` (e.g. a duplicate of ``source``) ``source``'s pipeline record, except its bake."""
    record = read_record(source)
    record.set("bake", None)
    write_record(target, record)


def objects_with_records(scene=None) -> list:
    objs = scene.objects if scene is not None else bpy.data.objects
    return [o for o in objs if core.RECORD_KEY in o.keys()]


def slices_path(obj) -> Optional[Path]:
    return read_record(obj).file("features", "slices")
