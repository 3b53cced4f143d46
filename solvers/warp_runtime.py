"""One place that initialises NVIDIA Warp for the project.

Warp compiles kernels on first use and caches the binaries; the cache lives in
:func:`unipixie.core.paths.warp_kernel_cache_dir` (``UNIPIXIE_WARP_CACHE`` or
``<cache root>/warp``), never in the source tree.
"""

from __future__ import annotations

import os
import threading

from ..core.errors import UserError
from ..core.paths import warp_kernel_cache_dir

_lock = threading.Lock()
_initialised = False


def init_warp(quiet: bool = True):
    """Import and initialise Warp once (kernel cache configured first); returns the ``warp`` module."""
    global _initialised
    with _lock:
        import warp as wp

        if not _initialised:
            wp.config.kernel_cache_dir = str(warp_kernel_cache_dir())
            if quiet:
                wp.config.log_level = getattr(wp, "LOG_WARNING", 30)
            wp.config.mode = "release"
            if os.environ.get("UNIPIXIE_WARP_VERIFY"):
                wp.config.verify_fp = True
            if quiet and not _cuda_driver_present():
                with _stderr_silenced():  # Warp's C code warns on stderr when there is no CUDA driver
                    wp.init()
            else:
                wp.init()
            _initialised = True
        return wp


def _cuda_driver_present() -> bool:
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None or os.path.exists("/usr/lib/x86_64-linux-gnu/libcuda.so.1")


class _stderr_silenced:
    """Redirect the process's file descriptor 2 to /dev/null for the duration of a block."""

    def __enter__(self):
        import sys

        try:
            sys.stderr.flush()
            self._saved = os.dup(2)
            self._null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(self._null, 2)
        except OSError:
            self._saved = None
        return self

    def __exit__(self, *exc):
        if self._saved is not None:
            os.dup2(self._saved, 2)
            os.close(self._saved)
            os.close(self._null)
        return False


def available_devices() -> list[str]:
    """Names of the Warp devices on this machine, e.g. ``["cpu", "cuda:0"]``."""
    wp = init_warp()
    return [str(d) for d in wp.get_devices()]


def cuda_available() -> bool:
    wp = init_warp()
    return wp.get_cuda_device_count() > 0


def resolve_device(device: str | None = "cpu") -> str:
    """Validate a device name (``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``) and return Warp's name for it.

    ``"auto"`` picks the first CUDA device when there is one, else the CPU.
    A CUDA device on a machine without one is a :class:`UserError`.
    """
    wp = init_warp()
    name = (device or "cpu").strip().lower()
    if name == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    if name == "cpu":
        return "cpu"
    if name.startswith("cuda"):
        n = wp.get_cuda_device_count()
        if n == 0:
            raise UserError(f"device {device!r} requested but Warp sees no CUDA device on this machine; use --device cpu")
        idx = 0
        if ":" in name:
            try:
                idx = int(name.split(":", 1)[1])
            except ValueError:
                raise UserError(f"bad device name {device!r}; expected cpu, cuda or cuda:N") from None
        if not 0 <= idx < n:
            raise UserError(f"device {device!r} does not exist; this machine has {n} CUDA device(s)")
        return f"cuda:{idx}"
    raise UserError(f"bad device name {device!r}; expected cpu, cuda, cuda:N or auto")


def device_description(device: str) -> str:
    """How the device reports itself (GPU name, or the CPU model with its core count)."""
    wp = init_warp()
    d = wp.get_device(device)
    if d.is_cuda:
        return str(d.name)
    return cpu_description()


def cpu_description(fallback: str = "CPU") -> str:
    """The CPU model that /proc/cpuinfo names (``fallback`` where it names none) with the core count,
    e.g. ``"AMD EPYC (2 cores)"``.  Needs no Warp (the torch-only benchmarks use it too)."""
    model = ""
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    return f"{model or fallback} ({os.cpu_count()} cores)"
