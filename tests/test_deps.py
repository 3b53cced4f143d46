"""How dependencies reach a Blender: the pinned list and the pip --target installer."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from unipixie.core import deps


def test_pins_match_requirements_lock(repo_root):
    lock = {}
    for line in (repo_root / "requirements.lock").read_text().splitlines():
        if "==" in line:
            name, ver = line.strip().split("==")
            lock[name.lower().replace("_", "-")] = ver
    for module, (dist, req) in deps.RUNTIME_REQUIREMENTS.items():
        if "==" in req:
            name, ver = req.split("==")
            assert lock.get(name.lower().replace("_", "-")) == ver, f"{req} disagrees with requirements.lock"


def test_check_reports_all_present_here():
    report = deps.check()
    assert deps.missing(report) == [], report


def test_install_into_target_with_pip(tmp_path):
    """The installer's pip --target path, exercised offline on a freshly built wheel."""
    src = tmp_path / "src"
    (src / "unipixie_dep_probe").mkdir(parents=True)
    (src / "unipixie_dep_probe" / "__init__.py").write_text("VALUE = 42\n")
    (src / "pyproject.toml").write_text(textwrap.dedent("""
        [build-system]
        requires = ["setuptools"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "unipixie-dep-probe"
        version = "1.0"
    """))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels),
                    str(src)], check=True)
    target = tmp_path / "site-packages"
    cmd = deps.install_command(target, modules=[], extra_args=["--no-index", "--find-links", str(wheels),
                                                               "unipixie-dep-probe"])
    assert cmd[:6] == [sys.executable, "-m", "pip", "install", "--upgrade", "--target"]
    subprocess.run(cmd, check=True, capture_output=True)
    assert deps.add_to_path(target)
    import importlib

    mod = importlib.import_module("unipixie_dep_probe")
    assert mod.VALUE == 42
    sys.path.remove(str(target))
    assert deps.install_command(target, modules=["torch", "warp"])[-2:] == ["torch==2.14.1", "warp-lang==1.19.0"]
