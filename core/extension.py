"""Build, validate and install the Blender extension (no bpy import here).

The build and validation use ``blender_ext.py``, the command-line tool that
ships inside Blender (and inside the ``bpy`` module) under
``scripts/addons_core/bl_pkg/cli/``.  Installation runs in a separate process
(the bpy module, or a Blender binary) with ``BLENDER_USER_RESOURCES`` pointing
at a directory of the caller's choice, so nothing touches the user's
``~/.config/blender``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path

from .errors import UserError

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
"""The extension's source directory (holds blender_manifest.toml)."""

CHECK_SCRIPT = Path(__file__).resolve().parent / "blender_io" / "extension_check.py"


def manifest() -> dict:
    with open(PACKAGE_ROOT / "blender_manifest.toml", "rb") as f:
        return tomllib.load(f)


def blender_ext_script() -> Path:
    """Path of ``blender_ext.py`` inside the installed bpy module or the running Blender."""
    candidates: list[Path] = []
    env = os.environ.get("UNIPIXIE_BLENDER_EXT")
    if env:
        candidates.append(Path(env))
    spec = importlib.util.find_spec("bpy")
    if spec is not None and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            candidates.extend(sorted(Path(loc).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py")))
    if "bpy" in sys.modules:  # inside a Blender binary: ask the already-loaded module, import nothing
        scripts = Path(sys.modules["bpy"].utils.resource_path("LOCAL")) / "scripts"
        candidates.append(scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py")
    for c in candidates:
        if c.is_file():
            return c
    raise UserError("cannot find Blender's blender_ext.py: install the bpy module (pip install bpy==5.0.1) "
                    "or set UNIPIXIE_BLENDER_EXT to its path")


def _run_blender_ext(args: list[str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(blender_ext_script()), *args]
    return subprocess.run(cmd, capture_output=True, text=True)


def build(output_dir: str | os.PathLike = "dist") -> Path:
    """Build ``<output_dir>/unipixie-<version>.zip`` from the package source; returns its path."""
    man = manifest()
    out_dir = Path(output_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{man['id']}-{man['version']}.zip"
    if out.exists():
        out.unlink()
    res = _run_blender_ext(["build", "--source-dir", str(PACKAGE_ROOT), "--output-filepath", str(out)])
    if res.returncode != 0 or not out.is_file():
        raise UserError(f"extension build failed: {(res.stdout + res.stderr).strip().splitlines()[-1:]}")
    return out


def validate(path: str | os.PathLike) -> str:
    """Run ``blender_ext.py validate`` on a zip or source directory; returns its message, raises on failure."""
    res = _run_blender_ext(["validate", str(path)])
    text = (res.stdout + res.stderr).strip()
    if res.returncode != 0 or "error" in text.lower():
        raise UserError(f"extension validation failed: {text}")
    return text


@dataclass
class InstallReport:
    """What a throw-away Blender reported after installing and enabling the extension."""

    ok: bool
    module: str
    operators: list
    panels: list
    operator_result: list
    dependency_report: dict
    log: str


def install_and_check(zip_path: str | os.PathLike, user_dir: str | os.PathLike | None = None,
                      blender_binary: str | None = None, timeout: float = 300) -> InstallReport:
    """Install the zip into a throw-away Blender user directory, enable it and run an operator.

    Runs in a child process: the bpy module (``python``) or, with ``blender_binary``, a Blender
    executable in background mode.  ``user_dir`` defaults to a new temporary directory.
    """
    zip_path = Path(zip_path).resolve()
    if not zip_path.is_file():
        raise UserError(f"extension zip not found: {zip_path}")
    tmp = None
    if user_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="unipixie-blender-user-")
        user_dir = tmp.name
    result_file = Path(user_dir) / "unipixie_check.json"
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(Path(user_dir).resolve())
    env.pop("BLENDER_USER_CONFIG", None)
    env.pop("BLENDER_USER_SCRIPTS", None)
    script_args = ["--zip", str(zip_path), "--out", str(result_file)]
    if blender_binary:
        cmd = [blender_binary, "-b", "--factory-startup", "--python", str(CHECK_SCRIPT), "--", *script_args]
    else:
        cmd = [sys.executable, str(CHECK_SCRIPT), *script_args]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
        log = res.stdout + res.stderr
        if not result_file.is_file():
            raise UserError(f"the Blender check process wrote no result (exit {res.returncode}):\n{log[-3000:]}")
        data = json.loads(result_file.read_text())
        return InstallReport(ok=bool(data.get("ok")), module=data.get("module", ""), operators=data.get("operators", []),
                             panels=data.get("panels", []), operator_result=data.get("operator_result", []),
                             dependency_report=data.get("dependency_report", {}), log=log)
    finally:
        if tmp is not None:
            tmp.cleanup()
