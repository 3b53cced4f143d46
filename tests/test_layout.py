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


# --------------------------------------------------------------------------- the import graph: layers point down
# docs/DEVELOPING.md, "Map": solvers/ at the bottom, core/ above it, training/ above core, unipixie_addon/ on top.
SOLVER_BASE = ("core.errors", "core.progress", "core.types", "core.paths")
"""The only core modules solvers/ may import (small base modules)."""
SOLVER_BASE_CLOSURE = SOLVER_BASE + ("core.atomic_io",)
"""Everything outside solvers/ that solvers/ reach, through any chain of imports (types saves with atomic_io)."""
FORBIDDEN = {"core": ("training", "unipixie_addon", "cli", "__init__"),
             "solvers": ("training", "unipixie_addon", "cli", "__init__"),
             "training": ("unipixie_addon",)}
"""Layer → what it never imports (``cli`` is the root command line, ``__init__`` the root package)."""


def _module_name(rel: str) -> tuple[str, bool]:
    parts = rel[:-3].split("/")
    is_package = parts[-1] == "__init__"
    return ".".join(parts[:-1] if is_package else parts) or "__init__", is_package


def import_graph(repo_root) -> dict:
    """``{module: {imported module: line}}`` over the package's modules (names relative to the package root,
    ``__init__`` for the root package), from every import statement (function-level ones included); a relative
    import is resolved to the submodule it names when that is a module, else to the package it comes from."""
    files = {}
    for rel, path in _package_files(repo_root):
        if rel.startswith(("wheels/", "models/")):
            continue
        files[_module_name(rel)[0]] = (rel, path)

    def known(name):
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or "__init__"

    graph = {}
    for name, (rel, path) in files.items():
        is_package = _module_name(rel)[1]
        edges = graph.setdefault(name, {})
        for node in ast.walk(ast.parse(path.read_text(), filename=rel)):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name.partition(".")[2] or "__init__" for a in node.names if a.name.split(".")[0] == "unipixie"]
            elif isinstance(node, ast.ImportFrom):
                if node.level == 0:
                    if not node.module or node.module.split(".")[0] != "unipixie":
                        continue
                    base = node.module.partition(".")[2].split(".") if "." in node.module else []
                else:
                    here = [] if name == "__init__" else name.split(".")
                    package = here if is_package else here[:-1]
                    if node.level - 1 > len(package):
                        continue
                    base = package[:len(package) - (node.level - 1)] + (node.module.split(".") if node.module else [])
                for alias in node.names:
                    sub = ".".join(base + [alias.name])
                    targets.append(sub if sub in files else (".".join(base) or "__init__"))
            for target in targets:
                target = known(target)
                if target != name:
                    edges.setdefault(target, node.lineno)
    return graph


def _layer(module: str) -> str:
    return module.split(".")[0]


def layer_violations(graph) -> list[str]:
    found = []
    for module, edges in sorted(graph.items()):
        layer = _layer(module)
        for target, line in sorted(edges.items()):
            if _layer(target) in FORBIDDEN.get(layer, ()) and target != layer:
                found.append(f"{module}:{line} -> {target}")
            if layer == "solvers" and _layer(target) != "solvers" and target not in SOLVER_BASE:
                found.append(f"{module}:{line} -> {target} (solvers/ may import only {', '.join(SOLVER_BASE)})")
    for module in SOLVER_BASE_CLOSURE:  # what the base modules pull in stays inside the base
        for target, line in sorted(graph.get(module, {}).items()):
            if target not in SOLVER_BASE_CLOSURE:
                found.append(f"{module}:{line} -> {target} (a base module of solvers/ reaches beyond the base)")
    return found


def import_cycles(graph) -> list[list[str]]:
    """One cycle (a list of modules, first = last) for each strongly connected component of the graph."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def visit(v):  # Tarjan, iterative
        work = [(v, iter(sorted(graph.get(v, {}))))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, {})))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == node:
                        break
                if len(component) > 1:
                    components.append(set(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    cycles = []
    for component in components:  # a shortest way back to the start, inside the component
        start = min(component)
        paths, seen, cycle = [[start]], {start}, None
        while paths and cycle is None:
            nxt = []
            for path in paths:
                for target in sorted(graph.get(path[-1], {})):
                    if target == start:
                        cycle = path + [start]
                        break
                    if target in component and target not in seen:
                        seen.add(target)
                        nxt.append(path + [target])
                if cycle:
                    break
            paths = nxt
        cycles.append(cycle)
    return cycles


def _describe(graph, cycle) -> str:
    return " -> ".join(f"{a}:{graph[a][b]}" for a, b in zip(cycle, cycle[1:])) + f" -> {cycle[-1]}"


def test_layers_only_import_downwards(repo_root):
    graph = import_graph(repo_root)
    assert len(graph) > 100 and "core.errors" in graph["solvers.mpm"]
    violations = layer_violations(graph)
    assert not violations, "imports against the layers (docs/DEVELOPING.md, Map):\n  " + "\n  ".join(violations)


def test_no_import_cycles(repo_root):
    graph = import_graph(repo_root)
    cycles = import_cycles(graph)
    assert not cycles, "import cycles (module:line -> ...):\n  " + "\n  ".join(_describe(graph, c) for c in cycles)


def test_import_graph_sees_function_level_and_relative_imports(repo_root, tmp_path):
    """The checker itself: a function-level relative import upwards and a two-module cycle are both found."""
    for rel, text in {"__init__.py": "", "core/__init__.py": "", "training/__init__.py": "",
                      "solvers/__init__.py": "", "solvers/a.py": "from ..core import errors\nfrom ..core.types import X\n",
                      "core/errors.py": "", "core/types.py": "", "core/lift.py": "",
                      "core/x.py": "def f():\n    from ..training import y\n    from . import z\n",
                      "core/z.py": "from .x import f\n", "training/y.py": "from ..solvers import a\n",
                      "solvers/b.py": "from ..core import lift\n"}.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    graph = import_graph(tmp_path)
    assert graph["solvers.a"] == {"core.errors": 1, "core.types": 2}
    assert layer_violations(graph) == ["core.x:2 -> training.y",
                                       "solvers.b:1 -> core.lift (solvers/ may import only "
                                       + ", ".join(SOLVER_BASE) + ")"]
    assert import_cycles(graph) == [["core.x", "core.z", "core.x"]]
