"""Operators for setting up: check and install the Python dependencies, fetch the CLIP weights."""

from __future__ import annotations

import json

import bpy

from ..core import deps
from .jobs import JobOperator
from .preferences import dependency_dir, store_extractor_info


class UNIPIXIE_OT_check_dependencies(bpy.types.Operator):
    """Check that UniPixie's Python dependencies (torch, warp, open_clip, trimesh, ...) import"""

    bl_idname = "unipixie.check_dependencies"
    bl_label = "Check dependencies"
    bl_options = {"REGISTER"}

    def execute(self, context):
        report = deps.check()
        missing = deps.missing(report)
        context.window_manager.unipixie_dependency_report = json.dumps(report)
        if missing:
            msg = f"missing: {', '.join(missing)} — use 'Install dependencies' in the add-on preferences"
            context.window_manager.unipixie_status = msg
            self.report({"WARNING"}, msg)
        else:
            versions = ", ".join(f"{m} {e['version']}" for m, e in report.items() if m in ("torch", "warp", "open_clip"))
            context.window_manager.unipixie_status = f"all dependencies present ({versions})"
            self.report({"INFO"}, context.window_manager.unipixie_status)
        return {"FINISHED"}


class UNIPIXIE_OT_install_dependencies(JobOperator, bpy.types.Operator):
    """Install the missing Python dependencies into this extension's user directory with pip"""

    bl_idname = "unipixie.install_dependencies"
    bl_label = "Install dependencies"
    bl_options = {"REGISTER"}

    def make_job(self, context):
        missing = deps.missing()
        if not missing:
            return "nothing to install"
        target = dependency_dir()
        yield 0.05, f"pip install {' '.join(missing)} (this can take minutes)"
        proc = deps.install(target, missing)
        if proc.returncode != 0:
            from ..core.errors import UserError

            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            raise UserError(f"pip failed: {tail[0]}")
        deps.add_to_path(target)
        yield 1.0, "installed"
        return f"installed {', '.join(missing)} into {target}"

    def finish(self, context, result):
        self.report({"INFO"}, str(result))
        bpy.ops.unipixie.check_dependencies()
        return {"FINISHED"}


class UNIPIXIE_OT_fetch_clip_weights(JobOperator, bpy.types.Operator):
    """Download the OpenCLIP weights of the CLIP feature extractor into the default weights folder (Hugging Face Hub:
    progress, resumed on dropped connections, checksum verified; HF_ENDPOINT selects a mirror). Esc cancels"""

    bl_idname = "unipixie.fetch_clip_weights"
    bl_label = "Fetch CLIP weights"
    bl_options = {"REGISTER"}

    model: bpy.props.StringProperty(name="Feature model", default="",
                                    description="The CLIP feature model (empty: the one the model expects, else "
                                                "ViT-B-16 laion2b_s34b_b88k)")

    def job_target(self, context):
        return None

    def make_job(self, context):
        from ..core import weights

        result = yield from weights.fetch_job(self.model or "")
        return result

    def finish(self, context, result):
        for note in result.notes:
            self.report({"WARNING"}, note)
        context.window_manager.unipixie_status = result.summary()
        store_extractor_info(context)
        self.report({"INFO"}, result.summary())
        return {"FINISHED"}


CLASSES = (UNIPIXIE_OT_check_dependencies, UNIPIXIE_OT_install_dependencies, UNIPIXIE_OT_fetch_clip_weights)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
