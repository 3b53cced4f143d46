"""The Python dependencies UniPixie needs at run time, and how they reach a Blender.

Outside Blender, ``setup.sh`` installs everything from ``requirements.lock``.
Inside a user's Blender (whose bundled Python has numpy but not torch, warp,
...), the add-on's preferences offer **Install dependencies**, which runs
Blender's own Python::

    <blender python> -m pip install --target <extension user dir>/site-packages <pinned requirements>

and the add-on puts that directory on ``sys.path`` when it is enabled.  The two
small pure-Python libraries (trimesh, tqdm) are bundled as wheels in the
extension zip instead.  This module holds the list and the command; it does
not import bpy.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import subprocess
import sys
from pathlib import Path

# import name -> (distribution name, pinned requirement for a Blender install)
RUNTIME_REQUIREMENTS: dict[str, tuple[str, str]] = {
    "numpy": ("numpy", "numpy<2"),
    "scipy": ("scipy", "scipy==1.17.1"),
    "torch": ("torch", "torch==2.14.1"),
    "torchvision": ("torchvision", "torchvision==0.29.1"),
    "open_clip": ("open_clip_torch", "open-clip-torch==3.3.0"),
    "warp": ("warp-lang", "warp-lang==1.19.0"),
    "trimesh": ("trimesh", "trimesh==5.2.0"),
    "rtree": ("rtree", "rtree==1.4.1"),
    "embreex": ("embreex", "embreex==4.4.0.post1"),
    "matplotlib": ("matplotlib", "matplotlib==3.11.2"),
    "tqdm": ("tqdm", "tqdm==4.70.1"),
    "safetensors": ("safetensors", "safetensors==0.8.0"),
    "PIL": ("pillow", "pillow==13.0.0"),
}

BUNDLED_WHEELS = ("trimesh", "tqdm")
"""Pure-Python dependencies shipped inside the extension zip (see blender_manifest.toml)."""


def check() -> dict[str, dict]:
    """For each runtime dependency: ``{"ok": bool, "version": str, "error": str}`` (imports each one)."""
    report: dict[str, dict] = {}
    for module, (dist, _req) in RUNTIME_REQUIREMENTS.items():
        entry = {"ok": False, "version": "", "error": ""}
        try:
            importlib.import_module(module)
            try:
                entry["version"] = importlib.metadata.version(dist)
            except importlib.metadata.PackageNotFoundError:
                entry["version"] = getattr(sys.modules[module], "__version__", "")
            entry["ok"] = True
        except Exception as exc:  # ImportError, or a broken binary
            entry["error"] = f"{type(exc).__name__}: {exc}"
        report[module] = entry
    return report


def missing(report: dict[str, dict] | None = None) -> list[str]:
    report = check() if report is None else report
    return [m for m, e in report.items() if not e["ok"]]


def install_command(target: str | Path, modules: list[str] | None = None, python: str | None = None,
                    extra_args: list[str] | None = None) -> list[str]:
    """The pip command that installs the given (default: all missing) dependencies into ``target``."""
    modules = missing() if modules is None else modules
    reqs = [RUNTIME_REQUIREMENTS[m][1] for m in modules]
    return [python or sys.executable, "-m", "pip", "install", "--upgrade", "--target", str(target),
            *(extra_args or []), *reqs]


def install(target: str | Path, modules: list[str] | None = None, python: str | None = None,
            extra_args: list[str] | None = None) -> subprocess.CompletedProcess:
    """Run :func:`install_command` (blocking); returns the finished process."""
    Path(target).mkdir(parents=True, exist_ok=True)
    cmd = install_command(target, modules, python, extra_args)
    return subprocess.run(cmd, capture_output=True, text=True)


def add_to_path(target: str | Path) -> bool:
    """Put ``target`` on ``sys.path`` (front) if it exists; returns whether it was added."""
    t = str(Path(target))
    if Path(t).is_dir() and t not in sys.path:
        sys.path.insert(0, t)
        importlib.invalidate_caches()
        return True
    return False
