"""Test set-up: isolate Blender's user directory and UniPixie's caches before anything imports bpy."""

from __future__ import annotations

import os
import signal
import tempfile
from pathlib import Path

import pytest

# A suite started in the background by a shell without job control (`make test &` in a script) inherits SIGINT
# ignored, and Python then never installs its KeyboardInterrupt handler: the Ctrl-C tests
# (tests/test_fault_interruption.py) would find no Ctrl-C to test.  Give the test process Python's own handler.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

_SESSION_TMP = tempfile.mkdtemp(prefix="unipixie-tests-")
# Blender reads these at import time: never touch ~/.config/blender from tests.
os.environ["BLENDER_USER_RESOURCES"] = os.path.join(_SESSION_TMP, "blender-user")
os.environ.pop("BLENDER_USER_CONFIG", None)
os.environ.pop("BLENDER_USER_SCRIPTS", None)
# Fresh caches per test session, but keep Warp's compiled kernels between sessions (compiling is slow).
_default_warp = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "unipixie" / "warp"
os.environ.setdefault("UNIPIXIE_WARP_CACHE", str(_default_warp))
os.environ["UNIPIXIE_CACHE_DIR"] = os.path.join(_SESSION_TMP, "cache")

REPO_ROOT = Path(__file__).resolve().parents[1]


class _RepositoryRootIsAFolder:
    """Collect the checkout's root as a plain folder, never as a test package.

    The root's ``__init__.py`` is the Blender extension's entry point, so pytest would collect the root as a
    package named after the folder the checkout sits in, and import it for its set-up.  A clone in a folder
    whose name is no Python module name (``git clone … "$(mktemp -d)"`` gives ``tmp.XXXX``) then fails every
    test at the root's relative imports.  The tests import the package as ``unipixie`` (the editable install).
    A conftest's hooks only reach the folders below it; the root is collected through its parent's hooks,
    hence a plugin registered for the whole session (``pytest_configure`` below).
    """

    @pytest.hookimpl(tryfirst=True)
    def pytest_collect_directory(self, path, parent):
        if Path(path).resolve() == REPO_ROOT:
            return pytest.Dir.from_parent(parent, path=Path(path))
        return None


def pytest_configure(config):
    config.pluginmanager.register(_RepositoryRootIsAFolder(), "unipixie-repository-root-is-a-folder")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """An untrained tiny model for the offline features (64³ grid, patch 4, 64 spring anchors)."""
    from unipixie.core.demo import untrained_checkpoint

    return untrained_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny", "tiny", spring_anchors=64)


@pytest.fixture
def one_torch_thread():
    """Torch's intra-op threads set to one for the test, then restored: on tiny tensors one thread is fastest and
    never oversubscribes a shared CI machine (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def blender():
    """The bpy module with an empty factory scene and the UniPixie add-on registered (in-process)."""
    bpy = pytest.importorskip("bpy")
    import unipixie

    bpy.ops.wm.read_factory_settings(use_empty=True)
    unipixie.register()
    try:
        yield bpy
    finally:
        unipixie.unregister()
        bpy.ops.wm.read_factory_settings(use_empty=True)
