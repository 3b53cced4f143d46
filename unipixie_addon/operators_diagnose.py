"""Panel operators for measurements and diagnosis: load, compare, diagnose, add the effect found.

UI only: each operator calls :mod:`unipixie.core.measurement`, :mod:`unipixie.core.diagnosis` and
:mod:`unipixie.core.blender_io.measure`.  Settings live on the scene (``scene.unipixie_diagnosis``).

* **Load measurement** — a ``.npz`` / ``.csv`` file becomes an animated point cloud.
* **Measurement from object** — the active object's keyframed/cached motion saved as a ``.npz``.
* **Compare** — simulate the model as given (the measurement's material, the chosen solver, the
  effects already on) and colour the measurement's points (and the source object, when it has
  the same vertices) by their error: over the run, and at each frame (keyed; scrub the time
  slider).  *Colour by* switches between the two; *Clear error colours* removes both.
* **Diagnose** — the full diagnosis (ranking, significance, additions) in the background with a
  progress bar (Esc cancels); writes ``diagnosis.json``, the pictures and ``diagnosis.html``.
* **Add effect** — the identified effect (or the one picked) with its fitted parameters is added
  to the effects that are on (and to the active object's bake effects); compare again to watch
  the error fall.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..core.errors import UserError
from ..solvers import effects as _effects
from .jobs import JobOperator
from .properties import DEVICE_ITEMS, SOLVER_ITEMS

NOTE_WIDTH_CHARS = 70
"""Characters per panel line of a diagnosis note (Blender labels do not wrap)."""

ADD_ITEMS = [("AUTO", "Identified", "The best significant effect of the last diagnosis")] + [
    (name, cls.label, cls.law) for name, cls in _effects.EFFECTS.items()]


def _error_objects(settings):
    return [obj for obj in (settings.measurement_object, settings.source_object)
            if obj is not None and obj.type == "MESH"]


def _show_error(settings, context=None) -> None:
    """Make the error colours the panel asks for (at this frame / over the run) the active colour attribute."""
    from ..core.blender_io import error_animation as bea
    from ..core.blender_io import measure as bio

    name = bea.ERROR_NOW_COLOR_ATTRIBUTE if settings.error_display == "FRAME" else bio.ERROR_COLOR_ATTRIBUTE
    for obj in _error_objects(settings):
        attrs = obj.data.color_attributes
        if name in attrs:
            attrs.active_color = attrs[name]
            obj.data.update()


class UniPixieDiagnosisSettings(bpy.types.PropertyGroup):
    """Scene-level settings and results of the measurement diagnosis."""

    measurement_path: StringProperty(name="Measurement", subtype="FILE_PATH", default="",
                                     description="Measurement file (.npz unipixie.measurement/1 or .csv t,id,x,y,z)")
    measurement_object: PointerProperty(name="Point cloud", type=bpy.types.Object,
                                        description="The animated point cloud that shows the measurement")
    source_object: PointerProperty(name="Source object", type=bpy.types.Object,
                                   description="Object whose vertices are the tracked points (also coloured by error)")
    solver: EnumProperty(name="Solver", items=SOLVER_ITEMS, default="spring_mass")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="cpu")
    effects_on: StringProperty(name="Effects on", default="",
                               description="Effects already in the model, separated by ';' (e.g. linear_drag:c=0.2)")
    solver_settings: StringProperty(name="Solver settings", default="",
                                    description="key=value pairs separated by ',' (e.g. anchors=256); empty: the "
                                                "diagnosis defaults")
    candidates: StringProperty(name="Candidates", default="",
                               description="Effects to try, separated by ',' (empty: every effect of the registry)")
    out_dir: StringProperty(name="Report folder", subtype="DIR_PATH", default="//unipixie_diagnosis")
    max_additions: IntProperty(name="Max additions", default=3, min=0, max=7,
                               description="Add at most this many effects (0: only rank them)")
    keep_outliers: BoolProperty(name="Keep tracking outliers", default=False,
                                description="Keep every sample. Off (the default): samples a tracker got wrong (a "
                                            "point centimetres off its neighbours' motion for an instant or three) "
                                            "are found from the tracks and treated as not observed; the report "
                                            "lists them")
    add_effect: EnumProperty(name="Add", items=ADD_ITEMS, default="AUTO")
    rmse: FloatProperty(name="RMSE (m)", default=0.0, precision=5)
    identified: StringProperty(name="Identified", default="")
    summary: StringProperty(name="Summary", default="")
    notes: StringProperty(name="Notes", default="",
                          description="The last diagnosis's warnings and caveats, one per line (also in its report)")
    report_path: StringProperty(name="Report", default="", subtype="FILE_PATH")
    error_display: EnumProperty(
        name="Colour by", default="FRAME", update=_show_error,
        items=[("FRAME", "At this frame", "Each point's error at the current frame (keyed at every measured instant: "
                "scrub the time slider); grey where it was not observed then"),
               ("RUN", "Over the run", "Each point's RMSE over every instant it was observed")],
        description="Which error the points' colours show (Solid shading, colour 'Attribute')")
    colour_scale: StringProperty(name="Colour scale", default="",
                                 description="What the error colours mean: the error shown yellow, per object")


def _settings(context) -> UniPixieDiagnosisSettings:
    return context.scene.unipixie_diagnosis


def _effects_on(text: str) -> list:
    return [_effects.parse(s) for s in text.split(";") if s.strip()]


def _load(settings):
    from ..core.measurement import load

    if not settings.measurement_path:
        raise UserError("no measurement loaded: use 'Load measurement' first")
    return load(bpy.path.abspath(settings.measurement_path))


def _solver_settings(settings):
    """The solver settings of the panel (``anchors=256, ...``) over the diagnosis defaults for the solver."""
    from ..core.commands.diagnose import parse_settings
    from ..core.diagnosis.diagnose import diagnosis_settings

    items = [x.strip() for x in settings.solver_settings.split(",") if x.strip()]
    return diagnosis_settings(settings.solver, parse_settings(items) if items else None)


def _colour(operator, settings, comparison) -> None:
    """Colour the point cloud and the source object (where its vertices are the tracked points) by ``comparison``
    (a :class:`~unipixie.core.diagnosis.compare.Comparison`): the per-point RMSE over the run and the error at each
    measured instant, keyed for the time slider."""
    from ..core.blender_io import error_animation as bea
    from ..core.blender_io import measure as bio

    notes = []
    # the top of the run's colour scale: stated in the panel, so drawn with (the default of error_colours too)
    run_top = float(np.nanmax(comparison.per_point)) if np.isfinite(comparison.per_point).any() else 0.0
    for obj in _error_objects(settings):
        if len(obj.data.vertices) != len(comparison.per_point):
            continue
        bio.write_error_attribute(obj, comparison.per_point, vmax=run_top)
        try:
            animation = bea.write_error_animation(obj, comparison.distances, comparison.times)
            notes.append(f"{obj.name}: {animation.describe()}; over the run 0 → {1e3 * run_top:.3g} mm")
        except UserError as exc:
            operator.report({"WARNING"}, f"{obj.name}: no error at each frame ({exc})")
            notes.append(f"{obj.name}: over the run 0 → {1e3 * run_top:.3g} mm (yellow)")
    settings.colour_scale = "; ".join(notes)
    _show_error(settings)


class UNIPIXIE_OT_load_measurement(bpy.types.Operator):
    """Load a measurement file and show it as an animated point cloud"""

    bl_idname = "unipixie.load_measurement"
    bl_label = "Load measurement"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.npz;*.csv", options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from ..core.blender_io import measure as bio
        from ..core.measurement import load

        try:
            m = load(bpy.path.abspath(self.filepath))
            obj = bio.create_measurement_object(m, name=f"Measurement {Path(self.filepath).stem}",
                                                source_path=self.filepath)
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        s = _settings(context)
        s.measurement_path = self.filepath
        s.measurement_object = obj
        s.summary = m.summary()
        self.report({"INFO"}, f"loaded {m.summary()}")
        return {"FINISHED"}


class UNIPIXIE_OT_measurement_from_object(bpy.types.Operator):
    """Save the active object's motion over the scene's frame range as a measurement file"""

    bl_idname = "unipixie.measurement_from_object"
    bl_label = "Measurement from object"
    bl_options = {"REGISTER"}

    filepath: StringProperty(subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.npz", options={"HIDDEN"})

    def invoke(self, context, event):
        if not self.filepath:
            self.filepath = bpy.path.abspath("//measurement.npz") if bpy.data.filepath else "measurement.npz"
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from ..core.blender_io import measure as bio

        obj = context.active_object
        try:
            m = bio.measurement_from_object(obj, scene=context.scene)
            path = m.save(bpy.path.abspath(self.filepath))
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        s = _settings(context)
        s.measurement_path = str(path)
        s.source_object = obj
        s.summary = m.summary()
        for w in m.warnings:
            self.report({"WARNING"}, w)
        self.report({"INFO"}, f"saved {path}: {m.summary()}")
        return {"FINISHED"}


def _run_in_thread(fn, progress):
    """Run ``fn()`` (which reports to ``progress``) in a worker thread, yielding (fraction, status) until it ends;
    Esc cancels it."""
    from ..core.jobs import worker_job

    return (yield from worker_job(lambda _progress: fn(), progress=progress, idle_status="working",
                                  name="unipixie-diagnosis"))


class UNIPIXIE_OT_compare_measurement(JobOperator, bpy.types.Operator):
    """Simulate the model as given and colour the measured points by their error"""

    bl_idname = "unipixie.compare_measurement"
    bl_label = "Compare"
    bl_options = {"REGISTER"}

    def make_job(self, context):
        from ..core.diagnosis.compare import compare
        from ..core.progress import Progress
        from ..solvers import api

        s = _settings(context)
        m = _load(s)
        effects_on = _effects_on(s.effects_on)
        solver, device, settings = s.solver, s.device, _solver_settings(s)
        progress = Progress(total=1.0, show_bar=False)

        def work():
            from ..solvers.warp_runtime import resolve_device

            progress.set_status(f"preparing {solver}")
            mat = m.require_material()
            sim = api.prepare(solver, m.body(), mat.to_spec(m.rest), m.scenario, m.times - m.times[0],
                              device=resolve_device(device), settings=settings)
            progress.set_status("simulating")
            traj = sim.run(effects_on, progress=progress)
            return compare(traj.positions, m.positions, m.times, m.rest)

        result = yield from _run_in_thread(work, progress)
        return result

    def finish(self, context, result):
        s = _settings(context)
        s.rmse = result.rmse
        _colour(self, s, result)
        s.summary = result.describe().splitlines()[0]
        self.report({"INFO"}, f"RMSE {1e3 * result.rmse:.2f} mm; worst points {result.worst_points[:3]}")
        return {"FINISHED"}


class UNIPIXIE_OT_diagnose(JobOperator, bpy.types.Operator):
    """Find the physical effect the model is missing: fit every effect, test significance, add, repeat"""

    bl_idname = "unipixie.diagnose"
    bl_label = "Diagnose"
    bl_options = {"REGISTER"}

    def make_job(self, context):
        from ..core.diagnosis import diagnose
        from ..core.progress import Progress
        from ..solvers.warp_runtime import resolve_device

        s = _settings(context)
        m = _load(s)
        effects_on = _effects_on(s.effects_on)
        cands = [c.strip() for c in s.candidates.split(",") if c.strip()] or None
        out_dir = bpy.path.abspath(s.out_dir) if s.out_dir else bpy.path.abspath("//unipixie_diagnosis")
        solver, device, max_add, settings = s.solver, s.device, s.max_additions, _solver_settings(s)
        reject_outliers = not s.keep_outliers
        progress = Progress(total=100.0, show_bar=False)

        def work():
            return diagnose.diagnose(m, solver, out_dir=out_dir, effects_on=effects_on, max_additions=max_add,
                                     device=resolve_device(device), settings=settings, candidates=cands,
                                     reject_outliers=reject_outliers, progress=progress)

        result = yield from _run_in_thread(work, progress)
        return result, out_dir

    def finish(self, context, value):
        result, out_dir = value
        s = _settings(context)
        s.rmse = result.final.rmse
        s.identified = result.identified or ""
        s.report_path = str(Path(out_dir) / "diagnosis.json")
        verdict = result.verdict or {}
        explained = bool(verdict.get("explained"))
        what = result.identified or ("nothing missing" if explained else "NOT explained (no effect helps)")
        if result.identified and not explained:
            what += " (the model still does NOT explain the measurement)"
        s.summary = (f"{what}: {1e3 * result.baseline.rmse:.2f} → "
                     f"{1e3 * result.final.rmse:.2f} mm (noise {1e3 * result.noise_rmse:.2f} mm)")
        s.notes = "\n".join(result.warnings)
        _colour(self, s, result.baseline)
        for w in result.warnings:  # e.g. a predictive window, the discretisation floor, a lossy floor's caveat
            self.report({"WARNING"}, w)
        self.report({"INFO"} if explained else {"WARNING"}, s.summary)
        return {"FINISHED"}


class UNIPIXIE_OT_add_effect(bpy.types.Operator):
    """Add the identified (or chosen) effect with its fitted parameters to the model's effects"""

    bl_idname = "unipixie.add_effect"
    bl_label = "Add effect"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        from ..core.diagnosis.report import load_report

        s = _settings(context)
        try:
            if not s.report_path:
                raise UserError("no diagnosis yet: run 'Diagnose' first")
            doc = load_report(bpy.path.abspath(s.report_path))
            want = doc.get("identified") if s.add_effect == "AUTO" else s.add_effect
            if not want:
                raise UserError("the last diagnosis identified no effect; pick one to add anyway")
            cand = next((c for c in doc["candidates"] if c["effect"] == want), None)
            if cand is None:
                raise UserError(f"{want!r} was not fitted in the last diagnosis")
            spec = _effects.make(want, **cand["params"]).to_spec()
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        kept = [e for e in s.effects_on.split(";") if e.strip() and
                (e.strip().split(":")[0] != want or want == "stiffness_region")]
        s.effects_on = "; ".join(kept + [spec])
        obj = s.source_object or context.active_object
        if obj is not None and hasattr(obj, "unipixie") and hasattr(obj.unipixie, "bake_effects"):
            others = [e for e in obj.unipixie.bake_effects.split(";") if e.strip() and
                      (e.strip().split(":")[0] != want or want == "stiffness_region")]
            obj.unipixie.bake_effects = "; ".join(others + [spec])
        self.report({"INFO"}, f"added {spec}; run Compare to see the error with it")
        return {"FINISHED"}


class UNIPIXIE_OT_clear_error_colours(bpy.types.Operator):
    """Remove the error colours (over the run and at each frame, with their keys) from the point cloud and the source
    object"""

    bl_idname = "unipixie.clear_error_colours"
    bl_label = "Clear error colours"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        from ..core.blender_io import error_animation as bea
        from ..core.blender_io import measure as bio

        s = _settings(context)
        objects = _error_objects(s)
        for obj in objects:
            bio.remove_error_attribute(obj)
            bea.remove_error_animation(obj)
        s.colour_scale = ""
        self.report({"INFO"}, f"error colours removed from {len(objects)} object(s)")
        return {"FINISHED"}


class UNIPIXIE_OT_open_diagnosis_report(bpy.types.Operator):
    """Open the diagnosis report (HTML) in the web browser"""

    bl_idname = "unipixie.open_diagnosis_report"
    bl_label = "Open report"

    def execute(self, context):
        s = _settings(context)
        html = Path(bpy.path.abspath(s.report_path)).with_name("diagnosis.html") if s.report_path else None
        if html is None or not html.is_file():
            self.report({"ERROR"}, "no report yet: run 'Diagnose' first")
            return {"CANCELLED"}
        bpy.ops.wm.url_open(url=html.as_uri())
        return {"FINISHED"}


class VIEW3D_PT_unipixie_diagnose(bpy.types.Panel):
    bl_idname = "VIEW3D_PT_unipixie_diagnose"
    bl_label = "Measurements & diagnosis"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "UniPixie"
    bl_parent_id = "VIEW3D_PT_unipixie"

    def draw(self, context):
        layout = self.layout
        s = _settings(context)
        row = layout.row(align=True)
        row.operator("unipixie.load_measurement", icon="IMPORT")
        row.operator("unipixie.measurement_from_object", icon="EXPORT")
        if s.measurement_path:
            layout.label(text=bpy.path.basename(s.measurement_path), icon="FILE")
        layout.prop(s, "source_object")
        row = layout.row()
        row.prop(s, "solver", expand=True)
        layout.prop(s, "device")
        layout.prop(s, "solver_settings")
        layout.prop(s, "effects_on")
        layout.operator("unipixie.compare_measurement", icon="DRIVER_DISTANCE")
        if s.colour_scale:
            row = layout.row(align=True)
            row.prop(s, "error_display", expand=True)
            row.operator("unipixie.clear_error_colours", text="", icon="X")
            col = layout.column(align=True)
            for i, line in enumerate(textwrap.wrap(s.colour_scale, NOTE_WIDTH_CHARS)):
                col.label(text=line, icon="COLOR" if i == 0 else "BLANK1")
        box = layout.box()
        box.prop(s, "out_dir")
        box.prop(s, "candidates")
        box.prop(s, "max_additions")
        box.prop(s, "keep_outliers")
        box.operator("unipixie.diagnose", icon="VIEWZOOM")
        if s.summary:
            layout.label(text=s.summary)
        for note in filter(None, s.notes.split("\n")):
            col = layout.column(align=True)
            for i, line in enumerate(textwrap.wrap(note, NOTE_WIDTH_CHARS)):
                col.label(text=line, icon="INFO" if i == 0 else "BLANK1")
        row = layout.row(align=True)
        row.prop(s, "add_effect", text="")
        row.operator("unipixie.add_effect", icon="ADD")
        layout.operator("unipixie.open_diagnosis_report", icon="URL")


CLASSES = (UniPixieDiagnosisSettings, UNIPIXIE_OT_load_measurement, UNIPIXIE_OT_measurement_from_object,
           UNIPIXIE_OT_compare_measurement, UNIPIXIE_OT_diagnose, UNIPIXIE_OT_add_effect,
           UNIPIXIE_OT_clear_error_colours, UNIPIXIE_OT_open_diagnosis_report, VIEW3D_PT_unipixie_diagnose)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    bpy.types.Scene.unipixie_diagnosis = PointerProperty(type=UniPixieDiagnosisSettings)


def unregister():
    if hasattr(bpy.types.Scene, "unipixie_diagnosis"):
        del bpy.types.Scene.unipixie_diagnosis
    _unregister_classes()
