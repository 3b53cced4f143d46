"""The add-on in-process through the bpy module: registration, panel, operators, the job runner."""

import json

import pytest

pytestmark = pytest.mark.blender


def test_register_panel_and_operators(blender):
    bpy = blender
    assert hasattr(bpy.types, "VIEW3D_PT_unipixie")
    assert bpy.types.VIEW3D_PT_unipixie.bl_category == "UniPixie"
    assert bpy.ops.unipixie.check_dependencies() == {"FINISHED"}
    report = json.loads(bpy.context.window_manager.unipixie_dependency_report)
    assert report["torch"]["ok"] and report["warp"]["ok"] and report["trimesh"]["ok"]


def test_object_settings_are_saved(blender, tmp_path):
    bpy = blender
    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.active_object
    obj.unipixie.alpha = 0.25
    obj.unipixie.solver = "lbs"
    path = str(tmp_path / "s.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    obj = bpy.data.objects["Cube"]
    assert obj.unipixie.alpha == pytest.approx(0.25) and obj.unipixie.solver == "lbs"


def test_job_runner_reports_user_errors_and_runs_to_end(blender):
    bpy = blender
    from unipixie.core.errors import UserError
    from unipixie.unipixie_addon.jobs import JobOperator

    steps = []

    class UNIPIXIE_OT_test_job(JobOperator, bpy.types.Operator):
        bl_idname = "unipixie.test_job"
        bl_label = "Test job"
        fail: bpy.props.BoolProperty(default=False)

        def make_job(self, context):
            for i in range(3):
                steps.append(i)
                yield (i + 1) / 3, f"step {i}"
                if self.fail:
                    raise UserError("the mesh has no faces")
            return "done"

        def finish(self, context, result):
            steps.append(result)
            return {"FINISHED"}

    bpy.utils.register_class(UNIPIXIE_OT_test_job)
    try:
        bpy.ops.mesh.primitive_cube_add()
        assert bpy.ops.unipixie.test_job() == {"FINISHED"}
        assert steps == [0, 1, 2, "done"]
        obj = bpy.context.active_object
        with pytest.raises(RuntimeError, match="the mesh has no faces"):  # an ERROR report raises for callers
            bpy.ops.unipixie.test_job(fail=True)
        assert obj.unipixie.last_error == "the mesh has no faces" and obj.unipixie.status == "failed"
    finally:
        bpy.utils.unregister_class(UNIPIXIE_OT_test_job)
