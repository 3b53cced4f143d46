"""The whole bake of an object: :func:`bake_steps` reads and checks everything first (bad input changes nothing),
runs the simulation in a worker thread (:func:`unipixie.core.jobs.worker_job`) and writes, as a generator of
``(fraction, status)`` for the add-on's modal operator (closing it cancels and removes anything half-written);
:func:`bake_object` runs it to the end (Python API, command line).

Uses bpy, :mod:`unipixie.core.bake`, :mod:`unipixie.core.jobs` and :mod:`.reading`, :mod:`.options`,
:mod:`.scenario`, :mod:`.removal`, :mod:`.result`.
"""

from __future__ import annotations

from typing import Iterator, Optional

import bpy

from ...bake import BakeOptions, choose_output, simulate
from ...jobs import worker_job
from ...progress import Progress, silent
from .options import object_settings, options_from_settings
from .reading import read_object
from .removal import bake_record
from .result import BakeReport, write_result
from .scenario import scenario_from_scene


def bake_steps(obj, options: Optional[BakeOptions] = None, scenario=None, scene=None,
               wait: float = 0.05) -> Iterator[tuple[float, str]]:
    """The whole bake of ``obj`` as a generator of ``(fraction, status)``; its return value is a :class:`BakeReport`.

    Reads and checks everything first (bad input changes nothing), runs the simulation in a worker
    thread (the caller yields to Blender between polls), then writes.  Closing the generator (Esc)
    cancels the simulation and removes anything written.
    """
    scene = scene or bpy.context.scene
    bo = read_object(obj, scene)
    options = options or options_from_settings(obj, scene)
    scenario = scenario if scenario is not None else scenario_from_scene(obj, scene)
    own_keys = obj.data.shape_keys is not None and bake_record(obj) is None
    choose_output(options.solver, options.output, bo.vertex_count, options.frames.count,
                  has_other_shape_keys=own_keys, mesh_shared=obj.data.users > 1)  # refuse before simulating
    yield 0.0, "starting"
    result = yield from worker_job(lambda progress: simulate(bo, scenario, options, progress),
                                   description=f"{options.solver} bake", idle_status="simulating", span=(0.0, 0.85),
                                   poll_s=wait)
    yield 0.85, "writing"
    gen = write_result(obj, bo, result, options)
    try:
        while True:
            try:
                frac, status = next(gen)
            except StopIteration as stop:
                report = stop.value
                break
            yield 0.85 + 0.15 * frac, status
    finally:
        gen.close()  # on Esc: the writer removes what it wrote
    s = object_settings(obj)
    if s is not None:
        s.status = f"baked: {report.mode.replace('_', ' ')}, frames {report.frames[0]}-{report.frames[1]}"
    return report


def bake_object(obj, options: Optional[BakeOptions] = None, scenario=None, progress: Optional[Progress] = None,
                scene=None) -> BakeReport:
    """Bake ``obj`` to the end (Python API for pipeline scripts).

    options: :class:`~unipixie.core.bake.BakeOptions` (default: the object's panel settings and the
    scene's frame range); scenario: a :class:`~unipixie.solvers.scenario.Scenario` (default: from the
    scene, see :func:`scenario_from_scene`).  ``progress`` receives the fraction and can cancel.
    """
    progress = progress or silent()
    gen = bake_steps(obj, options, scenario, scene)
    last = 0.0
    try:
        while True:
            try:
                frac, status = next(gen)
            except StopIteration as stop:
                return stop.value
            progress.step(max(0.0, frac - last) * progress.total, status)
            last = max(last, frac)
    finally:
        gen.close()
