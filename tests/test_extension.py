"""The Blender extension: manifest rules, build, validate, install through real bpy, run an operator."""

from __future__ import annotations

import tomllib
import zipfile

import pytest

from unipixie.core import extension


def test_manifest_rules(repo_root):
    man = tomllib.loads((repo_root / "blender_manifest.toml").read_text())
    assert man["schema_version"] == "1.0.0"
    assert man["id"] == "unipixie"
    assert man["type"] == "add-on"
    assert man["blender_version_min"] == "4.2.0"
    assert man["license"] == ["SPDX:GPL-3.0-or-later"]
    tagline = man["tagline"]
    assert len(tagline) < 64 and tagline[-1] not in ".!?,;:"
    excluded = man["build"]["paths_exclude_pattern"]
    for must in ("/tests/", "/.venv/", "__pycache__/"):
        assert must in excluded
    import unipixie

    assert man["version"] == unipixie.__version__
    for wheel in man.get("wheels", []):
        assert (repo_root / wheel).is_file(), wheel


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory):
    return extension.build(tmp_path_factory.mktemp("dist"))


def test_build_and_validate(built_zip):
    assert built_zip.name == f"unipixie-{extension.manifest()['version']}.zip"
    assert "Success" in extension.validate(built_zip)
    names = zipfile.ZipFile(built_zip).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "unipixie_addon/__init__.py" in names and "core/cli.py" in names and "solvers/effects.py" in names
    assert not any(n.startswith(("tests/", ".venv/", ".git/")) or "__pycache__" in n for n in names)


def test_install_enable_and_run_operator(built_zip, tmp_path):
    user_dir = tmp_path / "blender-user"
    rep = extension.install_and_check(built_zip, user_dir=user_dir)
    assert rep.ok, rep.log[-3000:]
    assert rep.module == "bl_ext.user_default.unipixie"
    assert "check_dependencies" in rep.operators
    assert "VIEW3D_PT_unipixie" in rep.panels
    assert rep.operator_result == ["FINISHED"]
    assert rep.dependency_report["torch"]["ok"] and rep.dependency_report["warp"]["ok"]
    # installed under the throw-away user directory, not ~/.config/blender
    assert any(p.name == "unipixie" for p in user_dir.rglob("unipixie") if p.is_dir())


def test_build_extension_command(tmp_path):
    from unipixie import cli

    assert cli.main(["build-extension", "--out-dir", str(tmp_path)]) == 0
    assert (tmp_path / f"unipixie-{extension.manifest()['version']}.zip").is_file()
