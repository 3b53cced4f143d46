"""What tests that follow a body's rigid motion share: how far it has turned."""

from __future__ import annotations

import numpy as np


def rotation_degrees(rest: np.ndarray, x: np.ndarray) -> float:
    """The angle (degrees, 0–180) of the best-fit rotation taking ``rest`` (n, 3) m to ``x`` (n, 3) m."""
    U, _, Vt = np.linalg.svd((rest - rest.mean(0)).T @ (x - x.mean(0)))
    d = np.sign(np.linalg.det(U @ Vt))
    R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
