"""Timing the writers for ``unipixie bench bake``: :func:`time_writes` writes one simulation as each output mode in a
fresh empty scene and reports the median wall time.

Uses bpy, :mod:`unipixie.core.bake`, :mod:`.result` and :mod:`.removal`.
"""

from __future__ import annotations

import time
from typing import Sequence

import bpy

from ...bake import BakeObject, BakeOptions, SimulationResult
from .removal import clear_bake, empty_trash
from .result import write_result


def time_writes(bo: BakeObject, result: SimulationResult, options: BakeOptions, modes: Sequence[str],
                repeats: int = 3) -> dict:
    """Median wall time (s) of writing ``result`` as each output mode, in a fresh empty scene (benchmark).

    Returns ``{mode: (seconds, runs)}``; a mode the writer had to replace (an LBS motion that bones
    cannot represent) is left out.  Everything written is cleared again.
    """
    import statistics
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory(prefix="unipixie-bench-bake-") as tmp:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        me = bpy.data.meshes.new(bo.name)
        me.from_pydata(bo.rest_local.tolist(), [], bo.triangles.tolist())
        me.update()
        obj = bpy.data.objects.new(bo.name, me)
        bpy.context.scene.collection.objects.link(obj)
        for mode in modes:
            times = []
            for _ in range(repeats):
                opts = BakeOptions(**{**options.__dict__, "output": mode, "cache_dir": tmp})
                t0 = time.perf_counter()
                gen = write_result(obj, bo, result, opts)
                while True:
                    try:
                        next(gen)
                    except StopIteration as stop:
                        rep = stop.value
                        break
                times.append(time.perf_counter() - t0)
                clear_bake(obj)
                if rep.mode != mode:
                    times = []
                    break
            if times:
                out[mode] = (statistics.median(times), len(times))
        empty_trash()
    return out
