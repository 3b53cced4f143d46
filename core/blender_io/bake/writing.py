"""What every writer of a bake shares: :class:`WriteRecord` (what a bake created, kept as it is written so that a
failure or Esc can remove it), Blender 5.0 layered actions with bulk keyframes (:func:`layered_action`,
:func:`set_keys`, :func:`assign_action`), unique names with the :data:`PREFIX`, and modifier placement.

Uses bpy and numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy
import numpy as np


PREFIX = "UniPixie"
"""Names of everything a bake adds start with this (shape keys, modifiers, objects, actions)."""
_INTERP_CODE = {"CONSTANT": 0, "LINEAR": 1}


def layered_action(name: str, id_type: str, slot_name: str):
    """A new Blender 5.0 layered action with one slot, one layer and one keyframe strip; returns (action, slot, channelbag)."""
    action = bpy.data.actions.new(name)
    slot = action.slots.new(id_type=id_type, name=slot_name)
    strip = action.layers.new("UniPixie").strips.new(type="KEYFRAME")
    return action, slot, strip.channelbag(slot, ensure=True)


def set_keys(fcurve, frames: np.ndarray, values: np.ndarray, interpolation: str) -> None:
    """Keyframes in bulk: ``keyframe_points.add`` + ``foreach_set`` (no per-keyframe Python)."""
    n = len(frames)
    kp = fcurve.keyframe_points
    kp.add(n)
    co = np.empty(2 * n, dtype=np.float32)
    co[0::2] = frames
    co[1::2] = values
    kp.foreach_set("co", co)
    kp.foreach_set("interpolation", np.full(n, _INTERP_CODE[interpolation], dtype=np.int32))
    fcurve.update()


def assign_action(id_block, action, slot) -> None:
    ad = id_block.animation_data or id_block.animation_data_create()
    ad.action = action
    ad.action_slot = slot


def unique_name(existing, base: str) -> str:
    if base not in existing:
        return base
    k = 1
    while f"{base}.{k:03d}" in existing:
        k += 1
    return f"{base}.{k:03d}"


def move_first(obj, mod) -> None:
    idx = list(obj.modifiers).index(mod)
    if idx:
        obj.modifiers.move(idx, 0)


def collection_of(obj):
    cols = list(obj.users_collection)
    return cols[0] if cols else bpy.context.scene.collection


@dataclass
class WriteRecord:
    """What a bake created (kept as it is written so a failure or Esc can remove it)."""

    obj_name: str
    shape_keys: list = field(default_factory=list)
    created_key: bool = False
    modifiers: list = field(default_factory=list)
    vertex_groups: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    objects: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    armatures: list = field(default_factory=list)
    node_groups: list = field(default_factory=list)
    files: list = field(default_factory=list)
    folders: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)
