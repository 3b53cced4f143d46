"""Measurements in Blender (through real bpy): the animated point cloud, the error colour attribute,
reading an object's keyframed motion, and the panel operators (load, compare, diagnose, add effect)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytestmark = pytest.mark.blender


def _evaluated(bpy, obj, frame):
    """Vertex positions of ``obj`` at ``frame`` with its point-drawing modifier off."""
    bpy.context.scene.frame_set(frame)
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    me = ev.to_mesh()
    co = np.empty(len(me.vertices) * 3, dtype=np.float32)
    me.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    return co.reshape(-1, 3)


def _measurement(T=6, fps=24.0):
    from unipixie.core.measurement import MeasuredMaterial, Measurement

    rest = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.2 + [0, 0, 0.5]
    t = np.arange(T) / fps
    pos = rest[None] + np.array([0.3, 0.0, -1.0])[None, None] * t[:, None, None]
    pos[2, 3] = np.nan  # occluded
    return Measurement(pos, t, scenario={"format": "unipixie.measurement/1", "ground": None}, rest_positions=rest,
                       material=MeasuredMaterial(2e5, 0.3, 1000.0))


def test_point_cloud_follows_the_measurement(blender, tmp_path):
    bpy = blender
    from unipixie.core.blender_io import measure as bio

    m = _measurement()
    path = m.save(tmp_path / "m.npz")
    assert bpy.ops.unipixie.load_measurement(filepath=str(path)) == {"FINISHED"}
    s = bpy.context.scene.unipixie_diagnosis
    obj = s.measurement_object
    assert obj is not None and len(obj.data.vertices) == 8 and obj.modifiers[0].type == "NODES"
    obj.modifiers[0].show_viewport = False
    f0 = bpy.context.scene.frame_start
    for i in (0, 1, 4, 5):
        assert np.allclose(_evaluated(bpy, obj, f0 + i), m.positions[i], atol=1e-5)
    held = _evaluated(bpy, obj, f0 + 2)  # the occluded point holds its last observed position
    assert np.allclose(held[3], m.positions[1, 3], atol=1e-5)
    assert np.allclose(held[[0, 1, 2, 4, 5, 6, 7]], m.positions[2][[0, 1, 2, 4, 5, 6, 7]], atol=1e-5)
    observed = np.empty(8, dtype=np.float32)
    obj.data.attributes[bio.OBSERVED_ATTRIBUTE].data.foreach_get("value", observed)
    assert observed[3] == pytest.approx(5 / 6) and observed[0] == 1.0
    # drawn as spheres, only where observed at that instant: the occluded point is not drawn at the third instant
    obj.modifiers[0].show_viewport = True
    faces = {}
    for i in (1, 2, 3):
        bpy.context.scene.frame_set(f0 + i)
        ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        faces[i] = len(ev.to_mesh().polygons)
        ev.to_mesh_clear()
    assert faces[1] == faces[3] > 0 and faces[2] == faces[1] * 7 // 8


def test_error_colour_attribute(blender):
    bpy = blender
    from unipixie.core.blender_io import measure as bio
    from unipixie.core.errors import UserError

    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.active_object
    err = np.array([0.0, 0.001, 0.002, 0.004, 0.008, np.nan, 0.01, 0.0])
    assert bio.write_error_attribute(obj, err, vmax=0.01) == bio.ERROR_COLOR_ATTRIBUTE
    me = obj.data
    col = np.empty(8 * 4, dtype=np.float32)
    me.color_attributes[bio.ERROR_COLOR_ATTRIBUTE].data.foreach_get("color", col)
    col = col.reshape(8, 4)
    assert me.color_attributes.active_color.name == bio.ERROR_COLOR_ATTRIBUTE
    assert np.allclose(col[5, :3], 0.5)                    # never observed: grey
    assert col[6, 1] > col[0, 1] and col[0, 2] > col[6, 2]  # viridis: blue (0) → yellow (vmax)
    vals = np.empty(8, dtype=np.float32)
    me.attributes[bio.ERROR_VALUE_ATTRIBUTE].data.foreach_get("value", vals)
    assert vals[4] == pytest.approx(0.008) and np.isnan(vals[5])
    bio.write_error_attribute(obj, np.zeros(8))  # writing again replaces, never duplicates
    assert list(me.color_attributes.keys()).count(bio.ERROR_COLOR_ATTRIBUTE) == 1
    with pytest.raises(UserError, match="8 vertices but the error has 3"):
        bio.write_error_attribute(obj, np.zeros(3))


def _frame_values(bpy, obj, frame):
    """(N,) ``unipixie_error_now_m`` and (N, 4) ``unipixie_error_now`` of ``obj``'s mesh at ``frame``."""
    from unipixie.core.blender_io import error_animation as bea

    bpy.context.scene.frame_set(frame)
    me = obj.data
    n = len(me.vertices)
    vals = np.empty(n, dtype=np.float32)
    me.attributes[bea.ERROR_NOW_VALUE_ATTRIBUTE].data.foreach_get("value", vals)
    col = np.empty(n * 4, dtype=np.float32)
    me.color_attributes[bea.ERROR_NOW_COLOR_ATTRIBUTE].data.foreach_get("color", col)
    return vals, col.reshape(n, 4)


def test_the_error_at_each_frame_follows_the_time_slider(blender):
    """The per-instant error keyed on the point cloud: each frame shows its instant's error (grey and −1 where the
    point was not observed then), between instants the last one's; the drawn spheres carry it as their active colour
    (what Solid shading shows); removing it leaves the mesh's own animation alone."""
    bpy = blender
    from unipixie.core.blender_io import error_animation as bea
    from unipixie.core.blender_io import measure as bio

    scene = bpy.context.scene
    scene.render.fps = 24
    m = _measurement(T=6, fps=12.0)  # two frames an instant
    obj = bio.create_measurement_object(m, name="per-frame error")
    me = obj.data
    own_path = f'attributes["{bio.OBSERVED_ATTRIBUTE}"].data[0].value'  # the mesh's own animation: must survive
    me.animation_data_create().action = bpy.data.actions.new("the user's")
    me.animation_data.action.fcurve_ensure_for_datablock(me, own_path).keyframe_points.insert(3, 1.0)
    d = np.linspace(0.0, 0.01, 8)[None, :] * (1 + np.arange(6))[:, None] / 6
    d[2, 3] = np.nan  # not observed at the third instant
    anim = bea.write_error_animation(obj, d, m.times, vmax=0.01)
    assert (anim.instants, anim.keyed, anim.stride) == (6, 6, 1)
    f0 = scene.frame_start
    assert (anim.first_frame, anim.last_frame) == (f0, f0 + 10)
    for i in range(6):
        for extra in (0, 1):  # on the instant's frame and the frame after it, before the next instant
            vals, col = _frame_values(bpy, obj, f0 + 2 * i + extra)
            want = np.where(np.isfinite(d[i]), d[i], bea.NOT_OBSERVED_VALUE)
            assert np.allclose(vals, want, atol=1e-7), (i, extra)
            assert np.allclose(col, bio.error_colours(d[i], 0.01), atol=1e-6)
    _, col = _frame_values(bpy, obj, f0 + 4)
    assert np.allclose(col[3, :3], 0.5) and not np.allclose(col[2, :3], 0.5)  # grey where not observed
    _, first = _frame_values(bpy, obj, f0)
    _, last = _frame_values(bpy, obj, f0 + 10)
    assert last[7, 1] > first[7, 1]  # the growing error turns the far point from blue towards yellow
    # the drawn spheres (Geometry Nodes) keep the keyed colour as their active colour attribute
    ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    drawn = ev.to_mesh()
    assert len(drawn.polygons) > 0 and drawn.color_attributes.active_color is not None
    assert drawn.color_attributes.active_color.name == bea.ERROR_NOW_COLOR_ATTRIBUTE
    ev.to_mesh_clear()
    # writing again replaces; removing takes only what it wrote
    bea.write_error_animation(obj, d, m.times)
    assert bea.remove_error_animation(obj) == 8 * 4
    assert bea.ERROR_NOW_COLOR_ATTRIBUTE not in me.attributes and bea.ERROR_NOW_VALUE_ATTRIBUTE not in me.attributes
    from bpy_extras import anim_utils

    bag = anim_utils.animdata_get_channelbag_for_assigned_slot(me.animation_data)
    assert [fc.data_path for fc in bag.fcurves] == [own_path] and me.animation_data.action.name == "the user's"


def test_the_error_at_each_frame_is_thinned_to_the_key_limit_and_refuses_bad_input(blender):
    bpy = blender
    from unipixie.core.blender_io import error_animation as bea
    from unipixie.core.errors import UserError

    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.active_object
    times = np.arange(50) / 24.0
    d = np.tile(np.arange(50)[:, None] * 1e-4, (1, 8))
    anim = bea.write_error_animation(obj, d, times, max_keys=32 * 10)  # 32 curves: at most 10 instants
    assert anim.keyed <= 10 and anim.stride > 1 and "one instant in" in anim.describe()
    vals, _ = _frame_values(bpy, obj, int(round(anim.last_frame)))
    assert np.allclose(vals, d[-1], atol=1e-8)  # the last instant is always keyed
    assert not obj.data.get(bea.OWN_ACTION_PROPERTY)
    assert obj.data.animation_data.action.get(bea.OWN_ACTION_PROPERTY)
    bea.remove_error_animation(obj)
    assert obj.data.animation_data.action is None  # the action it made goes with its last curve
    with pytest.raises(UserError, match="8 vertices but the error has 3"):
        bea.write_error_animation(obj, np.zeros((50, 3)), times)
    with pytest.raises(UserError, match="strictly increasing"):
        bea.write_error_animation(obj, d, times[::-1])
    with pytest.raises(UserError, match="at two instants"):
        bea.write_error_animation(obj, d, times, max_keys=40)


def test_measurement_from_keyframed_object(blender, tmp_path):
    bpy = blender
    from unipixie.core.blender_io import measure as bio
    from unipixie.core.measurement import load

    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 9
    scene.render.fps = 24
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(0, 0, 1))
    cube = bpy.context.active_object
    for f, z in ((1, 1.0), (9, 0.2)):
        cube.location = (0, 0, z)
        cube.keyframe_insert("location", frame=f)
    m = bio.measurement_from_object(cube, scene=scene)
    assert m.frame_count == 9 and m.point_count == 8 and m.faces is not None and len(m.faces) == 12
    assert m.times[1] == pytest.approx(1 / 24)
    assert np.allclose(m.positions[0].mean(0), [0, 0, 1.0]) and np.allclose(m.positions[-1].mean(0), [0, 0, 0.2])
    assert np.allclose(m.rest.mean(0), [0, 0, 1.0])
    assert m.scenario.gravity[2] == pytest.approx(-9.81, rel=1e-3)
    # the panel operator writes the same as a file
    bpy.context.view_layer.objects.active = cube
    path = tmp_path / "cube.npz"
    assert bpy.ops.unipixie.measurement_from_object(filepath=str(path)) == {"FINISHED"}
    again = load(path)
    assert np.allclose(again.positions, m.positions) and again.material is not None


def test_compare_diagnose_and_add_effect_operators(blender, tmp_path):
    """A small wind measurement through the panel: compare colours the points, diagnose names wind,
    add effect puts it (with its fitted acceleration) into the model's effects."""
    bpy = blender
    from unipixie.core.blender_io import error_animation as bea
    from unipixie.core.blender_io import measure as bio
    from unipixie.core.diagnosis import synth

    m = synth.synthesize(["wind:acceleration=0.8,0,0"], "spring_mass", settings={"anchors": 64}, shape="cube",
                         scenario="throw", noise=0.001, occlusion=0.0, points=60, duration=0.5, fps=30)
    path = m.save(tmp_path / "wind.npz")
    assert bpy.ops.unipixie.load_measurement(filepath=str(path)) == {"FINISHED"}
    s = bpy.context.scene.unipixie_diagnosis
    s.solver = "spring_mass"
    s.solver_settings = "anchors=64"
    s.out_dir = str(tmp_path / "report")
    s.candidates = "wind,linear_drag"
    s.max_additions = 1
    assert bpy.ops.unipixie.compare_measurement() == {"FINISHED"}
    before = s.rmse
    attrs = s.measurement_object.data.color_attributes
    assert before > 0.02 and bio.ERROR_COLOR_ATTRIBUTE in attrs and bea.ERROR_NOW_COLOR_ATTRIBUTE in attrs
    assert attrs.active_color.name == bea.ERROR_NOW_COLOR_ATTRIBUTE and "mm (yellow)" in s.colour_scale
    scene = bpy.context.scene
    early, _ = _frame_values(bpy, s.measurement_object, scene.frame_start + 1)
    late, _ = _frame_values(bpy, s.measurement_object, scene.frame_start + 14)
    assert np.nanmean(late) > 3 * np.nanmean(early)  # the wind's drift grows: so does the error shown
    s.error_display = "RUN"
    assert attrs.active_color.name == bio.ERROR_COLOR_ATTRIBUTE
    s.error_display = "FRAME"
    assert bpy.ops.unipixie.diagnose() == {"FINISHED"}
    assert s.identified == "wind" and (tmp_path / "report" / "diagnosis.html").is_file()
    doc = json.loads((tmp_path / "report" / "diagnosis.json").read_text())
    assert doc["identified"] == "wind" and doc["tracking_outliers"]["count"] == 0  # searched, none in these tracks
    assert s.notes == "\n".join(doc["warnings"])  # the report's warnings reach the panel
    s.keep_outliers, s.max_additions, s.out_dir = True, 0, str(tmp_path / "kept")  # the panel's switch reaches it
    assert bpy.ops.unipixie.diagnose() == {"FINISHED"}
    kept = json.loads((tmp_path / "kept" / "diagnosis.json").read_text())
    assert kept["tracking_outliers"] == {"checked": False}
    s.keep_outliers, s.max_additions = False, 1
    assert bpy.ops.unipixie.add_effect() == {"FINISHED"}
    assert s.effects_on.startswith("wind:acceleration=")
    assert bpy.ops.unipixie.compare_measurement() == {"FINISHED"}  # the model now has the wind: the error fell
    assert s.rmse < 0.2 * before
    assert bpy.ops.unipixie.clear_error_colours() == {"FINISHED"}
    assert not any(n.startswith("unipixie_error") for n in s.measurement_object.data.attributes.keys())
    assert s.colour_scale == ""


def test_the_diagnosis_panel_shows_the_notes_wrapped(blender):
    """Each of the last diagnosis's warnings is shown under its summary, wrapped to the panel's width (Blender
    labels do not wrap), with an info icon on its first line."""
    from types import SimpleNamespace

    from unipixie.unipixie_addon import operators_diagnose as od

    bpy = blender
    labels = []

    class Layout:
        def __getattr__(self, name):
            if name in ("row", "column", "box"):
                return lambda *a, **k: self
            return lambda *a, **k: SimpleNamespace()

        def label(self, text="", icon="NONE", **kw):
            labels.append((text, icon))

    s = bpy.context.scene.unipixie_diagnosis
    s.summary = "nothing missing: 12.61 → 2.16 mm (noise 1.75 mm)"
    s.notes = "the energy the ground contact takes is in the fitted floor " * 4 + "\nshort note"
    od.VIEW3D_PT_unipixie_diagnose.draw(SimpleNamespace(layout=Layout()), bpy.context)
    notes = labels[labels.index((s.summary, "NONE")) + 1:]
    assert all(len(t) <= od.NOTE_WIDTH_CHARS for t, _ in notes) and len(notes) >= 5
    assert [icon for _, icon in notes].count("INFO") == 2 and notes[-1] == ("short note", "INFO")
    assert " ".join(t for t, _ in notes[:-1]).split() == s.notes.split("\n")[0].split()
