"""Install the UniPixie extension zip into the running Blender and check that it works.

Run in a *separate* process whose ``BLENDER_USER_RESOURCES`` points at a
throw-away directory (see :func:`unipixie.core.extension.install_and_check`)::

    python extension_check.py --zip dist/unipixie-0.1.0.zip --out result.json
    blender -b --factory-startup --python extension_check.py -- --zip ... --out ...

It installs with ``bpy.ops.extensions.package_install_files(...,
enable_on_install=True)``, lists the registered ``bpy.ops.unipixie``
operators and UniPixie panels, runs ``bpy.ops.unipixie.check_dependencies``
and writes a JSON report.  This file is a standalone script (no package
imports) so that a Blender binary can run it directly.
"""

import argparse
import json
import sys
import traceback


def _write_report(path, report):
    """The report, written into a unique temporary file beside ``path`` and renamed over it (this standalone
    script cannot import the package's ``core/atomic_io.py``; the parent reads the file only once it is whole)."""
    import os
    import tempfile

    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".extension-check.", suffix=".tmp.json", dir=folder)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(report, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--zip", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    report = {"ok": False}
    try:
        import bpy

        res = bpy.ops.extensions.package_install_files(filepath=args.zip, repo="user_default",
                                                       enable_on_install=True)
        report["install_result"] = sorted(res)
        module = "bl_ext.user_default.unipixie"
        report["module"] = module
        report["enabled"] = module in bpy.context.preferences.addons
        report["operators"] = sorted(dir(bpy.ops.unipixie))
        panels = []
        for name in dir(bpy.types):
            cls = getattr(bpy.types, name, None)
            if isinstance(cls, type) and issubclass(cls, bpy.types.Panel) and getattr(cls, "bl_category", "") == "UniPixie":
                panels.append(name)
        report["panels"] = sorted(panels)
        result = bpy.ops.unipixie.check_dependencies()
        report["operator_result"] = sorted(result)
        wm = bpy.context.window_manager
        report["dependency_report"] = json.loads(wm.unipixie_dependency_report or "{}")
        report["ok"] = bool(report["enabled"] and report["panels"] and "FINISHED" in result)
    except Exception:  # the report carries the failure to the parent process
        report["error"] = traceback.format_exc()
    _write_report(args.out, report)
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    sys.exit(main(argv))
