"""The error on the mesh with the time slider: each tracked point coloured by its error at the current frame.

:func:`write_error_animation` keyframes, on every vertex of a mesh whose vertices are the tracked points (the
measurement's point cloud, or the object the measurement was read from), the distance between the simulated and
the measured point at each measured instant:

* ``unipixie_error_now`` — a colour attribute (viridis, 0 → dark blue … ``vmax`` → yellow, above it yellow; grey
  where the point was not observed at that instant), and
* ``unipixie_error_now_m`` — the distance in metres (−1 where not observed),

with constant interpolation: between two instants a point shows the error of the last instant (a colour is never
interpolated from grey or across an impact).  The keys sit on the mesh datablock's action (a new one named
``UniPixie error <mesh>``, or the mesh's own action where it has one, whose other curves are left alone), so they play
in the viewport, in renders and in saved files without the add-on.  :func:`remove_error_animation` takes them (and the
two attributes) away again.  Instants map to frames as the measurement's point cloud does: ``frame_start`` (the
scene's start by default) + (t − t₀) × fps.

Cost (this CPU, bpy 5.0.1): four curves a vertex, a key per instant each.  125 points × 101 instants: 0.19 s to write,
1.1 ms a frame to play; 3000 points × 300 instants (3.6 M keys): 2.7 s, +296 MB, 51 ms a frame.  Above
:data:`MAX_KEYS` keys the instants are thinned evenly (the last always kept) and the result says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import bpy
import numpy as np

from ..errors import UserError
from .bake.writing import PREFIX, assign_action, layered_action, set_keys
from .bake import scene_fps
from .measure import error_colours, remove_attributes

ERROR_NOW_COLOR_ATTRIBUTE = "unipixie_error_now"
ERROR_NOW_VALUE_ATTRIBUTE = "unipixie_error_now_m"
NOT_OBSERVED_VALUE = -1.0
"""``unipixie_error_now_m`` at an instant where the point was not observed (a distance is never negative)."""
SCALE_PROPERTY = "unipixie_error_now_scale_m"
"""Custom property on the mesh: the error (m) coloured yellow (the top of the colour scale)."""
OWN_ACTION_PROPERTY = "unipixie_error_action"
"""Custom property on an action this module created (removed with its last curve)."""
MAX_KEYS = 2_000_000
"""Keys written at most (four curves a vertex, one key per kept instant each): about 170 MB and 30 ms a frame."""
SCALE_PERCENTILE = 99.0
"""Default top of the colour scale: this percentile of the observed distances (one wild sample does not darken
every other colour)."""
_CHANNELS = 3  # red, green, blue (alpha stays 1)


@dataclass
class ErrorAnimation:
    """What :func:`write_error_animation` wrote.

    instants: measured instants given; keyed: instants keyed (every ``stride``-th, the last always); vmax: m, the
    error shown yellow; first_frame / last_frame: scene frames of the first and last key (float)."""

    instants: int
    keyed: int
    stride: int
    vmax: float
    first_frame: float
    last_frame: float

    def describe(self) -> str:
        thinned = (f", one instant in {self.stride} of {self.instants} (the key limit)" if self.stride > 1 else "")
        return (f"error at each frame on the points: 0 → {1e3 * self.vmax:.3g} mm (yellow), frames "
                f"{self.first_frame:g}–{self.last_frame:g}{thinned}")


def _paths(n: int):
    """(data path, index) of every curve this module writes on a mesh of ``n`` vertices."""
    for i in range(n):
        for ch in range(_CHANNELS):
            yield f'attributes["{ERROR_NOW_COLOR_ATTRIBUTE}"].data[{i}].color', ch
        yield f'attributes["{ERROR_NOW_VALUE_ATTRIBUTE}"].data[{i}].value', 0


def _ours(data_path: str) -> bool:
    return data_path.startswith((f'attributes["{ERROR_NOW_COLOR_ATTRIBUTE}"]',
                                 f'attributes["{ERROR_NOW_VALUE_ATTRIBUTE}"]'))


def _channelbag(me, ensure: bool):
    """The channel bag of the mesh's assigned action slot (None when there is none and ``ensure`` is False)."""
    from bpy_extras import anim_utils

    ad = me.animation_data
    if ad is None or ad.action is None:
        if not ensure:
            return None
        action, slot, bag = layered_action(f"{PREFIX} error {me.name}", "MESH", me.name)
        action[OWN_ACTION_PROPERTY] = True
        assign_action(me, action, slot)
        return bag
    if ad.action_slot is None:
        if not ensure:
            return None
        ad.action_slot = ad.action.slots.new(id_type="MESH", name=me.name)
    if ensure:
        return anim_utils.action_ensure_channelbag_for_slot(ad.action, ad.action_slot)
    return anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)


def remove_error_animation(obj) -> int:
    """Remove the per-frame error of :func:`write_error_animation` from ``obj``'s mesh: its curves (an action this
    module created goes with its last curve; any other curve is kept) and the two attributes.  Returns the number of
    curves removed."""
    if obj is None or obj.type != "MESH":
        raise UserError("the error can only be removed from a mesh object")
    me = obj.data
    removed = 0
    bag = _channelbag(me, ensure=False)
    if bag is not None:
        for fc in [fc for fc in bag.fcurves if _ours(fc.data_path)]:
            bag.fcurves.remove(fc)
            removed += 1
        action = me.animation_data.action
        if action.get(OWN_ACTION_PROPERTY) and not any(len(b.fcurves) for layer in action.layers
                                                       for strip in layer.strips for b in strip.channelbags):
            me.animation_data.action = None
            bpy.data.actions.remove(action)
    remove_attributes(me, (ERROR_NOW_COLOR_ATTRIBUTE, ERROR_NOW_VALUE_ATTRIBUTE))
    if SCALE_PROPERTY in me:
        del me[SCALE_PROPERTY]
    me.update()
    return removed


def write_error_animation(obj, distances: np.ndarray, times: np.ndarray, *, vmax: Optional[float] = None,
                          scene=None, frame_start: Optional[float] = None,
                          max_keys: int = MAX_KEYS) -> ErrorAnimation:
    """Key the error of every tracked point at every measured instant onto ``obj``'s vertices (module docstring).

    distances: (T, N) metres, simulated − measured point distance, NaN where not observed (a
    :class:`~unipixie.core.diagnosis.compare.Comparison`'s ``distances``); times: (T,) s, increasing; N must be the
    mesh's vertex count.  vmax: m, the error shown yellow (default the 99th percentile of the observed distances).
    Replaces an earlier per-frame error on the mesh; makes its colour the active one (Solid shading, colour
    "Attribute", shows it).
    """
    if obj is None or obj.type != "MESH":
        raise UserError("the error can only be written onto a mesh object")
    d = np.asarray(distances, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    me = obj.data
    if d.ndim != 2 or d.shape[0] != len(t):
        raise UserError(f"the per-frame error must be (instants, points) = ({len(t)}, N); got {d.shape}")
    T, N = d.shape
    if len(me.vertices) != N:
        raise UserError(f"object '{obj.name}' has {len(me.vertices)} vertices but the error has {N} points; "
                        "pick the object the measurement was made from (or its point cloud)")
    if T == 0 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise UserError("the instants of the per-frame error must be finite and strictly increasing")
    if np.any(d[np.isfinite(d)] < 0):
        raise UserError("the per-frame error has negative distances")
    observed = np.isfinite(d)
    if vmax is None:
        vmax = float(np.percentile(d[observed], SCALE_PERCENTILE)) if observed.any() else 1.0
    if not (math.isfinite(vmax) and vmax > 0):
        vmax = 1.0
    scene = scene or bpy.context.scene
    f0 = float(scene.frame_start if frame_start is None else frame_start)
    frames = f0 + (t - t[0]) * scene_fps(scene)
    curves = N * (_CHANNELS + 1)
    if 2 * curves > max_keys:
        raise UserError(f"object '{obj.name}' has {N} vertices: keying their error would take more than {max_keys} "
                        "keys even at two instants; colour by the error over the run instead")
    stride = max(1, math.ceil(T * curves / max_keys))
    while True:
        keep = np.unique(np.r_[np.arange(0, T, stride), T - 1])  # every stride-th instant and the last
        if len(keep) * curves <= max_keys:
            break
        stride += 1
    remove_error_animation(obj)
    colours = error_colours(d[keep].reshape(-1), vmax).reshape(len(keep), N, 4)
    values = np.where(observed[keep], d[keep], NOT_OBSERVED_VALUE).astype(np.float32)
    col = me.color_attributes.new(ERROR_NOW_COLOR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    col.data.foreach_set("color", colours[0].ravel())
    val = me.attributes.new(ERROR_NOW_VALUE_ATTRIBUTE, "FLOAT", "POINT")
    val.data.foreach_set("value", values[0])
    bag = _channelbag(me, ensure=True)
    key_frames = frames[keep].astype(np.float32)
    for k, (path, index) in enumerate(_paths(N)):
        i, slot = divmod(k, _CHANNELS + 1)
        series = colours[:, i, slot] if slot < _CHANNELS else values[:, i]
        set_keys(bag.fcurves.new(path, index=index), key_frames, series, "CONSTANT")
    me[SCALE_PROPERTY] = float(vmax)
    me.color_attributes.active_color = me.color_attributes[ERROR_NOW_COLOR_ATTRIBUTE]
    me.update()
    return ErrorAnimation(instants=T, keyed=len(keep), stride=stride, vmax=float(vmax),
                          first_frame=float(key_frames[0]), last_frame=float(key_frames[-1]))
