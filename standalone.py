"""Running a module of the checkout as a plain file, without the package installed.

``training/train.py`` (also in torchrun's file form), ``training/baselines.py``, ``training/pack.py`` and
``training/benchmarks/model.py`` must run as files from a bare checkout on a machine that has only torch,
numpy and safetensors.  A file run that way belongs to no package, so its relative imports would fail;
each of them therefore starts with (``parents[2]`` one folder deeper)::

    if __package__ in (None, ""):  # run as a file: import the checkout as `unipixie` (standalone.py)
        import runpy

        runpy.run_path(str(Path(__file__).resolve().parents[1] / "standalone.py"))["import_checkout"]()
        __package__ = "unipixie.training"

This module imports only the standard library.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def import_checkout() -> None:
    """Import the checkout this file is in as the package ``unipixie`` (nothing when a ``unipixie`` is
    imported already), so that a module run as a file can import its siblings relatively."""
    if "unipixie" in sys.modules:
        return
    root = Path(__file__).resolve().parent
    spec = importlib.util.spec_from_file_location("unipixie", root / "__init__.py",
                                                  submodule_search_locations=[str(root)])
    package = importlib.util.module_from_spec(spec)
    sys.modules["unipixie"] = package
    spec.loader.exec_module(package)
