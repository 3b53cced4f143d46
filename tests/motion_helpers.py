"""What tests of bodies' motions share: how far a body has turned, and a made-up motion in the LBS solver's form."""

from __future__ import annotations

import numpy as np


def rotation_degrees(rest: np.ndarray, x: np.ndarray) -> float:
    """The angle (degrees, 0–180) of the best-fit rotation taking ``rest`` (n, 3) m to ``x`` (n, 3) m."""
    U, _, Vt = np.linalg.svd((rest - rest.mean(0)).T @ (x - x.mean(0)))
    d = np.sign(np.linalg.det(U @ Vt))
    R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def lbs_motion(rest: np.ndarray, T: int = 5, H: int = 3, seed: int = 0, shear: float = 0.1,
               handle_scale: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A motion in the LBS solver's form: x = A[X;1] + Σ_h w_h D_h [X;1] (weights may be negative).

    rest: (N, 3) rest positions, m.  Returns ``(W, HT, pos)``: W (N, H + 1) weights (the last column, all ones, the
    constant handle's), HT (T, H + 1, 3, 4) handle transforms (the constant handle A last: turning, shearing by
    ``shear``·t and moving; the others D_h random, growing as ``handle_scale``·t) and pos (T, N, 3) the positions, m.
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    W = np.concatenate([rng.normal(0.3, 0.5, (len(rest), H)), np.ones((len(rest), 1))], axis=1)
    HT = np.zeros((T, H + 1, 3, 4))
    c = rest.mean(0)
    for t in range(T):
        R = Rotation.from_rotvec([0.2 * t, -0.1 * t, 0.05 * t]).as_matrix()
        HT[t, H, :, :3] = R @ np.array([[1, shear * t, 0], [0, 1, 0], [0, 0, 1]])
        HT[t, H, :, 3] = c - HT[t, H, :, :3] @ c + [0.1 * t, 0.0, -0.05 * t * t]
        HT[t, :H] = handle_scale * t * rng.normal(size=(H, 3, 4))
    X1 = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    pos = np.einsum("thij,nj->tnhi", HT, X1)
    pos = pos[:, :, H] + np.einsum("nh,tnhi->tni", W[:, :H], pos[:, :, :H])
    return W, HT, pos
