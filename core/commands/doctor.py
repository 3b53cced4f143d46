"""``unipixie doctor``: check this installation end to end."""

from __future__ import annotations

NAME = "doctor"
HELP = "print versions and devices, then build, validate, install and run the Blender extension in a throw-away Blender"
EXAMPLES = """  unipixie doctor
  unipixie doctor --skip-extension          # versions and devices only
  unipixie doctor --blender /opt/blender/blender   # also check with a Blender binary"""


def add_arguments(p):
    p.add_argument("--skip-extension", action="store_true", help="do not build/install the extension")
    p.add_argument("--blender", metavar="BINARY", help="also install into this Blender executable (>= 4.2) in background mode")


def run(args) -> int:
    import platform
    import tempfile

    import os
    import shutil

    from .. import deps, extension, paths
    from .. import __version__
    from ..errors import UserError

    if args.blender:  # the binary is checked before anything runs, and only the extension check uses it
        if args.skip_extension:
            raise UserError("--blender checks the extension with that Blender binary; it cannot be combined with "
                            "--skip-extension")
        found = shutil.which(os.path.expanduser(args.blender))
        if found is None:
            what = "is not executable" if os.path.exists(os.path.expanduser(args.blender)) else "does not exist"
            raise UserError(f"--blender {args.blender}: the file {what}; give the path of a Blender executable (>= 4.2)")

    print(f"unipixie {__version__}  (Python {platform.python_version()}, {platform.system()} {platform.machine()})")
    report = deps.check()
    try:
        import importlib.metadata as md

        report["bpy"] = {"ok": True, "version": md.version("bpy"), "error": ""}
    except Exception as exc:
        report["bpy"] = {"ok": False, "version": "", "error": str(exc)}
    for name in ("bpy", "torch", "warp", "open_clip", "trimesh", "numpy", "scipy"):
        e = report[name]
        print(f"  {name:<10} {e['version'] if e['ok'] else 'MISSING: ' + e['error']}")
    failures = [m for m, e in report.items() if not e["ok"]]

    if report["warp"]["ok"]:
        from ...solvers.warp_runtime import available_devices, device_description

        devs = available_devices()
        print(f"  warp devices: {', '.join(f'{d} ({device_description(d)})' for d in devs)}")
        print(f"  warp kernel cache: {paths.warp_kernel_cache_dir()}")
    if report["torch"]["ok"]:
        import torch

        print(f"  torch cuda: {torch.cuda.is_available()}" + (f" ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available() else ""))
    print(f"  cache: {paths.cache_root()}")

    if not args.skip_extension:
        with tempfile.TemporaryDirectory(prefix="unipixie-doctor-") as tmp:
            zip_path = extension.build(tmp)
            print(f"extension: built {zip_path.name} ({zip_path.stat().st_size / 1e6:.1f} MB)")
            print(f"extension: validate -> {extension.validate(zip_path)}")
            binaries = [None] + ([args.blender] if args.blender else [])
            for binary in binaries:
                where = binary or "bpy module"
                rep = extension.install_and_check(zip_path, blender_binary=binary)
                if rep.ok:
                    print(f"extension ({where}): installed and enabled as {rep.module}; "
                          f"{len(rep.operators)} operators, panels {', '.join(rep.panels)}; "
                          f"unipixie.check_dependencies -> {', '.join(rep.operator_result)}")
                else:
                    print(f"extension ({where}): FAILED\n{rep.log[-3000:]}")
                    failures.append(f"extension ({where})")
    if failures:
        print(f"doctor: problems with {', '.join(failures)}")
        return 1
    print("doctor: all checks passed")
    return 0
