"""Undoing a bake: :func:`clear_bake` removes exactly what a bake added, as its record (a JSON ID property
``unipixie_bake`` on the object, :func:`bake_record`) lists it — shape keys, actions, modifiers, vertex groups,
armature and particle objects, node groups, PC2 files and folders.  Removed PC2 files go to a session trash that
Ctrl-Z can bring back (:func:`restore_trashed_files`; :func:`empty_trash` when a new file is loaded).

Uses bpy, :mod:`unipixie.core.bake` (the record), :mod:`unipixie.core.paths` and :mod:`.options`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Optional

import bpy

from ...bake import BAKE_RECORD_KEY, parse_record
from ...errors import UserError
from .options import object_settings


# =========================================================================== removal
# PC2 files removed by clear_bake go to a session trash so that Ctrl-Z (which restores the Mesh Cache
# modifier) can bring them back: the add-on calls restore_trashed_files() after undo/redo.
_TRASHED: dict = {}


def _trash(path: Path) -> None:
    from ...paths import cache_dir

    folder = cache_dir("bake_trash")
    target = folder / f"{len(_TRASHED):06d}_{os.getpid()}_{path.name}"
    key = os.path.normpath(str(path.resolve()))
    _move(path, target)  # a rename when on the same file system
    _TRASHED[key] = target


def _move(src: Path, dst: Path) -> None:
    import shutil

    shutil.move(str(src), str(dst))


def restore_trashed_files() -> int:
    """Put back PC2 files that a cleared bake removed if a Mesh Cache modifier refers to them again
    (after Ctrl-Z).  Returns how many were restored."""
    restored = 0
    for obj in bpy.data.objects:
        for m in obj.modifiers:
            if m.type == "MESH_CACHE" and m.filepath:
                path = os.path.normpath(bpy.path.abspath(m.filepath))
                src = _TRASHED.get(path)
                if src is not None and not os.path.exists(path) and Path(src).is_file():
                    os.makedirs(os.path.dirname(path), exist_ok=True)
                    _move(Path(src), Path(path))
                    del _TRASHED[path]
                    restored += 1
    return restored


def empty_trash() -> None:
    """Delete the PC2 files kept for undo (a new file was loaded: the undo history is gone)."""
    for src in list(_TRASHED.values()):
        with contextlib.suppress(OSError):
            Path(src).unlink()
    _TRASHED.clear()


def remove_recorded(obj, rec: dict, keep_for_undo: bool = False) -> None:
    """Remove everything listed in a bake record (tolerates parts already gone).

    ``keep_for_undo``: PC2 files go to a session trash (see :func:`restore_trashed_files`) instead of
    being deleted."""
    data = bpy.data
    # actions first (they reference the ids)
    for name in rec.get("actions", []):
        act = data.actions.get(name)
        if act is not None:
            data.actions.remove(act)
    if obj is not None:
        if rec.get("created_key") and obj.data.shape_keys is not None:
            obj.shape_key_clear()
        for name in rec.get("modifiers", []):
            m = obj.modifiers.get(name)
            if m is not None:
                obj.modifiers.remove(m)
        for name in rec.get("vertex_groups", []):
            g = obj.vertex_groups.get(name)
            if g is not None:
                obj.vertex_groups.remove(g)
    for name in rec.get("objects", []):
        o = data.objects.get(name)
        if o is not None:
            if o.type == "MESH" and o.data is not None and o.data.shape_keys is not None:
                o.shape_key_clear()
            data.objects.remove(o)
    for name in rec.get("meshes", []):
        m = data.meshes.get(name)
        if m is not None and m.users == 0:
            data.meshes.remove(m)
    for name in rec.get("armatures", []):
        a = data.armatures.get(name)
        if a is not None and a.users == 0:
            data.armatures.remove(a)
    for name in rec.get("node_groups", []):
        g = data.node_groups.get(name)
        if g is not None and g.users == 0:
            data.node_groups.remove(g)
    for path in rec.get("files", []):
        p = Path(path)
        if p.suffix == ".pc2" and p.is_file():
            if keep_for_undo:
                _trash(p)
            else:
                p.unlink()
    for folder in rec.get("folders", []):
        with contextlib.suppress(OSError):
            os.rmdir(folder)  # only when empty


def bake_record(obj) -> Optional[dict]:
    """The record of the bake on ``obj`` (what it added), or ``None`` if it has none."""
    if obj is None:
        return None
    return parse_record(obj.get(BAKE_RECORD_KEY))


def clear_bake(obj) -> dict:
    """Remove everything the bake on ``obj`` added: shape keys, their action, modifiers, vertex groups,
    the armature or particle objects with their data and actions, and the PC2 files it wrote.

    The original mesh data is untouched.  Returns the record that was cleared; an object without a
    bake is a :class:`UserError`.
    """
    if obj is None:
        raise UserError("no object selected")
    rec = bake_record(obj)
    if rec is None:
        raise UserError(f"object '{obj.name}' has no UniPixie bake to clear")
    if obj.library is not None:
        raise UserError(f"'{obj.name}' is linked from another file and cannot be changed")
    # the Mesh Cache path may have been made relative since the bake: resolve it from the modifier
    files = set(rec.get("files", []))
    for name in rec.get("modifiers", []):
        m = obj.modifiers.get(name)
        if m is not None and m.type == "MESH_CACHE" and m.filepath:
            files.add(os.path.normpath(bpy.path.abspath(m.filepath)))
    for oname in rec.get("objects", []):
        o = bpy.data.objects.get(oname)
        if o is not None:
            for m in o.modifiers:
                if m.type == "MESH_CACHE" and m.filepath:
                    files.add(os.path.normpath(bpy.path.abspath(m.filepath)))
    rec = {**rec, "files": sorted(files)}
    remove_recorded(obj, rec, keep_for_undo=True)
    if BAKE_RECORD_KEY in obj:
        del obj[BAKE_RECORD_KEY]
    s = object_settings(obj)
    if s is not None:
        s.status = ""
    return rec
