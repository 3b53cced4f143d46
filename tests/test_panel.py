"""The artist's panel through real bpy: every operator in order, the α slider and its legend, stale states,
several objects, save and reopen, undo, errors, Esc, the preference checks, and the panel's draw()."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

pytestmark = pytest.mark.blender


@pytest.fixture
def panel(blender, tiny_checkpoint, monkeypatch):
    """bpy with the add-on, preferences pointing at the tiny model and 4 views."""
    from unipixie.unipixie_addon import preferences

    monkeypatch.setattr(preferences._Defaults, "checkpoint", str(tiny_checkpoint))
    monkeypatch.setattr(preferences._Defaults, "default_view_count", 4)
    return blender


def _rod(bpy, name="Rod", location=(0.0, 0.0, 0.3)):
    """A small cylinder (≈18k voxels of the 64³ grid once normalised)."""
    bpy.ops.mesh.primitive_cylinder_add(vertices=12, radius=0.03, depth=0.2, location=location)
    obj = bpy.context.active_object
    obj.name = name
    return obj


def _states(obj):
    return [getattr(obj.unipixie, f"state_{s}") for s in ("render", "features", "predict", "bake")]


def _record(obj):
    from unipixie.core.blender_io import pipeline as pio

    return pio.read_record(obj)


def _activate(bpy, obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)


def _ball(radius: float = 0.305):
    """(64, 64, 64) occupancy of a ball in the model's unit-cube grid (radius 0.305: ~31k voxels)."""
    from unipixie.core.normalise import unit_cube_grid

    R = unit_cube_grid().resolution
    c = (np.stack(np.meshgrid(*[np.arange(R)] * 3, indexing="ij"), -1) + 0.5) / R - 0.5
    return np.sum(c ** 2, axis=-1) < radius ** 2


def _show_sweep(bpy, obj, path, occ, logE):
    """Record on ``obj`` an α sweep at 11 α values (``logE``: (11, K) log10 E over ``occ``, saved to ``path``) as its
    prediction and show its field; returns the sweep."""
    from unipixie.core import pipeline as core
    from unipixie.core.blender_io import pipeline as pio
    from unipixie.core.model.sweep import AlphaSweep
    from unipixie.core.normalise import unit_cube_grid

    sweep = AlphaSweep(np.linspace(0, 1, 11), unit_cube_grid(), occ, log10_E=logE,
                       log10_density=np.full_like(logE, 3.0), nu=np.full_like(logE, 0.3),
                       material=np.zeros(logE.shape, np.int16))
    rec = core.PipelineRecord()
    rec.set("predict", {"inputs": {}, "sweep": str(sweep.save(path))})
    pio.write_record(obj, rec)
    assert bpy.ops.unipixie.toggle_field() == {"FINISHED"}
    return sweep


def _draw_calls(bpy) -> list:
    """The main panel's draw() through a stand-in layout that records ("prop" | "operator" | "label", name)
    and checks every property and operator it is given exists."""
    from unipixie.unipixie_addon.panels import VIEW3D_PT_unipixie

    calls = []

    class Layout:
        def __getattr__(self, name):
            if name in ("row", "column", "box"):
                return lambda *a, **k: self
            raise AttributeError(name)

        def prop(self, data, name, **kw):
            assert name in data.bl_rna.properties, name
            calls.append(("prop", name))

        def operator(self, idname, **kw):
            mod, op = idname.split(".")
            assert hasattr(getattr(bpy.ops, mod), op), idname
            calls.append(("operator", idname))
            return SimpleNamespace()

        def label(self, text="", **kw):
            calls.append(("label", text))

    VIEW3D_PT_unipixie.draw(SimpleNamespace(layout=Layout()), bpy.context)
    return calls


# --------------------------------------------------------------------------- the whole panel, in order
def test_every_panel_operator_in_order_leaves_its_data(panel):
    bpy = panel
    from unipixie.core import pipeline as core
    from unipixie.core.blender_io import bake as bio
    from unipixie.core.blender_io import field_view
    from unipixie.core.blender_io import pipeline as pio
    from unipixie.unipixie_addon.operators_pipeline import pipeline_settings

    bpy.ops.mesh.primitive_plane_add(size=2.0)
    ground = bpy.context.active_object
    obj = _rod(bpy)
    s = obj.unipixie
    assert _states(obj) == ["not done"] * 4

    assert bpy.ops.unipixie.pipeline_step(step="render") == {"FINISHED"}
    rec = _record(obj)
    assert rec.file("render", "views") is not None and rec.file("render", "sheet") is not None
    assert rec.get("render")["count"] == 4 and _states(obj)[0] == "done"

    assert bpy.ops.unipixie.pipeline_step(step="features") == {"FINISHED"}
    rec = _record(obj)
    assert rec.file("features", "grid") is not None and rec.file("features", "slices") is not None
    assert obj.unipixie_features.grid_path == rec.get("features")["grid"]
    assert rec.get("features")["feature_model"] == "offline-random-vit-w32" and _states(obj)[:2] == ["done"] * 2

    assert bpy.ops.unipixie.pipeline_step(step="predict") == {"FINISHED"}
    rec = _record(obj)
    assert rec.file("predict", "sweep") is not None and len(rec.get("predict")["alphas"]) == 11
    assert s.bake_material_source == "model" and s.field_summary.startswith("E at α 0.50: median")
    assert _states(obj) == ["done", "done", "done", "not done"]

    assert bpy.ops.unipixie.toggle_field() == {"FINISHED"}
    field = field_view.field_object(obj)
    assert s.show_field and field is not None and field.parent == obj
    assert field_view.COLOUR_ATTRIBUTE in field.data.color_attributes
    assert field_view.VOXEL_ATTRIBUTE in field.data.attributes
    bar, labels = field_view.legend_objects(obj)
    assert bar is not None and len(labels) == field_view.LEGEND_TICKS + 1

    s.alpha = 0.37
    assert bpy.ops.unipixie.refine_alpha() == {"FINISHED"}
    plan = pio.plan_of(obj, pipeline_settings(bpy.context, obj))
    assert core.refined_path(plan, 0.37, ("mpm", "lbs", "spring_mass")).is_file()

    s.solver = "spring_mass"
    s.use_bake_frame_range, s.bake_frame_start, s.bake_frame_end = True, 1, 8
    s.bake_ground = ground
    s.effects.linear_drag.use = True
    s.effects.linear_drag.c = 0.25
    assert s.bake_effects == "linear_drag:c=0.25"
    assert bpy.ops.unipixie.pipeline_step(step="bake") == {"FINISHED"}
    brec = bio.bake_record(obj)
    assert brec["mode"] == "shape_keys" and obj.data.shape_keys is not None
    assert brec["alpha"] == pytest.approx(0.37) and "refined" in brec["material"]
    assert brec["effects"] == [{"effect": "linear_drag", "params": {"c": 0.25}}]
    fall = bio.evaluated_positions(obj, 8)[:, 2].mean() - bio.evaluated_positions(obj, 1)[:, 2].mean()
    assert fall < -0.01                                        # it falls under gravity
    assert _states(obj) == ["done"] * 4

    # the baked object's features stay done (the fingerprint mutes the bake); α moved: only the bake is stale
    bpy.ops.unipixie.refresh_pipeline()
    assert _states(obj) == ["done"] * 4
    s.alpha = 0.65
    from unipixie.unipixie_addon import operators_pipeline as ops

    ops.settle_alpha()                                         # what the timer does once the slider rests
    assert _states(obj) == ["done", "done", "done", "stale"] and s.reason_bake == "α changed"
    assert bpy.ops.unipixie.run_all() == {"FINISHED"}        # runs only what is not done: the bake
    assert _states(obj) == ["done"] * 4 and bio.bake_record(obj)["alpha"] == pytest.approx(0.65)
    assert "exact inference" in bio.bake_record(obj)["material"]


def test_run_all_from_nothing_and_draw(panel):
    bpy = panel
    from unipixie.core.blender_io import bake as bio

    obj = _rod(bpy, "Fresh")
    s = obj.unipixie
    s.solver, s.use_bake_frame_range, s.bake_frame_end = "spring_mass", True, 5
    assert bpy.ops.unipixie.run_all() == {"FINISHED"}
    assert _states(obj) == ["done"] * 4 and bio.bake_record(obj)["material_source"] == {"source": "model"}

    # draw() lays out existing properties and operators only (recorded by a stand-in layout)
    calls = _draw_calls(bpy)
    labels = [c[1] for c in calls if c[0] == "label"]
    assert labels.count("done") == 4
    assert ("operator", "unipixie.run_all") in calls and ("prop", "alpha") in calls
    assert ("prop", "use") in calls and ("prop", "bake_frame_end") in calls
    assert ("prop", "device") in calls or "Device: CPU (no CUDA GPU found)" in labels


# --------------------------------------------------------------------------- the α slider
def test_panel_states_the_chosen_solvers_measured_floor(panel):
    bpy = panel
    from unipixie.core.solver_fidelity import floor_lines

    obj = _rod(bpy, "Floor")
    _activate(bpy, obj)
    shown = {}
    for solver in ("lbs", "spring_mass", "mpm"):
        obj.unipixie.solver = solver
        labels = [c[1] for c in _draw_calls(bpy) if c[0] == "label"]
        shown[solver] = [t.strip() for t in labels if t.strip() in floor_lines(solver)]
        assert shown[solver] == floor_lines(solver), solver
    # the measured figures of benchmarks/fidelity.json (LBS's drop rebound, +11 % at its former 5 ms step, is +1.4 %
    # at 2.5 ms and no longer stated)
    assert "static bending sag -19 %" in shown["lbs"] and "ground contact time +9 %" in shown["lbs"]
    assert not any("rebound" in line for line in shown["lbs"])


def test_alpha_slider_recolours_from_the_sweep_in_under_50_ms_with_a_monotone_legend(panel, tmp_path):
    bpy = panel
    from unipixie.core import pipeline as core
    from unipixie.core.blender_io import field_view

    # a realistic voxel count: a ball of ~31k voxels; log10 E rises with α (and varies over the voxels)
    occ = _ball()
    K = int(occ.sum())
    assert 28_000 < K < 34_000
    alphas = np.linspace(0, 1, 11)
    spread = np.random.default_rng(0).uniform(-0.3, 0.3, K)
    logE = (4.5 + 2.0 * alphas[:, None] + spread[None, :]).astype(np.float32)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    sweep = _show_sweep(bpy, obj, tmp_path / "sweep.npz", occ, logE)

    def mean_luminance():
        col = field_view.corner_colours(obj)
        return float((col[:, :3] @ np.array([0.2126, 0.7152, 0.0722])).mean())

    obj.unipixie.alpha = 0.0                       # warm-up (first call reads the field's voxel map)
    times, lum = [], []
    for a in (0.05, 0.23, 0.5, 0.77, 1.0):
        t = time.perf_counter()
        obj.unipixie.alpha = a                     # the slider: update callback → recolour from the cache
        times.append(time.perf_counter() - t)
        lum.append(mean_luminance())
    assert max(times) < 0.050, f"recolouring took {1e3 * max(times):.1f} ms for {K} voxels"
    assert np.all(np.diff(lum) > 0)                # stiffer α, brighter field (viridis)
    # the colours are the sweep's values at α through the legend's scale
    scale = core.FieldColourScale.of_sweep(sweep)
    _, corner_voxel, _ = field_view._entry(field_view.field_object(obj))
    expect = scale.colours_linear(sweep.values_at("log10_E", 1.0))[corner_voxel]
    np.testing.assert_allclose(field_view.corner_colours(obj), expect, atol=1e-6)

    # legend: colour bar bottom → top gets brighter; labels are the scale's ticks, increasing
    bar = field_view.legend_colours(obj)
    assert bar.shape == (field_view.LEGEND_SEGMENTS, 4)
    assert np.all(np.diff(bar[:, :3] @ np.array([0.2126, 0.7152, 0.0722])) > 0)
    _, labels = field_view.legend_objects(obj)
    ticks = [o.data.body for o in labels if o["unipixie_tick"] >= 0]
    assert ticks == [t[2] for t in scale.ticks(field_view.LEGEND_TICKS)]
    values = [t[1] for t in scale.ticks(field_view.LEGEND_TICKS)]
    assert np.all(np.diff(values) > 0)
    assert values[0] == pytest.approx(10 ** 4.2, rel=1e-3) and values[-1] == pytest.approx(10 ** 6.8, rel=1e-3)

    # hiding removes the display and leaves the object alone
    n_before = len(obj.data.vertices)
    assert bpy.ops.unipixie.toggle_field() == {"FINISHED"}
    assert field_view.display_objects(obj) == [] and not obj.unipixie.show_field
    assert len(obj.data.vertices) == n_before and len(obj.data.color_attributes) == 0


# --------------------------------------------------------------------------- stale states, several objects
def test_edits_make_steps_stale_and_objects_keep_their_own_state(panel, monkeypatch):
    bpy = panel
    from unipixie.unipixie_addon import preferences

    a = _rod(bpy, "A")
    bpy.ops.mesh.primitive_cube_add(size=0.1, location=(1.0, 0.0, 0.2))
    b = bpy.context.active_object
    _activate(bpy, a)
    assert bpy.ops.unipixie.pipeline_step(step="features") == {"FINISHED"}
    bpy.ops.unipixie.refresh_pipeline(all_objects=True)
    assert _states(a)[:2] == ["done", "done"]
    assert _states(b) == ["not done"] * 4 and "features" not in _record(b).steps

    # moving or scaling the object uniformly changes nothing the features depend on
    a.location.x += 0.7
    a.scale = (2.0, 2.0, 2.0)
    bpy.ops.unipixie.refresh_pipeline(all_objects=True)
    assert _states(a)[:2] == ["done", "done"]

    # editing the mesh does; the depsgraph handler notices the edit (and not a change of α) and refreshes
    from unipixie.unipixie_addon import operators_pipeline as ops

    bpy.context.view_layer.update()
    ops._PENDING.clear()
    a.unipixie.alpha = 0.3
    bpy.context.view_layer.update()
    assert "A" not in ops._PENDING
    a.data.vertices[0].co.z += 0.05
    a.data.update()
    bpy.context.view_layer.update()
    assert "A" in ops._PENDING and bpy.app.timers.is_registered(ops._refresh_pending)
    ops._refresh_pending()                       # what the timer does 0.4 s later in a UI session
    assert _states(a)[:2] == ["stale", "stale"]
    assert a.unipixie.reason_features == "the mesh, its modifiers or materials changed"
    a.data.vertices[0].co.z -= 0.05
    bpy.ops.unipixie.refresh_pipeline()
    assert _states(a)[:2] == ["done", "done"]

    # so do its materials, a modifier, and the view count of the preferences
    mat = bpy.data.materials.new("Red")
    a.data.materials.append(mat)
    bpy.ops.unipixie.refresh_pipeline()
    assert a.unipixie.state_features == "stale"
    a.data.materials.clear()
    mod = a.modifiers.new("Bend", "SIMPLE_DEFORM")
    bpy.ops.unipixie.refresh_pipeline()
    assert a.unipixie.state_features == "stale"
    a.modifiers.remove(mod)
    monkeypatch.setattr(preferences._Defaults, "default_view_count", 6)
    bpy.ops.unipixie.refresh_pipeline()
    assert a.unipixie.state_render == "stale" and a.unipixie.reason_render == "the number of views changed"
    _activate(bpy, b)
    bpy.ops.unipixie.refresh_pipeline()
    assert _states(b) == ["not done"] * 4


# --------------------------------------------------------------------------- save / reopen, undo
def test_reopened_file_finds_cached_results_and_bakes_from_them(panel, tmp_path):
    bpy = panel
    from unipixie.core.blender_io import bake as bio
    from unipixie.core.blender_io import field_view
    from unipixie.core.blender_io import pipeline as pio
    from unipixie.unipixie_addon.operators_pipeline import pipeline_settings

    obj = _rod(bpy, "Kept")
    obj.unipixie.solver = "spring_mass"
    obj.unipixie.use_bake_frame_range, obj.unipixie.bake_frame_end = True, 5
    for step in ("features", "predict"):
        assert bpy.ops.unipixie.pipeline_step(step=step) == {"FINISHED"}
    assert bpy.ops.unipixie.toggle_field() == {"FINISHED"}
    path = tmp_path / "kept.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))     # the load handler refreshes every pipeline object
    obj = bpy.data.objects["Kept"]
    assert _states(obj) == ["done", "done", "done", "not done"]
    assert pio.plan_of(obj, pipeline_settings(bpy.context, obj)) is not None   # the bake's plan, from the record
    field_view._CACHE.clear()
    obj.unipixie.alpha = 0.9                         # recolours the saved field display from the cached sweep
    assert field_view.corner_colours(obj) is not None
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.unipixie.bake() == {"FINISHED"}   # the sub-panel's Simulate & bake: the pipeline's bake step
    assert bio.bake_record(obj)["material_source"] == {"source": "model"} and _states(obj) == ["done"] * 4


def test_undo_restores_the_pipeline_state(panel, tmp_path):
    bpy = panel

    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "undo.blend"))
    obj = _rod(bpy, "Undone")
    assert bpy.ops.unipixie.pipeline_step(step="features") == {"FINISHED"}
    bpy.ops.ed.undo_push(message="features done")
    assert bpy.ops.unipixie.pipeline_step("EXEC_DEFAULT", True, step="predict") == {"FINISHED"}
    assert "predict" in _record(bpy.data.objects["Undone"]).steps
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Undone"]
    assert "predict" not in _record(obj).steps and "features" in _record(obj).steps
    assert obj.unipixie.state_predict == "not done" and obj.unipixie.bake_material_source == "homogeneous"
    bpy.ops.ed.redo()
    obj = bpy.data.objects["Undone"]
    assert "predict" in _record(obj).steps and obj.unipixie.state_predict == "done"


# --------------------------------------------------------------------------- errors, Esc, preferences
def test_errors_are_reports_and_shown_in_the_panel(panel, tmp_path, monkeypatch):
    bpy = panel
    from unipixie.unipixie_addon import preferences

    obj = _rod(bpy, "Early")
    with pytest.raises(RuntimeError, match="has no features yet: run Features first"):
        bpy.ops.unipixie.pipeline_step(step="predict")
    assert "run Features first" in obj.unipixie.last_error and obj.unipixie.status == "failed"
    assert obj.unipixie.state_predict == "not done"
    with pytest.raises(RuntimeError, match="no prediction to show"):
        bpy.ops.unipixie.toggle_field()
    with pytest.raises(RuntimeError, match="no prediction yet: run Predict first"):
        bpy.ops.unipixie.refine_alpha()
    assert bpy.ops.unipixie.pipeline_step(step="features") == {"FINISHED"}
    monkeypatch.setattr(preferences._Defaults, "checkpoint", str(tmp_path / "no_model"))
    with pytest.raises(RuntimeError, match="no_model does not exist"):
        bpy.ops.unipixie.pipeline_step(step="predict")
    bpy.ops.object.mode_set(mode="EDIT")
    assert not bpy.ops.unipixie.pipeline_step.poll()
    bpy.ops.object.mode_set(mode="OBJECT")


def test_esc_during_a_step_keeps_the_record_as_it_was(panel):
    bpy = panel
    from unipixie.core.blender_io import pipeline as pio
    from unipixie.unipixie_addon.operators_pipeline import pipeline_settings

    bpy.ops.mesh.primitive_cone_add(vertices=9, radius1=0.05, depth=0.15)
    obj = bpy.context.active_object
    job = pio.features_step(obj, pipeline_settings(bpy.context, obj))
    next(job)
    assert pio.running_step(obj) == "features"
    job.close()                                      # Esc between two views
    assert pio.running_step(obj) == "" and _record(obj).steps == {}
    bpy.ops.unipixie.refresh_pipeline()
    assert _states(obj) == ["not done"] * 4


def test_preference_checks_give_clear_messages(panel, tmp_path, tiny_checkpoint):
    bpy = panel
    from unipixie.unipixie_addon.preferences import check_preferences

    good = SimpleNamespace(checkpoint=str(tiny_checkpoint), clip_weights="", cache_dir=str(tmp_path), device="cpu",
                           default_view_count=24)
    assert check_preferences(good) == []
    bad = SimpleNamespace(checkpoint=str(tmp_path / "missing"), clip_weights=str(tmp_path / "clip"),
                          cache_dir=str(tmp_path), device="cpu", default_view_count=5)
    problems = check_preferences(bad)
    assert [p.split(":")[0] for p in problems] == ["Model checkpoint", "CLIP weights", "Default views"]
    assert bpy.ops.unipixie.check_preferences() == {"FINISHED"}       # the panel fixture asks for only 4 views
    assert bpy.context.window_manager.unipixie_preference_problems.startswith("Default views: 4 views")


def test_alpha_slider_on_a_100k_vertex_object_neither_refingerprints_nor_takes_50_ms(panel, tmp_path, monkeypatch):
    """Issue 22's slider path on a 99.6k-vertex object with a prediction and the field shown: each move
    recolours from the cached sweep (the states follow once the slider rests); the object's geometry is not
    hashed again, and a move takes under 50 ms (2026-11-27, 2-core machine at load 3–5, 50 moves a run: median
    2.0–8.4 ms wall, 3.2–3.4 ms CPU, CPU at most 4.3 ms; 3.7–4.0 ms CPU, at most 7.6, when every move also
    refreshed the states)."""
    bpy = panel
    from unipixie.core.blender_io import pipeline as pio

    occ = _ball()
    alphas = np.linspace(0, 1, 11)
    logE = (4.5 + 2.0 * alphas[:, None] + np.zeros(int(occ.sum()))[None]).astype(np.float32)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5, segments=400, ring_count=250)
    obj = bpy.context.active_object
    assert len(obj.data.vertices) > 99_000
    _show_sweep(bpy, obj, tmp_path / "sweep.npz", occ, logE)
    obj.unipixie.alpha = 0.0                       # warm-up: the field's voxel map, the fingerprint
    hashed = []
    real_fingerprint = pio.fingerprint
    monkeypatch.setattr(pio, "fingerprint", lambda o: hashed.append(o.name) or real_fingerprint(o))
    times = []
    for a in (0.05, 0.23, 0.5, 0.77, 1.0, 0.6, 0.4):
        t = time.perf_counter()
        obj.unipixie.alpha = a
        times.append(time.perf_counter() - t)
    assert hashed == [], f"a slider move hashed the geometry again ({len(hashed)} times)"
    assert max(times) < 0.050, f"a slider move took {1e3 * max(times):.1f} ms on {len(obj.data.vertices)} vertices"
    assert obj.unipixie.field_summary.startswith("E at α 0.40")


def test_a_slider_move_only_recolours_and_the_states_follow_once_it_rests(panel, tmp_path, monkeypatch):
    """Issue 22, part 4: a move of α recolours the field and the summary from the cached sweep; it neither reads
    the object's record nor refreshes the step states.  Those follow once, from ``refresh_object``, when the slider
    has rested (the timer; ``settle_alpha`` here, where timers do not run)."""
    bpy = panel
    from unipixie.core.blender_io import field_view
    from unipixie.core.blender_io import pipeline as pio
    from unipixie.unipixie_addon import operators_pipeline as ops

    occ = _ball(0.15)
    logE = (4.0 + 3.0 * np.linspace(0, 1, 11)[:, None] + np.zeros(int(occ.sum()))[None]).astype(np.float32)
    bpy.ops.mesh.primitive_cube_add(size=0.2)
    obj = bpy.context.active_object
    _show_sweep(bpy, obj, tmp_path / "sweep.npz", occ, logE)
    bpy.ops.unipixie.refresh_pipeline()
    obj.unipixie.alpha = 0.0                            # warm-up: the field's voxel map
    ops.settle_alpha()

    calls = {"record": 0, "refresh": 0}
    real_read, real_refresh = pio.read_record, ops.refresh_object
    monkeypatch.setattr(pio, "read_record", lambda o: calls.__setitem__("record", calls["record"] + 1) or real_read(o))
    monkeypatch.setattr(ops, "refresh_object",
                        lambda *a, **k: calls.__setitem__("refresh", calls["refresh"] + 1) or real_refresh(*a, **k))
    before = field_view.corner_colours(obj).copy()
    for a in (0.2, 0.5, 0.9):
        obj.unipixie.alpha = a
    assert calls == {"record": 0, "refresh": 0}, f"a slider move read the record or refreshed the states: {calls}"
    assert not np.allclose(field_view.corner_colours(obj), before)            # recoloured
    assert obj.unipixie.field_summary.startswith("E at α 0.90")
    assert obj.name in ops._SETTLING and bpy.app.timers.is_registered(ops._refresh_settled)

    ops.settle_alpha()                                   # the slider rests: one refresh, from refresh_object
    assert calls["refresh"] == 1 and calls["record"] >= 1 and obj.name not in ops._SETTLING
    assert ops._refresh_settled() is None                # nothing left for the timer
