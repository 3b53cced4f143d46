"""The panel's pipeline operators and the handlers that keep every object's step states current.

Operators (all on the active object, as modal jobs: progress bar, status text, **Esc** cancels,
errors as reports and in the panel):

* ``unipixie.pipeline_step`` (``step`` = render / features / predict / bake) — one step of
  :mod:`unipixie.core.blender_io.pipeline`.  Predict makes the model the bake's material source.  Its bake is
  :class:`BakeJob`, the one bake of the panel: the *Simulate & bake* sub-panel's ``unipixie.bake``
  (:mod:`.operators_bake`) runs the same job.
* ``unipixie.run_all`` — every step that is not done, in order, as one job.
* ``unipixie.refine_alpha`` — exact inference at the slider's α (cached; the bake at that α uses it).
* ``unipixie.toggle_field`` — the material field over the object, coloured by log E, with a legend.
* ``unipixie.refresh_pipeline`` — recompute the step states (the handlers do this on their own after
  edits, undo and file loads; in background mode, where timers do not run, call it).

State lives on the object: the pipeline record (an ID property, saved and undone with the object) and
the panel's ``obj.unipixie.state_<step>`` / ``reason_<step>`` strings, written by
:func:`refresh_object` — the one place that writes them, never ``draw()`` — after a step, an edit (the depsgraph
handler, 0.4 s later), undo, a file load, and once the α slider has come to rest (:func:`on_alpha_changed`).
"""

from __future__ import annotations

import time

import bpy
from bpy.app.handlers import persistent

from ..core import extractors
from ..core import pipeline as core
from ..core.blender_io import field_view
from ..core.blender_io import pipeline as pio
from ..core.errors import UserError
from .jobs import JobOperator
from .preferences import get_preferences, store_extractor_info

STEP_ITEMS = [(k, core.STEP_LABELS[k], f"Run the step '{core.STEP_LABELS[k]}' on the active object") for k in core.STEPS]
STEP_DESCRIPTIONS = {
    "render": "Render the object's views (normalised into the unit cube) into the cache",
    "features": "Extract dense features from the views and lift them into the 64³ voxel grid",
    "predict": "Run the model on the feature grid at the α sweep's values (default 11) and cache the sweep",
    "bake": "Simulate the object with the chosen solver and effects at α and bake the motion into keyframes",
}
REFRESH_DELAY = 0.4
"""Seconds after the last edit before the step states are recomputed (edits come in bursts)."""

_FINGERPRINTS: dict = {}
"""Object name → its last fingerprint (reused when only settings changed)."""
_PENDING: set = set()
_REFRESHING = [False]
_QUIET: set = set()
"""Objects whose next depsgraph update comes from one of UniPixie's own settings (a property with an update
callback, such as α, tags the object for re-evaluation), not from an edit: their state is already current."""
SETTLE_DELAY = 0.3
"""Seconds the α slider must rest before the step states follow it (a drag moves it once per mouse event)."""
_SETTLING: dict = {}
"""Object name → when (``time.monotonic()``) its α last moved, until its states are refreshed."""
_SWEEPS: dict = {}
"""Object name → its α sweep file (or ``None``) as of its last :func:`refresh_object`: the slider's summary line
reads the cached sweep without reading the record."""


# --------------------------------------------------------------------------- settings and state
def pipeline_settings(context, obj=None) -> core.PipelineSettings:
    """The pipeline settings from the add-on preferences (views, CLIP weights, checkpoint, device of the
    model and feature extraction; the object's own *Device* is where it is simulated)."""
    prefs = get_preferences(context)
    return core.PipelineSettings(
        view_count=int(prefs.default_view_count),
        clip_weights=bpy.path.abspath(prefs.clip_weights) if prefs.clip_weights else "",
        checkpoint=bpy.path.abspath(prefs.checkpoint) if prefs.checkpoint else "",
        device=str(prefs.device)).with_model_recipe()


def _set(group, name: str, value) -> None:
    if getattr(group, name) != value:        # unchanged values are not written (no needless updates)
        setattr(group, name, value)


def _valid(obj) -> bool:
    try:
        return obj is not None and obj.name in bpy.data.objects and hasattr(obj, "unipixie")
    except ReferenceError:
        return False


def refresh_object(obj, context=None, geometry: bool = True) -> dict:
    """Recompute ``obj``'s step states into ``obj.unipixie.state_<step>`` / ``reason_<step>`` and update the
    field summary.  ``geometry=False`` reuses the last
    fingerprint (for setting changes such as α).  Returns ``{step: StepState}``."""
    if not _valid(obj):
        return {}
    context = context or bpy.context
    _SETTLING.pop(obj.name, None)
    _REFRESHING[0] = True
    try:
        settings = pipeline_settings(context, obj)
        fp = None if geometry else _FINGERPRINTS.get(obj.name)
        if fp is None:
            try:
                fp = pio.fingerprint(obj)
                _FINGERPRINTS[obj.name] = fp
            except UserError:
                fp = None
        states = pio.states(obj, settings, context.scene, fingerprint_value=fp)
        s = obj.unipixie
        for step, st in states.items():
            _set(s, f"state_{step}", st.state)
            _set(s, f"reason_{step}", st.reason)
        _SWEEPS[obj.name] = pio.read_record(obj).file("predict", "sweep")
        _set(s, "field_summary", _summary(obj))
        if s.show_field and field_view.field_object(obj) is None:
            _set(s, "show_field", False)
        return states
    finally:
        _REFRESHING[0] = False


def refresh_all(context=None, geometry: bool = True) -> None:
    for obj in pio.objects_with_records():
        refresh_object(obj, context, geometry)


def _summary(obj) -> str:
    """The panel's one line on E at the object's α, from its cached sweep (``""`` without a prediction)."""
    if obj.name not in _SWEEPS:             # not refreshed yet in this session: read the record once
        _SWEEPS[obj.name] = pio.read_record(obj).file("predict", "sweep")
    path = _SWEEPS[obj.name]
    if path is None:
        return ""
    try:
        return core.field_summary(core.load_sweep(path), obj.unipixie.alpha)
    except UserError as exc:
        return str(exc)


def on_alpha_changed(obj, context) -> None:
    """The α slider moved: recolour the field display and the summary line from the cached sweep — nothing else.

    A drag calls this once per mouse event and Blender has no "released" event for a property, so the step
    states (which read the record and the bake's settings and record) are not refreshed here.  The move is noted
    (``_SETTLING``) and a timer, :func:`_refresh_settled`, hands the object to :func:`refresh_object` once α has
    rested :data:`SETTLE_DELAY` seconds: one refresh per drag, from the one place that writes the states.  A step
    run, undo and a file load refresh them too; the bake itself always reads α afresh.  In background mode, where
    timers do not run, :func:`settle_alpha` (or *Refresh states*) does what the timer does."""
    if not _valid(obj):
        return
    _QUIET.add(obj.name)
    s = obj.unipixie
    if s.show_field:
        try:
            field_view.recolour(obj, s.alpha)
        except UserError as exc:
            s.last_error = str(exc)
    _set(s, "field_summary", _summary(obj))
    if pio.has_record(obj) or s.state_bake != core.NOT_DONE:
        _SETTLING[obj.name] = time.monotonic()
        if not bpy.app.timers.is_registered(_refresh_settled):
            bpy.app.timers.register(_refresh_settled, first_interval=SETTLE_DELAY)


def settle_alpha(names=None) -> None:
    """Refresh now the states of the objects whose α moved (``names``; default: all still waiting)."""
    for name in list(_SETTLING) if names is None else names:
        _SETTLING.pop(name, None)
        obj = bpy.data.objects.get(name)
        if obj is not None:
            try:
                refresh_object(obj, geometry=False)
            except Exception as exc:  # a timer must never break Blender
                print(f"UniPixie: could not refresh the state of '{name}': {exc}")


def _refresh_settled():
    """The slider's timer: settle the objects whose α has rested :data:`SETTLE_DELAY` s; come back for the others
    (returns the seconds until the next one is due, or ``None`` when none is left)."""
    now = time.monotonic()
    settle_alpha([name for name, moved in _SETTLING.items() if now - moved >= SETTLE_DELAY])
    if not _SETTLING:
        return None
    return max(0.01, SETTLE_DELAY - (now - min(_SETTLING.values())))


def on_settings_changed(obj, context) -> None:
    """A bake setting changed (solver, frames, effects, material source, device): update the bake's state."""
    if _valid(obj):
        _QUIET.add(obj.name)
        if pio.has_record(obj) or obj.unipixie.state_bake != core.NOT_DONE:
            refresh_object(obj, context, geometry=False)


def _mark_running(obj, step: str) -> None:
    _set(obj.unipixie, f"state_{step}", core.RUNNING)
    _set(obj.unipixie, f"reason_{step}", "")


def _after_job(name: str, context) -> None:
    obj = bpy.data.objects.get(name)
    if obj is not None:
        try:
            refresh_object(obj, context)
        except Exception as exc:  # the job's own outcome (report) matters more than the panel's state
            print(f"UniPixie: could not refresh the state of '{name}': {exc}")


def _use_model_material(op, obj) -> None:
    if obj.unipixie.bake_material_source != "model":
        obj.unipixie.bake_material_source = "model"
        op.report({"INFO"}, "Simulate & bake now uses the model's material at α")


def _redraw(context) -> None:
    screen = getattr(context, "screen", None)
    for area in (screen.areas if screen is not None else []):
        if area.type == "VIEW_3D":
            area.tag_redraw()


# --------------------------------------------------------------------------- operators
def _poll(context) -> bool:
    from ..core.blender_io.scene_import import GEOMETRY_TYPES

    obj = getattr(context, "active_object", None)
    return obj is not None and obj.type in GEOMETRY_TYPES and obj.mode == "OBJECT"


class _ObjectJob(JobOperator):
    """A job on the active object, remembered by name (the selection may change while it runs)."""

    _object_name = ""

    @classmethod
    def poll(cls, context):
        return _poll(context)

    def job_target(self, context):
        return bpy.data.objects.get(self._object_name) or getattr(context, "active_object", None)

    def _begin(self, context, step: str):
        obj = context.active_object
        if obj is None:
            raise UserError("no object selected: select the mesh object to work on")
        self._object_name = obj.name
        if step:
            _mark_running(obj, step)
        return obj, pipeline_settings(context, obj)

    def on_cancel(self, context):
        obj = bpy.data.objects.get(self._object_name)
        if obj is not None:
            obj.unipixie.status = "cancelled: nothing of the cancelled step was kept"
        _after_job(self._object_name, context)


class BakeJob(_ObjectJob):
    """The panel's one bake job: :func:`unipixie.core.blender_io.pipeline.bake_step` on the active object — its
    bake settings, and when its material source is the model, its own prediction at α (the source carries the
    object's plan).  Progress, Esc (nothing half-written is kept) and undo as every job; the pipeline step
    ``bake`` and ``unipixie.bake`` both run it."""

    def bake_job(self, context, **overrides):
        obj, settings = self._begin(context, "bake")
        try:
            report = yield from pio.bake_step(obj, settings, context.scene, **overrides)
        finally:
            _after_job(self._object_name, context)
        return report

    def finish_bake(self, context, report):
        for note in report.notes:
            self.report({"WARNING"}, note)
        self.report({"INFO"}, report.summary())      # the object's status is the bake's ("baked: …")
        _redraw(context)
        return {"FINISHED"}

    def on_cancel(self, context):
        obj = bpy.data.objects.get(self._object_name)
        if obj is not None:
            obj.unipixie.status = "bake cancelled: nothing was written"
        _after_job(self._object_name, context)


class UNIPIXIE_OT_pipeline_step(BakeJob, bpy.types.Operator):
    """Run one step of the UniPixie pipeline on the active object"""

    bl_idname = "unipixie.pipeline_step"
    bl_label = "UniPixie step"
    bl_options = {"REGISTER", "UNDO"}

    step: bpy.props.EnumProperty(name="Step", items=STEP_ITEMS, default="render")

    @classmethod
    def description(cls, context, properties):
        return STEP_DESCRIPTIONS[properties.step]

    def make_job(self, context):
        if self.step == "bake":
            return (yield from self.bake_job(context))
        obj, settings = self._begin(context, self.step)
        try:
            result = yield from pio.STEP_JOBS[self.step](obj, settings)
        finally:
            _after_job(self._object_name, context)
        return result

    def on_cancel(self, context):
        (BakeJob if self.step == "bake" else _ObjectJob).on_cancel(self, context)

    def finish(self, context, result):
        if self.step == "bake":
            return self.finish_bake(context, result)
        obj = bpy.data.objects.get(self._object_name)
        if self.step == "render":
            msg = f"views of '{self._object_name}' in {result}"
        elif self.step == "features":
            g = result.grid
            msg = (f"{int(g.occupancy.sum())} voxels, D = {g.dim}, {extractors.label(g.feature_model)}"
                   + (" (from the cache)" if result.cache_hit else ""))
            for w in result.warnings:
                self.report({"WARNING"}, w)
        elif self.step == "predict":
            msg = f"α sweep of {len(result.alphas)} values ({', '.join(core.sweep_heads(result))})"
            if obj is not None:
                _use_model_material(self, obj)
                if obj.unipixie.show_field:
                    sweep = pio.read_record(obj).file("predict", "sweep")
                    field_view.show_field(obj, sweep, obj.unipixie.alpha)
                refresh_object(obj, context, geometry=False)
        if obj is not None:
            obj.unipixie.status = f"{core.STEP_LABELS[self.step]}: done"
        self.report({"INFO"}, msg)
        _redraw(context)
        return {"FINISHED"}


class UNIPIXIE_OT_run_all(_ObjectJob, bpy.types.Operator):
    """Run every step that is not done yet, in order: Render views → Features → Predict → Simulate & bake"""

    bl_idname = "unipixie.run_all"
    bl_label = "Run all"
    bl_options = {"REGISTER", "UNDO"}

    def make_job(self, context):
        obj, settings = self._begin(context, "")
        _use_model_material(self, obj)
        try:
            ran = yield from pio.run_all(obj, settings, context.scene)
        finally:
            _after_job(self._object_name, context)
        return ran

    def finish(self, context, ran):
        obj = bpy.data.objects.get(self._object_name)
        if obj is not None:
            obj.unipixie.status = "all steps done"
            if obj.unipixie.show_field:
                field_view.show_field(obj, pio.read_record(obj).file("predict", "sweep"), obj.unipixie.alpha)
        labels = ", ".join(core.STEP_LABELS[s] for s in ran) or "nothing (every step was done)"
        self.report({"INFO"}, f"ran {labels}")
        _redraw(context)
        return {"FINISHED"}


class UNIPIXIE_OT_refine_alpha(_ObjectJob, bpy.types.Operator):
    """Exact inference at the slider's α (the α sweep is interpolated between its values); cached, and used by
    Simulate & bake at this α"""

    bl_idname = "unipixie.refine_alpha"
    bl_label = "Refine at this α"
    bl_options = {"REGISTER"}

    def make_job(self, context):
        obj, settings = self._begin(context, "predict")
        self._alpha = float(obj.unipixie.alpha)
        try:
            result = yield from pio.refine_step(obj, settings, self._alpha)
        finally:
            _after_job(self._object_name, context)
        return result

    def finish(self, context, result):
        import numpy as np

        pred, how, _path = result
        obj = bpy.data.objects.get(self._object_name)
        if obj is not None and pred.mpm is not None and obj.unipixie.show_field and abs(obj.unipixie.alpha - self._alpha) < 1e-9:
            field_view.colour_by(obj, np.log10(pred.mpm[0].E))
        self.report({"INFO"}, f"exact prediction at α = {self._alpha:.3g} ({how})")
        _redraw(context)
        return {"FINISHED"}


class UNIPIXIE_OT_toggle_field(bpy.types.Operator):
    """Show or hide the model's material field over the active object, coloured by log E, with a legend"""

    bl_idname = "unipixie.toggle_field"
    bl_label = "Material field"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _poll(context)

    def execute(self, context):
        obj = context.active_object
        s = obj.unipixie
        if field_view.field_object(obj) is not None:
            field_view.hide_field(obj)
            s.show_field = False
            return {"FINISHED"}
        sweep = pio.read_record(obj).file("predict", "sweep")
        if sweep is None:
            self.report({"ERROR"}, f"'{obj.name}' has no prediction to show: run Predict first")
            return {"CANCELLED"}
        try:
            field_view.show_field(obj, sweep, s.alpha)
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            s.last_error = str(exc)
            return {"CANCELLED"}
        s.show_field = True
        screen = getattr(context, "screen", None)
        for area in (screen.areas if screen is not None else []):
            if area.type == "VIEW_3D":
                for space in area.spaces:
                    if space.type == "VIEW_3D" and space.shading.type == "SOLID":
                        space.shading.color_type = "VERTEX"     # solid mode shows the active colour attribute
                area.tag_redraw()
        return {"FINISHED"}


class UNIPIXIE_OT_refresh_pipeline(bpy.types.Operator):
    """Recompute the pipeline states (done / stale / not done) of the active object, or of all objects"""

    bl_idname = "unipixie.refresh_pipeline"
    bl_label = "Refresh states"
    bl_options = {"REGISTER"}

    all_objects: bpy.props.BoolProperty(name="All objects", default=False)

    def execute(self, context):
        if self.all_objects:
            refresh_all(context)
        else:
            obj = context.active_object
            if obj is None:
                self.report({"ERROR"}, "no object selected")
                return {"CANCELLED"}
            refresh_object(obj, context)
        _redraw(context)
        return {"FINISHED"}


CLASSES = (UNIPIXIE_OT_pipeline_step, UNIPIXIE_OT_run_all, UNIPIXIE_OT_refine_alpha, UNIPIXIE_OT_toggle_field,
           UNIPIXIE_OT_refresh_pipeline)


# --------------------------------------------------------------------------- handlers
def _refresh_pending():
    names = list(_PENDING)
    _PENDING.clear()
    for name in names:
        obj = bpy.data.objects.get(name)
        if obj is not None:
            try:
                refresh_object(obj)
            except Exception as exc:  # a handler must never break Blender
                print(f"UniPixie: could not refresh the state of '{name}': {exc}")
    return None


@persistent
def _on_depsgraph(scene, depsgraph):
    """Edits of a pipeline object's mesh, modifiers, transform or of materials: refresh its states soon."""
    if pio.muting() or _REFRESHING[0]:
        return
    names = set()
    shading = False
    for update in depsgraph.updates:
        idb = update.id
        if isinstance(idb, bpy.types.Object):
            orig = idb.original
            if orig.name in _QUIET:          # a UniPixie setting changed, not the object
                _QUIET.discard(orig.name)
                continue
            if (update.is_updated_geometry or update.is_updated_transform) and core.RECORD_KEY in orig.keys():
                names.add(orig.name)
        elif isinstance(idb, (bpy.types.Material, bpy.types.Image, bpy.types.NodeTree)):
            shading = True
    if shading:
        names |= {o.name for o in pio.objects_with_records()}
    if names:
        _PENDING.update(names)
        if not bpy.app.timers.is_registered(_refresh_pending):
            bpy.app.timers.register(_refresh_pending, first_interval=REFRESH_DELAY)


@persistent
def _on_load(*_args):
    _FINGERPRINTS.clear()
    _SWEEPS.clear()
    _SETTLING.clear()
    try:
        bpy.context.window_manager.unipixie_cuda_available = core.cuda_device_count() > 0
        store_extractor_info(bpy.context)
        refresh_all()
    except Exception as exc:  # a handler must never break loading a file
        print(f"UniPixie: could not refresh pipeline states after loading: {exc}")


@persistent
def _on_undo(*_args):
    _SWEEPS.clear()
    try:
        refresh_all(geometry=True)
    except Exception as exc:
        print(f"UniPixie: could not refresh pipeline states after undo: {exc}")


_HANDLERS = ((bpy.app.handlers.depsgraph_update_post, _on_depsgraph), (bpy.app.handlers.load_post, _on_load),
             (bpy.app.handlers.undo_post, _on_undo), (bpy.app.handlers.redo_post, _on_undo))


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    for handlers, fn in _HANDLERS:
        if fn not in handlers:
            handlers.append(fn)
    try:
        bpy.context.window_manager.unipixie_cuda_available = core.cuda_device_count() > 0
        store_extractor_info(bpy.context)
    except AttributeError:  # no window manager yet (registration at start-up): the load handler sets it
        pass


def unregister():
    for handlers, fn in _HANDLERS:
        if fn in handlers:
            handlers.remove(fn)
    for timer in (_refresh_pending, _refresh_settled):
        if bpy.app.timers.is_registered(timer):
            bpy.app.timers.unregister(timer)
    _PENDING.clear()
    _SETTLING.clear()
    _SWEEPS.clear()
    _FINGERPRINTS.clear()
    _unregister_classes()
