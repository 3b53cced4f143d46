"""Writing a motion as a Mesh Cache: a PC2 file (written atomically, :mod:`unipixie.core.bake.pc2`) in the bake's
cache folder (:func:`cache_folder`) and a Mesh Cache modifier first in the stack reading it
(:func:`write_mesh_cache`).

Uses bpy, :mod:`unipixie.core.bake` and :mod:`.writing`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import bpy
import numpy as np

from ...bake import BakeOptions, safe_name, write_pc2
from .writing import PREFIX, WriteRecord, move_first, unique_name


def cache_folder(obj_name: str, options: BakeOptions, record: WriteRecord) -> tuple[Path, list[str]]:
    """Folder for PC2 files: ``options.cache_dir``, else ``<blend>_unipixie/`` next to the saved .blend,
    else the UniPixie cache (with a warning to save and re-bake)."""
    notes = []
    if options.cache_dir:
        folder = Path(options.cache_dir)
    elif bpy.data.filepath:
        blend = Path(bpy.data.filepath)
        folder = blend.parent / f"{blend.stem}_unipixie"
    else:
        from ...paths import cache_dir

        folder = cache_dir("bakes")
        notes.append(f"the .blend is not saved: the PC2 cache for '{obj_name}' is in {folder}; save the .blend and "
                     "re-bake to keep the cache next to it")
    if not folder.exists():
        folder.mkdir(parents=True)
        record.folders.append(str(folder))
    return folder, notes


def _pc2_path(folder: Path, name: str, suffix: str = "") -> Path:
    stem = safe_name(name) + suffix
    path = folder / f"{stem}.pc2"
    k = 1
    while path.exists():
        path = folder / f"{stem}.{k:03d}.pc2"
        k += 1
    return path


def write_mesh_cache(obj, local: np.ndarray, frames: np.ndarray, interpolation: str, folder: Path,
                     record: WriteRecord, suffix: str = "") -> Iterator[float]:
    """A PC2 file (written atomically) and a Mesh Cache modifier first in the stack reading it."""
    path = _pc2_path(folder, obj.name, suffix)
    write_pc2(path, local, start_frame=float(frames[0]), sample_rate=1.0)
    record.files.append(str(path))
    yield 0.8
    mod = obj.modifiers.new(name=unique_name({m.name for m in obj.modifiers}, f"{PREFIX} Mesh Cache"),
                            type="MESH_CACHE")
    record.modifiers.append(mod.name)
    mod.cache_format = "PC2"
    # relative to the .blend where it is saved (Blender remaps relative paths on "Save As")
    mod.filepath = bpy.path.relpath(str(path)) if bpy.data.filepath else str(path)
    mod.frame_start = float(frames[0])
    mod.frame_scale = 1.0
    mod.play_mode = "SCENE"
    mod.time_mode = "FRAME"
    mod.deform_mode = "OVERWRITE"
    mod.interpolation = "LINEAR" if interpolation == "LINEAR" else "NONE"
    mod.forward_axis = "POS_Y"
    mod.up_axis = "POS_Z"
    move_first(obj, mod)
    yield 1.0
