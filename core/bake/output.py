"""How a bake's motion is stored: the output modes (shape keys, a Mesh Cache on a PC2 file, an armature for
LBS), the keyframe interpolations, the ``auto`` rule that picks a mode per solver and size
(:func:`choose_output`) and the trajectory in the object's local space (:func:`trajectory_to_local`).

Owns the output constants the panel, the command line and the writers read.  Uses :mod:`.body` and
:mod:`unipixie.core.errors` only; the Blender writers are in :mod:`unipixie.core.blender_io.bake`.
"""

from __future__ import annotations

import numpy as np

from ..errors import UserError
from .body import BakeObject


OUTPUT_MODES = ("auto", "shape_keys", "mesh_cache", "armature")
"""How the motion is stored: ``auto`` picks per solver and size (see :func:`choose_output`)."""
OUTPUT_LABELS = {
    "auto": ("Automatic", "Armature for LBS when exact enough, else shape keys; a Mesh Cache (PC2) for large bakes"),
    "shape_keys": ("Shape keys", "One keyframed shape key per frame (stored in the .blend)"),
    "mesh_cache": ("Mesh Cache (PC2)", "A Mesh Cache modifier reading a PC2 file written next to the .blend"),
    "armature": ("Armature (LBS)", "One bone per LBS handle, vertex groups and an Armature modifier"),
}
INTERPOLATIONS = ("LINEAR", "CONSTANT")
"""Keyframe interpolation between frames; both give the exact trajectory at integer frames."""

SHAPE_KEY_VERTEX_FRAME_LIMIT = 2_000_000
"""``auto`` switches from shape keys to a Mesh Cache above this many vertices × frames (24 MB of keys)."""
MESH_CACHE_FRAME_LIMIT = 1000
"""``auto`` also uses a Mesh Cache above this many frames (a thousand shape keys is unwieldy in the UI)."""
ARMATURE_TOLERANCE = 1e-4
"""Default largest allowed armature error, as a fraction of the object's size (0.1 mm for a 1 m object)."""


def choose_output(solver: str, requested: str, n_vertices: int, n_frames: int, *, has_other_shape_keys: bool = False,
                  mesh_shared: bool = False) -> tuple[str, list[str]]:
    """Pick how to store the motion; returns ``(mode, notes)``.

    ``auto``: LBS → ``armature`` (the writer falls back to shape keys/Mesh Cache when the handle
    transforms are not representable); otherwise shape keys unless the bake is large
    (> :data:`SHAPE_KEY_VERTEX_FRAME_LIMIT` vertex-frames or > :data:`MESH_CACHE_FRAME_LIMIT` frames),
    the mesh already has shape keys of its own, or the mesh data is shared by several objects —
    those use a Mesh Cache modifier, which leaves the mesh data untouched.
    """
    notes: list[str] = []
    if requested not in OUTPUT_MODES:
        raise UserError(f"unknown output {requested!r}; choose one of {', '.join(OUTPUT_MODES)}")
    if requested == "armature" and solver != "lbs":
        raise UserError(f"an armature bake needs the LBS solver, not {solver}")
    if requested == "shape_keys":
        if has_other_shape_keys:
            raise UserError("the mesh already has shape keys of its own; a shape-key bake would mix with them — "
                            "choose the Mesh Cache output (or remove the mesh's shape keys)")
        if mesh_shared:
            raise UserError("the mesh data is shared by several objects; shape keys would move all of them — "
                            "choose the Mesh Cache output (or make the mesh single-user)")
        return "shape_keys", notes
    if requested in ("mesh_cache", "armature"):
        return requested, notes
    if solver == "lbs":
        return "armature", notes
    return vertex_output(n_vertices, n_frames, has_other_shape_keys, mesh_shared, notes), notes


def vertex_output(n_vertices: int, n_frames: int, has_other_shape_keys: bool, mesh_shared: bool,
                  notes: list[str]) -> str:
    """Shape keys or Mesh Cache for per-vertex motion (the ``auto`` rule of :func:`choose_output`)."""
    if has_other_shape_keys:
        notes.append("the mesh has shape keys of its own: the motion is stored in a Mesh Cache (PC2) instead")
        return "mesh_cache"
    if mesh_shared:
        notes.append("the mesh data is shared by several objects: the motion is stored in a Mesh Cache (PC2) instead")
        return "mesh_cache"
    if n_vertices * n_frames > SHAPE_KEY_VERTEX_FRAME_LIMIT or n_frames > MESH_CACHE_FRAME_LIMIT:
        notes.append(f"{n_vertices} vertices × {n_frames} frames is a large bake: stored in a Mesh Cache (PC2)")
        return "mesh_cache"
    return "shape_keys"


def trajectory_to_local(obj: BakeObject, positions: np.ndarray) -> np.ndarray:
    """(T, N, 3) world metres → (T, N, 3) float32 object-local Blender units."""
    return obj.to_local(np.asarray(positions, dtype=np.float64)).astype(np.float32)
