"""The suite runs in a checkout whatever its folder is called (README: clone, ``./setup.sh``, ``make test``).

The checkout's root is the ``unipixie`` package (the Blender extension's ``__init__.py``); pytest must not
collect it as a test package named after the folder: a clone made with ``git clone … "$(mktemp -d)"`` sits in
``tmp.XXXX``, no Python module name, and every test then failed at the root's relative imports (669 errors).
"""

from __future__ import annotations

import shutil
import subprocess
import sys


def test_a_checkout_in_a_folder_with_a_dot_in_its_name_runs_its_tests(tmp_path, repo_root):
    checkout = tmp_path / "tmp.Ab3.d" / "unipixie.clone"
    (checkout / "tests").mkdir(parents=True)
    # The root as it is: the package's __init__.py (relative imports) and the pytest configuration.
    for name in ("__init__.py", "pyproject.toml"):
        shutil.copy(repo_root / name, checkout / name)
    shutil.copy(repo_root / "tests" / "conftest.py", checkout / "tests" / "conftest.py")
    (checkout / "tests" / "test_probe.py").write_text(
        "def test_probe(repo_root):\n    assert (repo_root / 'tests' / 'test_probe.py').is_file()\n")
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=checkout,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "1 passed" in run.stdout
