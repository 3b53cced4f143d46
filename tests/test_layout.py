"""The product's layout rules: where bpy may be imported, relative imports, packaging."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib

BPY_ALLOWED = ("unipixie_addon", "core/blender_io")


def _package_files(repo_root):
    for path in sorted(repo_root.rglob("*.py")):
        rel = path.relative_to(repo_root).as_posix()
        if rel.startswith((".venv/", "tests/", "build/", "dist/", "docs/", "benchmarks/", ".git/")):
            continue
        yield rel, path


def test_core_solvers_training_do_not_import_bpy():
    code = ("import sys, unipixie, unipixie.core, unipixie.solvers, unipixie.training, unipixie.cli;"
            "import unipixie.core.types, unipixie.solvers.effects, unipixie.solvers.materials, unipixie.solvers.api;"
            "print('bpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "False"


def test_bpy_imported_only_in_addon_and_blender_io(repo_root):
    offenders = []
    for rel, path in _package_files(repo_root):
        if rel.startswith(BPY_ALLOWED):
            continue
        tree = ast.parse(path.read_text(), filename=rel)
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            if any(n == "bpy" or n.startswith(("bpy.", "bmesh", "mathutils")) for n in names):
                offenders.append(f"{rel}:{node.lineno}")
    assert not offenders, f"bpy imported outside unipixie_addon/ and core/blender_io/: {offenders}"


def test_package_code_uses_relative_imports(repo_root):
    offenders = []
    for rel, path in _package_files(repo_root):
        if rel == "core/blender_io/extension_check.py":  # a standalone script run by Blender
            continue
        tree = ast.parse(path.read_text(), filename=rel)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and node.module.split(".")[0] == "unipixie":
                offenders.append(f"{rel}:{node.lineno}")
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "unipixie" for a in node.names):
                offenders.append(f"{rel}:{node.lineno}")
    assert not offenders, f"absolute 'unipixie' imports inside the package (must be relative): {offenders}"


def test_every_subpackage_is_listed_in_pyproject(repo_root):
    listed = set(tomllib.loads((repo_root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"unipixie"}
    for init in repo_root.rglob("__init__.py"):
        rel = init.parent.relative_to(repo_root).as_posix()
        if rel == "." or rel.startswith((".venv", "tests", "build", "dist")):
            continue
        found.add("unipixie." + rel.replace("/", "."))
    assert found == listed, f"pyproject packages differ: missing {sorted(found - listed)}, stale {sorted(listed - found)}"


def test_layout_directories_exist(repo_root):
    for name in ("blender_manifest.toml", "__init__.py", "unipixie_addon", "core", "solvers", "training", "tests"):
        assert (repo_root / name).exists(), name


def test_package_never_uses_a_context_override(repo_root):
    """``bpy.context.temp_override`` around an operator crashes Blender 5.0 while another Python thread runs
    (:mod:`unipixie.core.blender_io.context_safety`); the package's bakes and warm-ups always have such threads."""
    offenders = []
    for rel, path in _package_files(repo_root):
        tree = ast.parse(path.read_text(), filename=rel)
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "temp_override":
                offenders.append(f"{rel}:{node.lineno}")
    assert not offenders, f"context overrides in the package (use core/blender_io/context_safety.py): {offenders}"
