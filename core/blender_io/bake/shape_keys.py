"""Writing a motion as shape keys: one shape key per frame, keyed 0 → 1 → 0 around its frame, written in chunks
with bulk ``foreach_set`` calls (:func:`write_shape_keys`).

Uses bpy and :mod:`.writing`.
"""

from __future__ import annotations

from typing import Iterator

import bpy
import numpy as np

from ...errors import UserError
from .writing import PREFIX, WriteRecord, assign_action, layered_action, set_keys


def write_shape_keys(obj, local: np.ndarray, frames: np.ndarray, interpolation: str, record: WriteRecord,
                     chunk: int = 32) -> Iterator[float]:
    """One shape key per frame (keyed 0 → 1 → 0 around its frame), yielding the fraction written.

    local: (T, N, 3) float32 object-local positions; frames: (T,) scene frames.  At every integer
    frame exactly one key has value 1, so the evaluated mesh is that frame's positions; the last key
    stays at 1 after the end (the final state is held) and before the start the first key (= rest).
    """
    T, N, _ = local.shape
    if obj.data.shape_keys is not None:
        raise UserError(f"object '{obj.name}' already has shape keys; use the Mesh Cache output")
    basis = obj.shape_key_add(name=f"{PREFIX} Basis", from_mix=False)
    record.created_key = True
    record.shape_keys.append(basis.name)
    key = obj.data.shape_keys
    key.use_relative = True
    names = []
    for t0 in range(0, T, chunk):
        for t in range(t0, min(T, t0 + chunk)):
            kb = obj.shape_key_add(name=f"{PREFIX} {int(frames[t]):04d}", from_mix=False)
            kb.data.foreach_set("co", local[t].ravel())
            kb.value = 0.0
            kb.slider_min = 0.0
            names.append(kb.name)
            record.shape_keys.append(kb.name)
        yield 0.9 * min(T, t0 + chunk) / T
    action, slot, bag = layered_action(f"{PREFIX} {obj.name} shape keys", "KEY", key.name)
    record.actions.append(action.name)
    f = frames.astype(np.float64)
    for t, name in enumerate(names):
        fc = bag.fcurves.new(f'key_blocks["{bpy.utils.escape_identifier(name)}"].value')
        lo, hi = max(t - 1, 0), min(t + 1, T - 1)
        kf = f[lo:hi + 1]
        vals = (np.arange(lo, hi + 1) == t).astype(np.float32)  # the last key holds 1 after the end
        set_keys(fc, kf, vals, interpolation)
    assign_action(key, action, slot)
    yield 1.0
