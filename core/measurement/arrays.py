"""Checks and repairs of a measurement's arrays: coordinates, numbers, faces, rest positions.

Owns the error helper every reader of a measurement uses (:func:`fail`, a :class:`UserError` that names the
source), the coordinate limit (:data:`COORDINATE_LIMIT`), the check of a surface (``faces``: closed and
consistently oriented) and the rebuilding of rest positions for points unobserved at the first instant.  Pure
numpy on plain arrays: it may use only :mod:`unipixie.core.errors`, never the other modules of this package.
"""

from __future__ import annotations

import numpy as np

from ..errors import UserError


def fail(source: str, msg: str) -> UserError:
    return UserError(f"{source}: {msg}" if source else msg)


COORDINATE_LIMIT = 1e10
"""Metres: no coordinate of a tracked point may be farther from the origin than this (about 70 times the distance
to the Sun).  Beyond it the value is a sentinel or a unit mistake, and the arithmetic of differences and squares
(noise estimate, errors) loses every digit of the motion or overflows."""


def check_magnitude(values: np.ndarray, key: str, src: str) -> None:
    with np.errstate(invalid="ignore"):
        biggest = float(np.nanmax(np.abs(values)))
    if biggest > COORDINATE_LIMIT:
        raise fail(src, f"key '{key}' holds a coordinate of {biggest:.3g} m, beyond {COORDINATE_LIMIT:.0e} m from the "
                         "origin: positions are metres — this is a sentinel value (mark unobserved samples with NaN, "
                         "an empty CSV cell) or a unit mistake")


def float_array(value, key: str, src: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise fail(src, f"key '{key}' must hold numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64)


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t with R a + t ≈ b (Kabsch; translation only for < 3 points)."""
    ca, cb = a.mean(0), b.mean(0)
    if len(a) < 3:
        return np.eye(3), cb - ca
    H = (a - ca).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def reconstruct_rest(pos: np.ndarray) -> np.ndarray:
    """Rest positions = positions[0], with points unobserved there carried back from their first
    observation by the rigid motion of the points observed at both instants."""
    rest = pos[0].copy()
    obs = ~np.isnan(pos[..., 0])
    for i in np.nonzero(~obs[0])[0]:
        f = int(np.argmax(obs[:, i]))
        both = obs[0] & obs[f]
        if not np.any(both):
            rest[i] = pos[f, i]
            continue
        R, t = _rigid_fit(pos[f, both], pos[0, both])  # maps instant f back onto instant 0
        rest[i] = R @ pos[f, i] + t
    return rest


def check_faces(faces, n_points: int, src: str, warnings: list) -> np.ndarray:
    arr = np.asarray(faces)
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind == "f" and arr.size and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            arr = arr.astype(np.int64)
        else:
            raise fail(src, f"key 'faces' must hold integer vertex indices, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise fail(src, f"key 'faces' must have shape (F, 3) with F > 0, got {arr.shape}")
    if arr.min() < 0 or arr.max() >= n_points:
        raise fail(src, f"key 'faces' refers to vertex {int(arr.max()) if arr.max() >= n_points else int(arr.min())}, "
                         f"but there are {n_points} tracked points (indices 0..{n_points - 1})")
    if np.any((arr[:, 0] == arr[:, 1]) | (arr[:, 1] == arr[:, 2]) | (arr[:, 0] == arr[:, 2])):
        raise fail(src, "key 'faces' has triangles that repeat a vertex")
    # closed: every undirected edge used by exactly two faces, once in each direction (consistent orientation)
    directed = np.concatenate([arr[:, [0, 1]], arr[:, [1, 2]], arr[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    if np.any(counts != 2):
        bad = int(np.sum(counts != 2))
        raise fail(src, f"key 'faces' is not a closed surface ({bad} edge(s) not shared by exactly two triangles)")
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    if np.any(dcounts != 1):
        raise fail(src, "key 'faces' is not consistently oriented (an edge runs the same way in two triangles)")
    return arr


