"""What the fault-injection tests (tests/test_fault_*.py) share: a small falling-cube measurement, a full disk
simulated at write time, the leftovers of an interrupted write."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np

from unipixie.core import atomic_io
from unipixie.core.measurement import Measurement, MeasuredMaterial
from unipixie.solvers.scenario import Scenario


REPO_ROOT = Path(__file__).resolve().parents[1]


def _leftovers(folder: Path) -> list[str]:
    """Temporary or lock files an interrupted write left behind."""
    return [p.name for p in folder.iterdir() if atomic_io.is_temporary(p.name) or ".tmp" in p.name]


# --------------------------------------------------------------------------- a small measurement
CUBE = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (0.05, 0.15)], dtype=np.float64)

CUBE_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def _falling_cube(frames: int = 20, fps: float = 50.0, **scenario) -> Measurement:
    """A cube falling freely for ``frames`` instants (z up, metres), the jelly material stated."""
    t = np.arange(frames) / fps
    pos = CUBE[None] + np.array([0.0, 0.0, 1.0])[None, None] * (-0.5 * 9.81 * t ** 2)[:, None, None]
    pos = pos + np.random.default_rng(0).normal(0.0, 1e-4, pos.shape)
    sc = Scenario(**{"ground_height": -1.0, **scenario})
    return Measurement(positions=pos, times=t, scenario=sc, rest_positions=CUBE.copy(), faces=CUBE_FACES,
                       material=MeasuredMaterial(2e5, 0.3, 1000.0))


# --------------------------------------------------------------------------- full disk (simulated at write time)
def _enospc_after(nbytes: int):
    """A ``numpy.lib.format.write_array`` stand-in that writes ``nbytes`` of an archive member and then fails as a
    full disk does."""

    def fake(fp, array, *args, **kwargs):
        fp.write(b"\x93NUMPY" + b"\0" * nbytes)
        raise OSError(errno.ENOSPC, "No space left on device")

    return fake
